"""Hostile input, third round: what a client can make the server hold (memory, connections, jobs), what it
may frame, and what the request models and the upload path accept.  Each test failed on the code before its
fix."""
from __future__ import annotations

import asyncio
import hashlib
import io
import socket
import time
import tracemalloc

import numpy as np
import pytest
from utils.service import flight_csv, live_server, running_app, upload


# -- an upload in progress: parts on disk, a ceiling on the body's time ----------------------------------------
def test_an_upload_in_progress_holds_its_file_parts_on_disk_not_in_memory(tmp_path):
    """20 file parts of 512 KiB each and no closing boundary: the parts were kept in memory (Starlette spooled
    parts under 1 MiB in RAM) for as long as the client withheld the end."""
    part = b"x" * (512 << 10)
    chunks = [b'--xyz\r\nContent-Disposition: form-data; name="files"; filename="f%d.csv"\r\n\r\n' % i + part + b"\r\n"
              for i in range(20)]
    held: list[int] = []
    with running_app(tmp_path) as client:
        app = client.app
        pulled = [0]

        async def receive():
            if pulled[0] < len(chunks):
                pulled[0] += 1
                return {"type": "http.request", "body": chunks[pulled[0] - 1], "more_body": True}
            held.append(tracemalloc.get_traced_memory()[0])   # every part is in; the end never comes
            return {"type": "http.disconnect"}

        async def send(message):
            pass

        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
                 "scheme": "http", "path": "/flights", "raw_path": b"/flights", "query_string": b"", "root_path": "",
                 "server": ("testserver", 80), "client": ("127.0.0.1", 5000),
                 "headers": [(b"host", b"testserver"), (b"content-type", b"multipart/form-data; boundary=xyz"),
                             (b"content-length", str(sum(map(len, chunks)) + 1000).encode())]}
        tracemalloc.start()
        try:
            start = tracemalloc.get_traced_memory()[0]
            asyncio.run(app(scope, receive, send))
        finally:
            tracemalloc.stop()
    assert held, "the app never read the whole body"
    assert held[0] - start < 3 << 20, f"{(held[0] - start) / 2**20:.1f} MiB held in memory for 10 MiB of parts"


def test_a_body_that_keeps_coming_is_cut_off_at_the_ceiling():
    """Fast enough never to fall behind the rate rule, the body still ends at LEARNEST_BODY_MAX_S (the
    deadline used to grow with every byte received)."""
    from starlette.exceptions import HTTPException

    from learnest.service.api.server import BodyDeadline

    async def reads_everything(scope, receive, send):
        while (await receive()).get("more_body"):
            pass

    async def endless():
        await asyncio.sleep(0.02)
        return {"type": "http.request", "body": b"x" * 100_000, "more_body": True}

    guarded = BodyDeadline(reads_everything, timeout_s=0.2, min_rate=1000, max_s=0.5)
    scope = {"type": "http", "headers": [(b"content-length", b"999999999")]}
    start = time.monotonic()
    with pytest.raises(HTTPException) as refused:
        asyncio.run(guarded(scope, endless, None))
    assert refused.value.status_code == 408 and "LEARNEST_BODY_MAX_S" in refused.value.detail
    assert time.monotonic() - start < 1.5


# -- a flight's CSV is streamed ----------------------------------------------------------------------------------
def test_a_flights_csv_is_streamed_in_blocks_with_bounded_memory(tmp_path):
    from learnest.ingest.flight import Flight
    from learnest.service.api.routes.flights import CSV_COLUMNS, csv_blocks

    rng = np.random.default_rng(0)
    n = 200_000
    flight = Flight(np.arange(n) / 100.0, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 4)),
                    {"vbat": np.full(n, 3.9)}, {"name": "big"})
    path = tmp_path / "big.npz"
    path.write_bytes(flight.to_bytes())
    whole = io.StringIO()   # what the route built in memory before
    np.savetxt(whole, np.column_stack([flight.t, flight.p, flight.a_meas, flight.quat]), delimiter=",",
               fmt="%.10g", header=CSV_COLUMNS, comments="")
    expected = whole.getvalue().encode()
    del flight, whole
    digest, size = hashlib.sha256(), 0
    tracemalloc.start()
    try:
        for block in csv_blocks(path.open("rb")):
            digest.update(block)
            size += len(block)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert size == len(expected) and digest.hexdigest() == hashlib.sha256(expected).hexdigest()
    assert peak < len(expected) / 8, f"peak {peak / 2**20:.1f} MiB for a {len(expected) / 2**20:.1f} MiB CSV"


