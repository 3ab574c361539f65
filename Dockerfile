# learnest image: CPU-only torch, the learnest CLI and its HTTP service (uvicorn, learnest.service.app.factory).
# Build: docker build -t learnest .   Serve: docker run --rm -p 8000:8000 -v learnest-data:/data learnest
# One-off command: docker run --rm -v learnest-data:/data learnest reproduce --task cartpole --seeds 2
FROM python:3.11-slim

WORKDIR /app
# CPU build of torch first, from PyTorch's CPU index, so no CUDA packages are pulled in
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml constraints.txt README.md CHANGELOG.md mkdocs.yml ./
COPY learnest ./learnest
COPY ingest ./ingest
COPY models ./models
COPY estimators ./estimators
COPY workflows ./workflows
COPY service ./service
COPY docs ./docs
# docs: MkDocs, which builds the manual that `learnest serve` shows at /manual
RUN pip install --no-cache-dir -c constraints.txt ".[dask,postgres,docs]"

ENV LEARNEST_HOME=/data
VOLUME /data
EXPOSE 8000
ENTRYPOINT ["learnest"]
# the HTTP service (uvicorn); any other learnest command can be given instead
CMD ["serve", "--host", "0.0.0.0", "--port", "8000"]
