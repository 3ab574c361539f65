"""Helpers for the service tests: a running app, uploads, jobs, small simulated NanoBench flights.

Flights are small NanoBench CSVs written by the project's simulator (ingest.sim) that pass the quality
checks (11 s, ~6.8 s of flying part), so every test drives the real app, the real adapters and the real
estimators in seconds.
"""
from __future__ import annotations

import atexit
import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from learnest.ingest.sim import Circle, SimulatedFlight, Timing, simulate, write_flight

if TYPE_CHECKING:  # the service stack is imported when a test first uses it, not at collection
    from fastapi.testclient import TestClient

    from learnest.service.config import Settings
    from learnest.service.jobs.executors import LocalPoolExecutor

FAST_METHODS = ["ukf", "knode-ukf"]   # the MHE adds seconds per flight; one test runs it
EPOCHS = 3


# A compact timeline (sit 1 s, take off 1.5 s, hover 0.5 s, circle, hover, land 1.5 s, sit 0.5 s) so that an
# 11-s flight keeps ~6.8 s of flying part after the take-off/landing cut (the quality checks want 5 s).
TIMING = Timing(sit_before_s=1.0, takeoff_s=1.5, hover_s=0.5, land_s=1.5, sit_after_s=0.5)


def simulated_circle(seed: int = 0, seconds: float = 11.0) -> SimulatedFlight:
    """The simulator (ingest.sim) flying rest, take-off to 1 m, a circle whose radius and rate depend on the
    seed, landing: `seconds` in all, with the simulator's nominal sensor noise (seeded)."""
    radius, omega = 0.3 + 0.05 * (seed % 5), 0.8 + 0.1 * (seed % 3)
    circling = seconds - (TIMING.sit_before_s + TIMING.takeoff_s + 2 * TIMING.hover_s + TIMING.land_s
                          + TIMING.sit_after_s)
    circle = Circle(radius=radius, speed=radius * omega, altitude=1.0, duration_s=circling,
                    ramp_s=min(1.5, circling / 2))
    return simulate(circle, timing=TIMING, seed=seed, name=f"flight{seed}")


def flight_csv(directory: Path, seed: int, name: str | None = None, seconds: float = 11.0) -> Path:
    """`simulated_circle(seed, seconds)` written as a NanoBench CSV (once per path)."""
    path = Path(directory) / (name or f"flight{seed}.csv")
    if not path.exists():
        written = write_flight(simulated_circle(seed, seconds), "nanobench", path.parent, path.stem)
        assert written == [path], written
    return path


# one warm worker process for every test module (spawning one imports torch: seconds)
_shared_pool: LocalPoolExecutor | None = None


def shared_pool() -> LocalPoolExecutor:
    global _shared_pool
    if _shared_pool is None:
        from learnest.service.jobs.executors import LocalPoolExecutor

        _shared_pool = LocalPoolExecutor(max_workers=1)
        atexit.register(_shared_pool.shutdown)
    return _shared_pool


_shared_decoder = None


def shared_decoder():
    """One upload decoder pool (its worker processes warm) for every test app."""
    global _shared_decoder
    if _shared_decoder is None:
        from learnest.service.jobs.decoding import DecodePool

        _shared_decoder = DecodePool(workers=1, waiting=64, timeout_s=60)  # room for the concurrency tests
        _shared_decoder.start()
        atexit.register(_shared_decoder.shutdown)
    return _shared_decoder


def settings_for(home: Path, **changes) -> Settings:
    """Service settings on a SQLite file under ``home``; Starlette's TestClient sends ``Host: testserver``."""
    changes.setdefault("allowed_hosts", "localhost,127.0.0.1,::1,testserver")
    from learnest.service.config import Settings

    return Settings(home=Path(home), pool_workers=1, **changes)


@contextmanager
def running_app(home: Path, executor=None, **changes):
    """The real app (lifespan included: migrations, job runner) on a SQLite file under `home`."""
    from fastapi.testclient import TestClient

    from learnest.service.app.factory import create_app
    from learnest.service.jobs.executors import init_worker

    init_worker()  # this process trains too (CLI paths): one torch thread, as in the workers
    app = create_app(settings_for(home, **changes), executor=executor or shared_pool(), decoder=shared_decoder(),
                     scheduler=False)
    with TestClient(app) as client:
        yield client