def test_the_data_route_streams_the_same_csv(tmp_path):
    from learnest.ingest.flight import Flight
    from learnest.service.api.routes.flights import CSV_COLUMNS
    from learnest.service.storage.tables import FlightRecord

    with running_app(tmp_path / "home") as client:
        stored = upload(client, flight_csv(tmp_path, seed=1)).json()
        answer = client.get(f"/flights/{stored['id']}/data")
        services = client.app.state.services
        with services.db.transaction() as session:
            blob = session.get(FlightRecord, stored["id"]).flight_blob
        flight = Flight.from_bytes(services.blobs.read_bytes(blob))
    assert answer.status_code == 200 and "content-length" not in answer.headers   # streamed, not built whole
    assert answer.headers["content-type"].startswith("text/csv")
    assert f'filename="{stored["name"]}.csv"' in answer.headers["content-disposition"]
    whole = io.StringIO()
    np.savetxt(whole, np.column_stack([flight.t, flight.p, flight.a_meas, flight.quat]), delimiter=",",
               fmt="%.10g", header=CSV_COLUMNS, comments="")
    assert answer.content == whole.getvalue().encode()


# -- connections: per client network, header bytes, framing ------------------------------------------------------
@pytest.fixture(scope="module")
def port(tmp_path_factory):
    with live_server(tmp_path_factory.mktemp("live3"), limit_concurrency=40, max_client_connections=5) as port:
        yield port


def connect(port: int, source: str = "127.0.0.1") -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(source, 0))


def health(port: int, source: str) -> bytes:
    with connect(port, source) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n\r\n")
        return sock.recv(65536)


def test_one_client_network_cannot_take_every_connection(port):
    """25 slow-header connections from one /24 (the probe's 250, scaled to the test's limit of 40): the
    network keeps 5, the rest get 503, and another network's /health is answered."""
    slow = []
    try:
        for _ in range(25):
            sock = connect(port)
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n")   # headers never finished
            slow.append(sock)
        time.sleep(0.1)
        refused = 0
        for sock in slow[5:]:
            sock.settimeout(0.5)
            try:
                answer = sock.recv(65536)
            except TimeoutError:
                answer = b""
            refused += answer.startswith(b"HTTP/1.1 503") and b"LEARNEST_MAX_CLIENT_CONNECTIONS" in answer
        assert refused == 20
        assert health(port, "127.0.1.1").startswith(b"HTTP/1.1 200")   # another /24
    finally:
        for sock in slow:
            sock.close()
    time.sleep(0.1)
    assert health(port, "127.0.0.1").startswith(b"HTTP/1.1 200")   # its slots are free again


def test_headers_past_the_limit_in_one_packet_get_431(port):
    request = b"GET /health HTTP/1.1\r\nHost: localhost\r\n" + b"X-Big: " + b"a" * 70_000 + b"\r\n\r\n"
    with connect(port) as sock:
        sock.sendall(request)
        answer = read_until_closed(sock)
    assert answer.startswith(b"HTTP/1.1 431") and b"LEARNEST_MAX_HEADER_BYTES" in answer
    # many headers, each small, count together
    many = b"".join(b"X-H%d: %s\r\n" % (i, b"b" * 90) for i in range(300))
    with connect(port) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n" + many + b"\r\n")
        assert sock.recv(65536).startswith(b"HTTP/1.1 431")


