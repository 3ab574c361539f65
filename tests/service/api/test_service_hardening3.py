"""Hostile input, third round: gap plans that would never end, estimate exports that would fill the disk.
The real app on SQLite files (a live uvicorn server where a stalled client matters); the attacks are what a
client would send."""
from __future__ import annotations

import time

import pytest
from utils.service import evaluate, flight_csv, running_app, train, upload


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
def test_a_gap_plan_that_never_ends_is_a_422_naming_the_field_before_any_job(model_home):
    """1e-300-s gaps every 2e-300 s were accepted (202) and their windows grew the worker without end.  Refused
    before any job is made (how fast: benchmarks/bench_service_hostile.py, not a timed test)."""
    ids = model_home["ids"]
    with running_app(model_home["home"]) as client:
        for body, field in (({"gap_s": 1e-300, "gap_every_s": 2e-300}, "gap_s"),
                            ({"gap_s": 0.5, "gap_every_s": 0.5 + 1e-12}, "gap_every_s"),
                            ({"gap_s": 0.5, "gap_every_s": 0.5005}, "gap_every_s")):
            refused = client.post("/evaluations", json={"model": "nothing:1", "flights": [ids[1]], **body})
            assert refused.status_code == 422, refused.text
            assert f"{field} must be" in refused.text
        # physically possible, but shorter than one sample of these 100 Hz flights: refused before any job
        jobs = client.get("/jobs").json()["total"]
        finer = client.post("/evaluations", json={"model": "quad:1", "flights": [ids[1]], "gap_s": 0.002,
                                                  "gap_every_s": 0.004, "methods": ["ukf"]})
        assert finer.status_code == 422, finer.text
        assert "gap_s must be 0 (no gaps) or at least one sample (0.01 s)" in finer.json()["detail"]
        assert f"flight {ids[1]}" in finer.json()["detail"]
        assert client.get("/jobs").json()["total"] == jobs


# -- estimate exports: made once, kept within a budget, dropped with a stalled reader ------------------
SEND_TIMEOUT_S = 1.5   # s: the live server's slow-reader timeout here (60 by default)


@pytest.fixture(scope="module")
def long_evaluation(model_home, tmp_path_factory):
    """quad:1 evaluated on two 60-s flights: a CSV export of ~17 MB, more than a stalled client's socket holds
    (~3 MB on loopback), so the server has to keep it while its client stalls."""
    logs = tmp_path_factory.mktemp("long")
    with running_app(model_home["home"]) as client:
        ids = [upload(client, flight_csv(logs, seed, seconds=60.0)).json()["id"] for seed in (5, 6)]
        accepted, _ = evaluate(client, "quad:1", ids)
    return {**model_home, "evaluation": accepted["evaluation_id"], "long": ids}


def _export_files(home) -> dict[str, int]:
    """{name: bytes} of every export on disk: kept (blobs/.exports) and being written or sent (blobs/.tmp)."""
    blobs = home / "blobs"
    found = [p for p in (blobs / ".exports").glob("*") if not p.name.startswith(".")] \
        if (blobs / ".exports").exists() else []
    found += [p for p in (blobs / ".tmp").rglob("*") if p.is_file()]
    return {p.name: p.stat().st_size for p in found}


def _stalled_download(port: int, path: str):
    """A GET whose client reads nothing (a 4-kB receive buffer): the server's writes stall."""
    import socket

    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    return sock


def _answer_started(sock) -> bool:
    import socket

    try:
        return bool(sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT))
    except BlockingIOError:
        return False


def _read_to_end(sock, limit_s: float = 10.0) -> tuple[int, bool]:
    """(bytes read, whether the server ended the connection within ``limit_s``)."""
    sock.settimeout(limit_s)
    total = 0
    try:
        while chunk := sock.recv(1 << 16):
            total += len(chunk)
    except ConnectionResetError:
        pass
    except TimeoutError:
        return total, False
    return total, True