def upload(client: TestClient, *paths: Path, names=None, headers=None, **form):
    names = names or [p.name for p in paths]
    files = [("files", (name, Path(p).read_bytes())) for name, p in zip(names, paths)]
    return client.post("/flights", files=files, data=form, headers=headers or {})


def wait_for_job(client: TestClient, job_id: int, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} still {job['state']} after {timeout} s")


def train(client: TestClient, name: str, flight_id: int, **extra) -> dict:
    response = client.post("/models", json={"name": name, "flight_id": flight_id, "epochs": EPOCHS, **extra})
    assert response.status_code == 202, response.text
    job = wait_for_job(client, response.json()["job_id"])
    assert job["state"] == "succeeded", job
    return response.json()


def evaluate(client: TestClient, model: str, flights, methods=None, **extra) -> tuple[dict, dict]:
    response = client.post("/evaluations", json={"model": model, "flights": flights,
                                                 "methods": methods or FAST_METHODS, **extra})
    assert response.status_code == 202, response.text
    accepted = response.json()
    job = wait_for_job(client, accepted["job_id"])
    assert job["state"] == "succeeded", job
    report = client.get(f"/evaluations/{accepted['evaluation_id']}")
    assert report.status_code == 200, report.text
    return accepted, report.json()


def without_timing(report: dict) -> dict:
    """A report minus ms_per_step, also the gap runs' (wall time differs from run to run)."""
    def flight(f: dict) -> dict:
        f = {k: v for k, v in f.items() if k != "ms_per_step"}
        if (f.get("yardsticks") or {}).get("mocap_gaps"):
            gaps = {k: v for k, v in f["yardsticks"]["mocap_gaps"].items() if k != "ms_per_step"}
            f["yardsticks"] = {**f["yardsticks"], "mocap_gaps": gaps}
        return f
    return {**report, "flights": [flight(f) for f in report["flights"]]}


def blob_files(home: Path) -> set[str]:
    root = Path(home) / "blobs"
    return {p.parent.name + p.name for p in root.glob("??/*") if p.is_file()}


MULTIPART_XYZ = (b"content-type", b"multipart/form-data; boundary=xyz")


def raw_post(app, path: str, chunks: list[bytes], headers: list) -> tuple[int, int, bytes]:
    """POST ``chunks`` to the ASGI ``app`` one receive() at a time; -> (status, chunks the app pulled, answer
    body).  What a TestClient cannot show: how much of a body the server read before it answered."""
    import asyncio

    pulled, sent = [0], []

    async def receive():
        if pulled[0] < len(chunks):
            pulled[0] += 1
            return {"type": "http.request", "body": chunks[pulled[0] - 1], "more_body": pulled[0] < len(chunks)}
        return {"type": "http.disconnect"}

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "server": ("testserver", 80), "client": ("127.0.0.1", 5000),
             "headers": [(b"host", b"testserver"), (b"content-length", str(sum(map(len, chunks))).encode()),
                         *headers]}
    asyncio.run(app(scope, receive, send))
    return sent[0]["status"], pulled[0], b"".join(m.get("body", b"") for m in sent[1:])


TIMEOUT_S = 1.0   # s: the live server's header, body and keep-alive timeouts


@contextmanager
def live_server(home, **changes):
    """The app under uvicorn (in a thread, with `learnest serve`'s options) on 127.0.0.1:<free port>."""
    import uvicorn

    from learnest.service.api.server import DeadlineH11Protocol
    from learnest.service.app.factory import create_app
    from learnest.service.local.serving import uvicorn_options

    settings = settings_for(home, header_timeout_s=TIMEOUT_S, body_timeout_s=TIMEOUT_S, body_min_rate=1000,
                            keep_alive_s=TIMEOUT_S, **changes)

    class Protocol(DeadlineH11Protocol):
        header_timeout_s = TIMEOUT_S
        send_timeout_s = settings.send_timeout_s
        max_client_connections = settings.max_client_connections
        trusted_proxies = settings.trusted_proxy_addresses

    options = {**uvicorn_options(settings), "http": Protocol}
    config = uvicorn.Config(create_app(settings, executor=shared_pool(), scheduler=False), log_level="warning",
                            **options)
    server = uvicorn.Server(config)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.started
    try:
        yield sock.getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()