def read_until_closed(sock: socket.socket) -> bytes:
    answer = b""
    while chunk := sock.recv(65536):
        answer += chunk
    return answer


def test_content_length_with_transfer_encoding_gets_400(port):
    request = (b"POST /models HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: 4\r\n"
               b"Transfer-Encoding: chunked\r\n\r\n2\r\n{}\r\n0\r\n\r\n")
    with connect(port) as sock:
        sock.sendall(request)
        answer = read_until_closed(sock)
    assert answer.startswith(b"HTTP/1.1 400") and b"Transfer-Encoding" in answer


# -- security headers ----------------------------------------------------------------------------------------------
def every_route(routes):
    """The routes, and those of FastAPI's included routers (nested ones too)."""
    for route in routes:
        included = getattr(route, "original_router", None)
        if included is not None:
            yield from every_route(included.routes)
        else:
            yield route


def test_every_answer_forbids_framing_and_sniffing(tmp_path):
    """Every GET route (pages, JSON, static files, docs), whatever its status, says it may not be framed."""
    from fastapi.routing import APIRoute
    from starlette.routing import Mount

    with running_app(tmp_path / "home") as client:
        flight_id = upload(client, flight_csv(tmp_path, seed=1)).json()["id"]
        paths = []
        for route in every_route(client.app.routes):
            if isinstance(route, Mount):
                paths.append(route.path + "/style.css")
            elif isinstance(route, APIRoute) and "GET" in route.methods and route.path != "/manual/{path:path}":
                # (the manual's pages are built on first view, seconds: the same middleware answers them)
                paths.append(route.path.replace("{flight_id}", str(flight_id)).replace("{name}", "m")
                             .replace("{version}", "1").replace("{alias}", "production")
                             .replace("{evaluation_id}", "1").replace("{diagnosis_id}", "1")
                             .replace("{job_id}", "1").replace("{path:path}", "x"))
        assert "/" in paths and f"/ui/flights/{flight_id}/delete" in paths
        for path in paths:
            answer = client.get(path, follow_redirects=False)
            assert answer.headers.get("x-frame-options") == "DENY", path
            assert answer.headers.get("content-security-policy") == "frame-ancestors 'none'", path
            assert answer.headers.get("x-content-type-options") == "nosniff", path
        refused = client.get("/", headers={"Host": "evil.example"})   # the guard's own refusals too
        assert refused.status_code == 400 and refused.headers["x-frame-options"] == "DENY"


# -- the failed-key throttle ---------------------------------------------------------------------------------------
def test_the_right_key_passes_a_throttled_address_and_wrong_ones_get_429(tmp_path):
    with running_app(tmp_path, api_key="s3cret", key_failures=3) as client:
        for _ in range(3):
            assert client.post("/models", json={}, headers={"X-API-Key": "guess"}).status_code == 401
        assert client.post("/models", json={}, headers={"X-API-Key": "guess"}).status_code == 429
        right = client.post("/models", json={}, headers={"X-API-Key": "s3cret"})
        assert right.status_code == 422, right.text   # past the guard: the empty body is what is wrong
        signed_in = client.post("/ui/signin", data={"token": "s3cret"}, follow_redirects=False)
        assert signed_in.status_code == 303     # the sign-in page counts into the same throttle
        assert client.post("/ui/signin", data={"token": "nope"}).status_code == 429