def test_six_stalled_export_readers_share_one_file_and_are_dropped(long_evaluation):
    """Six clients that stop reading a CSV export: the export is on disk once (each request wrote its own copy
    and kept it while its client stalled), and after the send deadline they are dropped and nothing but the
    one kept export remains."""
    from utils.service import live_server

    home, evaluation = long_evaluation["home"], long_evaluation["evaluation"]
    path = f"/evaluations/{evaluation}/estimates?format=csv"
    with live_server(home, send_timeout_s=SEND_TIMEOUT_S) as port:
        readers = [_stalled_download(port, path) for _ in range(6)]
        try:
            deadline = time.monotonic() + 60
            while not all(map(_answer_started, readers)) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert all(map(_answer_started, readers))
            time.sleep(0.5)   # the writes have filled the sockets
            stalled = _export_files(home)
            one = max(stalled.values())
            assert one > 8e6, stalled          # larger than what the sockets hold
            assert sum(stalled.values()) < 2 * one, stalled
            time.sleep(SEND_TIMEOUT_S + 1.0)   # the send deadline passes for every one of them
            ended = [_read_to_end(sock) for sock in readers]
            assert all(done for _, done in ended), ended          # dropped, not waited for
            assert all(got < one for got, _ in ended), (ended, one)   # cut off, never a whole export
        finally:
            for sock in readers:
                sock.close()
        assert _export_files(home) == {name: size for name, size in stalled.items() if size == one}
        assert len(_export_files(home)) == 1


def test_an_export_is_made_once_for_concurrent_requests_and_goes_with_its_evaluation(model_home, monkeypatch):
    """Four requests at once: one writes the export, all four read it; a flight's own export is another file;
    deleting the evaluation deletes its exports, and deleting a flight deletes the exports of the evaluations
    that scored it."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from learnest.service.operations import exports

    made, real = [], exports.write_estimates

    def counted(flights, target, fmt):
        made.append(fmt)
        time.sleep(0.3)   # the others arrive while it is being written
        real(flights, target, fmt)

    monkeypatch.setattr(exports, "write_estimates", counted)
    home, ids = model_home["home"], model_home["ids"]
    with running_app(home) as client:
        accepted, _ = evaluate(client, "quad:1", [ids[1]])
        path = f"/evaluations/{accepted['evaluation_id']}/estimates"
        start = threading.Barrier(4)

        def download(_):
            start.wait()
            return client.get(path)

        with ThreadPoolExecutor(4) as pool:
            answers = list(pool.map(download, range(4)))
        assert [a.status_code for a in answers] == [200] * 4
        assert len({a.content for a in answers}) == 1 and made == ["csv"]
        assert answers[0].headers["content-length"] == str(len(answers[0].content))
        assert client.get(path, params={"flight": ids[1]}).status_code == 200
        assert client.get(path).content == answers[0].content and made == ["csv", "csv"]   # kept, not made again
        assert len(_export_files(home)) >= 2
        assert client.delete(f"/evaluations/{accepted['evaluation_id']}").status_code == 204
        assert not [n for n in _export_files(home) if n.startswith(f"e{accepted['evaluation_id']}-")]

        logs = home.parent / "another"
        logs.mkdir(exist_ok=True)
        flight = upload(client, flight_csv(logs, 3)).json()["id"]
        other, _ = evaluate(client, "quad:1", [ids[1], flight])
        assert client.get(f"/evaluations/{other['evaluation_id']}/estimates").status_code == 200
        assert [n for n in _export_files(home) if n.startswith(f"e{other['evaluation_id']}-")]
        assert client.delete(f"/flights/{flight}").status_code == 204
        assert not [n for n in _export_files(home) if n.startswith(f"e{other['evaluation_id']}-")]


def test_exports_stay_within_their_disk_budget(model_home):
    """An export that does not fit is a 507 that leaves nothing; one that fits only without the others makes
    room by removing the least recently served."""
    home, ids = model_home["home"], model_home["ids"]
    with running_app(home) as client:
        accepted, _ = evaluate(client, "quad:1", [ids[1]])
    path = f"/evaluations/{accepted['evaluation_id']}/estimates"
    before = _export_files(home)
    with running_app(home, export_budget_mb=0.05) as client:
        refused = client.get(path)
        assert refused.status_code == 507, refused.text
        assert "LEARNEST_EXPORT_BUDGET_MB" in refused.json()["detail"]
        assert _export_files(home) == before
    size = len(running_app_get(home, path))
    with running_app(home, export_budget_mb=1.5 * size / 1024 / 1024) as client:
        assert client.get(path).status_code == 200
        kept = set(_export_files(home))
        assert client.get(path, params={"flight": ids[1]}).status_code == 200   # the same size: the first goes
        assert sum(_export_files(home).values()) <= 1.5 * size
        assert not (kept - set(before)) & set(_export_files(home))


def running_app_get(home, path: str) -> bytes:
    with running_app(home) as client:
        answer = client.get(path)
        assert answer.status_code == 200
        return answer.content
