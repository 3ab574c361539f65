"""`learnest serve`'s starting app (service.app.starting): /health and / answer while the service loads, every
other request waits for it and is answered by it, a service that cannot start is said so; the manual is built
in the background, and a visitor meanwhile gets a page that says so at once."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from learnest.service.app.starting import StartingApp

GATE = threading.Event()     # the fake service's import and start-up "take" until the test opens this
STARTED, STOPPED = [], []


def gated_service() -> FastAPI:
    """A stand-in for the service's factory: slow (until GATE opens), with a start-up and a shut-down."""
    from contextlib import asynccontextmanager

    assert GATE.wait(30)

    @asynccontextmanager
    async def lifespan(app):
        STARTED.append(True)
        yield
        STOPPED.append(True)

    app = FastAPI(lifespan=lifespan)
    app.get("/health")(lambda: {"status": "ok"})
    app.get("/")(lambda: {"page": "home"})
    app.get("/api/things")(lambda: ["thing"])
    return app


def broken_service() -> FastAPI:
    raise RuntimeError("the database is of a newer schema")


def test_health_and_home_answer_at_once_while_the_service_loads_and_other_requests_wait_for_it():
    GATE.clear()
    STARTED.clear()
    STOPPED.clear()
    with TestClient(StartingApp(f"{__name__}:gated_service", stop_on_failure=False, build_manual=False)) as client:
        health = client.get("/health")
        assert health.status_code == 503 and health.json()["status"] == "starting"
        assert health.headers["retry-after"] == "2"
        home = client.get("/")
        assert home.status_code == 503 and "learnest is starting" in home.text
        assert "http-equiv='refresh'" in home.text                         # the page reloads itself
        manual = client.get("/manual/index.html")
        assert manual.status_code == 503 and "learnest is starting" in manual.text
        with ThreadPoolExecutor(1) as pool:
            waiting = pool.submit(client.get, "/api/things")
            assert not waiting.done()
            GATE.set()
            answer = waiting.result(timeout=30)
        assert answer.status_code == 200 and answer.json() == ["thing"]    # answered by the service itself
        assert STARTED == [True]
        assert client.get("/health").json() == {"status": "ok"}
        assert client.get("/").json() == {"page": "home"}
    assert STOPPED == [True]                                               # its shut-down ran with the server's


def test_a_service_that_cannot_start_is_said_so():
    with TestClient(StartingApp(f"{__name__}:broken_service", stop_on_failure=False, build_manual=False)) as client:
        answer = client.get("/api/things")
        assert answer.status_code == 503
        assert answer.json()["detail"] == "learnest could not start: the database is of a newer schema"


def test_the_real_service_starts_behind_it_and_starts_the_manual_build(tmp_path, monkeypatch):
    from learnest.service.web import manual

    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("LEARNEST_ALLOWED_HOSTS", "testserver")
    monkeypatch.setenv("LEARNEST_POOL_WORKERS", "1")
    monkeypatch.setenv("LEARNEST_SCHEDULE_SECONDS", "0")
    builds = []
    monkeypatch.setattr(manual, "build_in_background", builds.append)   # the real build is test_docs.py's
    with TestClient(StartingApp(stop_on_failure=False)) as client:
        assert client.get("/flights").status_code == 200                  # waited for the service
        health = client.get("/health")
        assert health.status_code == 200 and health.json()["status"] == "ok"
    assert builds == [tmp_path / "home"]


def test_a_manual_page_during_a_build_says_so_at_once(tmp_path):
    from utils.service import running_app

    from learnest.service.web import manual

    with running_app(tmp_path) as client:
        with manual._build_lock:            # a build under way, as `learnest serve` starts one
            page = client.get("/manual/index.html")
    assert page.status_code == 503 and "The manual is being built" in page.text
    assert page.headers["retry-after"] == "2" and "http-equiv='refresh'" in page.text


@pytest.fixture(autouse=True)
def _open_gate():
    yield
    GATE.set()     # never leave a loader thread waiting
