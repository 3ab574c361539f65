"""Helpers for the service tests: a running app, uploads, jobs, small simulated NanoBench flights.

Flights are small simulated NanoBench CSVs that pass the quality checks (11 s, ~6 s of flying part), so
every test drives the real app, the real adapters and the real estimators in seconds.
"""
from __future__ import annotations

import atexit
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from learnest.ingest.formats.nanobench import reader as nanobench
from learnest.ingest.frames import GRAVITY, quat_to_matrix
from learnest.service.config import Settings
from learnest.service.executors import LocalPoolExecutor

if TYPE_CHECKING:  # the app (torch, filterpy, matplotlib) is imported when a test first runs one
    from fastapi.testclient import TestClient
FAST_METHODS = ["ukf", "knode-ukf"]   # the MHE adds seconds per flight; one test runs it
EPOCHS = 3


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10 - 15 * u + 6 * u * u)


def flight_table(seed: int = 0, seconds: float = 11.0) -> pd.DataFrame:
    """Rest, take-off to 1 m, a circle (radius and rate depend on the seed), landing; the accelerometer
    measures the path's second derivative plus gravity in the body frame, with noise."""
    rng = np.random.default_rng(seed)
    radius, omega = 0.3 + 0.05 * (seed % 5), 0.8 + 0.1 * (seed % 3)
    t = np.arange(int(seconds * 100)) * 0.01
    up = _smoothstep((t - 1.0) / 1.5) - _smoothstep((t - (seconds - 2.5)) / 1.5)
    p = np.column_stack([radius * np.sin(omega * t) * up, radius * (1 - np.cos(omega * t)) * up, 0.05 + 0.95 * up])
    a = np.gradient(np.gradient(p, 0.01, axis=0), 0.01, axis=0)
    quat = np.column_stack([rng.normal(0, 0.01, (len(t), 3)), np.ones(len(t))])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    acc_body_g = np.einsum("tji,tj->ti", quat_to_matrix(quat), a + [0, 0, GRAVITY]) / GRAVITY
    acc_body_g += rng.normal(0, 0.005, acc_body_g.shape)
    p += rng.normal(0, 2e-4, p.shape)
    columns = {"t": 1.7e9 + t, "px": p[:, 0], "py": p[:, 1], "pz": p[:, 2]}
    columns.update(zip(("qx", "qy", "qz", "qw"), quat.T))
    columns.update(zip(nanobench.ACC_COLUMNS, acc_body_g.T))
    return pd.DataFrame(columns)


def flight_csv(directory: Path, seed: int, name: str | None = None) -> Path:
    path = Path(directory) / (name or f"flight{seed}.csv")
    if not path.exists():
        flight_table(seed).to_csv(path, index=False, float_format="%.9f")
    return path


# one warm worker process for every test module (spawning one imports torch: seconds)
_shared_pool: LocalPoolExecutor | None = None


def shared_pool() -> LocalPoolExecutor:
    global _shared_pool
    if _shared_pool is None:
        _shared_pool = LocalPoolExecutor(max_workers=1)
        atexit.register(_shared_pool.shutdown)
    return _shared_pool


def settings_for(home: Path, **changes) -> Settings:
    return Settings(home=Path(home), pool_workers=1, **changes)


@contextmanager
def running_app(home: Path, executor=None, **changes):
    """The real app (lifespan included: migrations, job runner) on a SQLite file under `home`."""
    from fastapi.testclient import TestClient

    from learnest.service.app import create_app
    from learnest.service.executors import init_worker

    init_worker()  # this process trains too (CLI paths): one torch thread, as in the workers
    app = create_app(settings_for(home, **changes), executor=executor or shared_pool(), scheduler=False)
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
        if job["state"] in ("succeeded", "failed"):
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
    """A report minus ms_per_step (wall time differs from run to run)."""
    return {**report, "flights": [{k: v for k, v in f.items() if k != "ms_per_step"} for f in report["flights"]]}


def blob_files(home: Path) -> set[str]:
    root = Path(home) / "blobs"
    return {p.parent.name + p.name for p in root.glob("??/*") if p.is_file()}