def test_failures_are_counted_per_client_network():
    """Rotating the source through 127.0.0.0/24 (or an IPv6 /64) is one network, one allowance."""
    from learnest.service.api.request_guard import RequestGuard
    from learnest.service.api.throttle import KeyThrottle, client_network

    assert client_network("127.0.0.9") == client_network("127.0.0.200") == "127.0.0.0/24"
    assert client_network("127.0.1.9") != client_network("127.0.0.9")
    assert client_network("2001:db8::1") == client_network("2001:db8::ffff:1") == "2001:db8::/64"
    assert client_network("::ffff:10.0.0.5") == "10.0.0.0/24" and client_network("unknown") == "unknown"

    async def ok(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b""})

    guard = RequestGuard(ok, ("localhost",), api_key="s3cret", throttle=KeyThrottle(3, 60.0))

    def post(source: str, key: str) -> int:
        sent = []

        async def receive():
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message):
            sent.append(message)

        scope = {"type": "http", "method": "POST", "path": "/models", "client": (source, 5000),
                 "headers": [(b"host", b"localhost"), (b"x-api-key", key.encode())]}
        asyncio.run(guard(scope, receive, send))
        return sent[0]["status"]

    assert [post(f"127.0.0.{k}", "guess") for k in range(2, 6)] == [401, 401, 401, 429]
    assert post("127.0.0.77", "s3cret") == 200 and post("127.0.5.1", "guess") == 401
    assert [post(f"2001:db8::{k}", "guess") for k in range(1, 5)] == [401, 401, 401, 429]


# -- sidecars nested too deep ------------------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["a: " + "[" * 5000 + "]" * 5000 + "\n", "- " * 1200 + "x\n"],
                         ids=["flow", "block"])
def test_a_sidecar_nested_too_deep_is_refused_naming_the_clients_file(tmp_path, text):
    csv = flight_csv(tmp_path / "logs", seed=2)
    sidecar = csv.with_name(f"{csv.stem}_metadata.yaml")
    sidecar.write_text(text)
    with running_app(tmp_path / "home") as client:
        refused = upload(client, csv, sidecar)
        assert refused.status_code == 422, refused.text[:300]
        detail = refused.json()["detail"]
        assert detail.startswith(f"{sidecar.name}:") and "nested" in detail and "upload_" not in detail
        assert client.get("/flights").json()["total"] == 0


def test_a_readers_warning_names_the_clients_file_not_the_staged_one(tmp_path):
    csv = flight_csv(tmp_path / "logs", seed=2)
    sidecar = csv.with_name(f"{csv.stem}_metadata.yaml")
    sidecar.write_text("crazyflie_id: " + "9" * 5000 + "\n")   # unreadable (not a cap): ignored with a warning
    with running_app(tmp_path / "home") as client:
        stored = upload(client, csv, sidecar)
        assert stored.status_code == 201, stored.text[:300]
        warnings = client.get(f"/flights/{stored.json()['id']}").json()["meta"]["warnings"]
    warned = [w for w in warnings if "unreadable YAML" in w]
    assert warned and warned[0].startswith(sidecar.name) and "upload_" not in warned[0]


# -- training quota: all the work a request causes ------------------------------------------------------------------
def test_validation_flights_and_groups_are_charged(tmp_path):
    logs = tmp_path / "logs"
    paths = [flight_csv(logs, seed=k, name=name) for k, name in enumerate(["a_1.csv", "a_2.csv", "b_1.csv"])]
    home = tmp_path / "home"
    with running_app(home) as client:
        ids, samples = [], []
        for path in paths:
            stored = upload(client, path).json()
            ids.append(stored["id"])
            samples.append(stored["samples"])
    one = 3 * samples[0] * 8   # epochs x samples x hidden of a training on a_1 alone
    with running_app(home, max_training_work=one * 1.5) as client:
        answer = client.post("/models", json={"name": "m", "flight_id": ids[0], "validation_ids": [ids[2]],
                                              "epochs": 3, "hidden": 8})
        assert answer.status_code == 422 and "LEARNEST_MAX_TRAINING_WORK" in answer.json()["detail"]
    pooled = 3 * sum(samples) * 8   # one training on all three
    with running_app(home, max_training_work=pooled * 1.5) as client:
        grouped = client.post("/models", json={"name": "m", "flight_ids": ids, "validation_ids": [], "epochs": 3,
                                               "hidden": 8, "group_by": "name:^([ab])_"})
        assert grouped.status_code == 422, grouped.text   # 2 groups: 3 trainings
        assert "3 trainings" in grouped.json()["detail"]


