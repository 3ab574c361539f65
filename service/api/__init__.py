"""The HTTP API (FastAPI): `app` (the factory uvicorn runs, the upload size limit), `errors` (one handler per
kind of exception), `deps` (the dependencies routes and web pages share), `schemas` (request and response
models) and `routes/` (one module per resource).

Nothing is imported here, so the web pages can use `deps` and `schemas` without loading the app.
"""
