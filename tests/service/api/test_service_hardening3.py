"""Hostile input, third round: gap plans that would never end, estimate exports that would fill the disk.
The real app on SQLite files (a live uvicorn server where a stalled client matters); the attacks are what a
client would send."""
from __future__ import annotations

import time

import pytest
from utils.service import flight_csv, running_app, train, upload


@pytest.fixture(scope="module")
def model_home(tmp_path_factory):
    """A home with two flights (11 s at 100 Hz) and quad:1 trained on the first."""
    root = tmp_path_factory.mktemp("hardening3")
    home, logs = root / "home", root / "logs"
    logs.mkdir()
    with running_app(home) as client:
        ids = [upload(client, flight_csv(logs, seed)).json()["id"] for seed in (0, 1)]
        train(client, "quad", ids[0])
    return {"home": home, "ids": ids}


# -- gap plans are bounded before anything runs --------------------------------------------------------
def test_a_gap_plan_that_never_ends_is_a_422_naming_the_field_within_a_second(model_home):
    """1e-300-s gaps every 2e-300 s were accepted (202) and their windows grew the worker without end."""
    ids = model_home["ids"]
    with running_app(model_home["home"]) as client:
        for body, field in (({"gap_s": 1e-300, "gap_every_s": 2e-300}, "gap_s"),
                            ({"gap_s": 0.5, "gap_every_s": 0.5 + 1e-12}, "gap_every_s"),
                            ({"gap_s": 0.5, "gap_every_s": 0.5005}, "gap_every_s")):
            started = time.perf_counter()
            refused = client.post("/evaluations", json={"model": "nothing:1", "flights": [ids[1]], **body})
            assert time.perf_counter() - started < 1.0
            assert refused.status_code == 422, refused.text
            assert f"{field} must be" in refused.text
        # physically possible, but shorter than one sample of these 100 Hz flights: refused before any job
        jobs = client.get("/jobs").json()["total"]
        started = time.perf_counter()
        finer = client.post("/evaluations", json={"model": "quad:1", "flights": [ids[1]], "gap_s": 0.002,
                                                  "gap_every_s": 0.004, "methods": ["ukf"]})
        assert time.perf_counter() - started < 1.0
        assert finer.status_code == 422, finer.text
        assert "gap_s must be 0 (no gaps) or at least one sample (0.01 s)" in finer.json()["detail"]
        assert f"flight {ids[1]}" in finer.json()["detail"]
        assert client.get("/jobs").json()["total"] == jobs