def test_a_group_pattern_that_backtracks_without_end_is_refused_in_time():
    from learnest.errors import InvalidInput
    from learnest.estimators.group_training import group_names

    start = time.monotonic()
    with pytest.raises(InvalidInput, match="backtracks"):
        group_names([("a" * 40 + "X", {}), ("b", {})], "name:^((?:a|aa)+)$")
    assert time.monotonic() - start < 3
    assert group_names([("B2_circle", {}), ("B3_helix", {})], r"name:^(B\d+)_") == ["B2", "B3"]


def test_a_backtracking_group_pattern_is_refused_before_a_job_starts(tmp_path):
    logs = tmp_path / "logs"
    name = "a" * 40 + "X"
    paths = [flight_csv(logs, seed=k, name=f"{name}{k}.csv") for k in range(2)]
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, path).json()["id"] for path in paths]
        answer = client.post("/models", json={"name": "m", "flight_ids": ids, "epochs": 1,
                                              "group_by": "name:^((?:a|aa)+)$"})
        assert answer.status_code == 422 and "backtracks" in answer.json()["detail"]
        assert client.get("/jobs").json()["total"] == 0


# -- queue cap, 404 lists, strict JSON types ------------------------------------------------------------------------
def test_jobs_beyond_the_queue_cap_get_503(tmp_path):
    with running_app(tmp_path / "home", max_queued_jobs=2) as client:
        flight_id = upload(client, flight_csv(tmp_path, seed=1)).json()["id"]
        services = client.app.state.services
        with services.db.transaction() as session:   # two jobs waiting for a thread
            services.runner.create(session, "training")
            services.runner.create(session, "training")
        answer = client.post("/models", json={"name": "m", "flight_id": flight_id, "epochs": 1})
        assert answer.status_code == 503 and answer.headers["Retry-After"]
        assert "LEARNEST_MAX_QUEUED_JOBS" in answer.json()["detail"]
        assert client.get("/models/m").status_code == 404   # no version reserved


def test_a_404_for_many_missing_flights_lists_a_few_and_counts(tmp_path):
    with running_app(tmp_path / "home") as client:
        flight_id = upload(client, flight_csv(tmp_path, seed=1)).json()["id"]
        missing = list(range(flight_id + 1, flight_id + 5001))
        answer = client.post("/diagnoses", json={"flights": [flight_id, *missing], "epochs": 1})
        assert answer.status_code == 404 and len(answer.text) < 300
        assert "4990 more" in answer.json()["detail"] and "5000 in all" in answer.json()["detail"]


@pytest.mark.parametrize("body, field", [({"name": "m", "flight_id": 1, "epochs": True}, "epochs"),
                                         ({"name": "m", "flight_id": 1, "epochs": "5"}, "epochs"),
                                         ({"name": "m", "flight_id": True}, "flight_id"),
                                         ({"name": "m", "flight_ids": [True, 2]}, "flight_ids"),
                                         ({"name": "m", "flight_id": 1, "include_bad": 1}, "include_bad")])
def test_training_requests_take_json_types_strictly(tmp_path, body, field):
    with running_app(tmp_path / "home") as client:
        answer = client.post("/models", json=body)
    assert answer.status_code == 422 and answer.json()["errors"][0]["field"].startswith(field), answer.text


def test_evaluation_diagnosis_and_alias_requests_take_json_types_strictly(tmp_path):
    with running_app(tmp_path / "home") as client:
        evaluation = client.post("/evaluations", json={"model": "m:1", "flights": [True]})
        diagnosis = client.post("/diagnoses", json={"flights": [1], "epochs": "5"})
        alias = client.put("/models/m/aliases/production", json={"version": True})
        lax = client.post("/evaluations", json={"model": "m:1", "flights": [1], "horizon": "10"})
    assert evaluation.status_code == 422 and "flights" in evaluation.json()["detail"]
    assert diagnosis.status_code == 422 and "epochs" in diagnosis.json()["detail"]
    assert alias.status_code == 422 and "version" in alias.json()["detail"]
    assert lax.status_code == 422 and "horizon" in lax.json()["detail"]
