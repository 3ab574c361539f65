"""Slow and idle clients are cut off, the concurrency limit holds, failed keys are
throttled.  Real sockets against a real uvicorn server on an ephemeral loopback port, with 1-s timeouts."""
from __future__ import annotations

import socket
import time

import pytest
from utils.service import TIMEOUT_S, live_server, running_app


@pytest.fixture(scope="module")
def port(tmp_path_factory):
    with live_server(tmp_path_factory.mktemp("live"), limit_concurrency=6) as port:
        yield port


def connect(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    return sock


def closed_after(sock: socket.socket, limit_s: float = 4.0) -> tuple[float, bytes]:
    """Seconds until the server closed the connection (recv gives b""), and what it sent before."""
    start, received = time.monotonic(), b""
    sock.settimeout(limit_s)
    while True:
        try:
            chunk = sock.recv(65536)
        except ConnectionResetError:
            chunk = b""
        if not chunk:
            return time.monotonic() - start, received
        received += chunk


def test_a_connection_that_sends_nothing_is_closed(port):
    with connect(port) as sock:
        seconds, _ = closed_after(sock)
    assert TIMEOUT_S * 0.8 < seconds < TIMEOUT_S + 1.5


def test_a_request_whose_headers_never_end_is_closed(port):
    with connect(port) as sock:
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n")
        seconds, answer = closed_after(sock)
    assert seconds < TIMEOUT_S + 1.5 and answer == b""


def test_headers_trickling_in_a_byte_at_a_time_are_cut_off(port):
    """Bytes keep arriving (one per 0.2 s), but the headers are not complete by the deadline."""
    request = b"GET /health HTTP/1.1\r\nHost: localhost\r\nX-Slow: " + b"a" * 100 + b"\r\n\r\n"
    with connect(port) as sock:
        start = time.monotonic()
        try:
            for byte in request:
                sock.sendall(bytes([byte]))
                time.sleep(0.2)
                if time.monotonic() - start > TIMEOUT_S + 2:
                    break
        except (BrokenPipeError, ConnectionResetError):
            pass
        seconds, answer = closed_after(sock)
    assert time.monotonic() - start < TIMEOUT_S + 2.5 and answer == b""


def test_a_trickling_body_gets_a_408_and_the_connection_is_closed(port):
    head = (b"POST /flights HTTP/1.1\r\nHost: localhost\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            b"Content-Length: 100000\r\n\r\n")
    with connect(port) as sock:
        sock.sendall(head + b"--b\r\n")
        start = time.monotonic()
        try:
            while time.monotonic() - start < TIMEOUT_S + 2:
                sock.sendall(b"x")
                time.sleep(0.25)
        except (BrokenPipeError, ConnectionResetError):
            pass
        seconds, answer = closed_after(sock)
    assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
    assert b"connection: close" in answer.lower() and b"LEARNEST_BODY_TIMEOUT_S" in answer


def read_answer(sock: socket.socket) -> bytes:
    """One response with a Content-Length body."""
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(65536)
    head, _, body = answer.partition(b"\r\n\r\n")
    lines = head.lower().split(b"\r\n")
    length = int(next(line.split(b":")[1] for line in lines if line.startswith(b"content-length")))
    while len(body) < length:
        body += sock.recv(65536)
    return head + b"\r\n\r\n" + body


def test_a_prompt_client_keeps_its_connection_for_several_requests(port):
    with connect(port) as sock:
        for _ in range(3):
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n\r\n")
            answer = read_answer(sock)
            assert answer.startswith(b"HTTP/1.1 200") and b'"status":"ok"' in answer
        seconds, _ = closed_after(sock)    # then idle: closed by the keep-alive timeout
    assert seconds < TIMEOUT_S + 1.5


def test_connections_beyond_the_concurrency_limit_get_503(port):
    idle = [connect(port) for _ in range(6)]    # the limit: 6 connections
    try:
        time.sleep(0.1)
        with connect(port) as sock:
            sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n\r\n")
            assert sock.recv(65536).startswith(b"HTTP/1.1 503")
    finally:
        for sock in idle:
            sock.close()
    time.sleep(0.1)
    with connect(port) as sock:  # once they are gone, requests are answered again
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: localhost\r\n\r\n")
        assert sock.recv(65536).startswith(b"HTTP/1.1 200")


# -- failed API keys ---------------------------------------------------------------------------------------
def test_failed_keys_are_throttled_per_address_then_let_through_again():
    from learnest.service.api.throttle import KeyThrottle

    now = [1000.0]
    throttle = KeyThrottle(3, 60.0, clock=lambda: now[0])
    for _ in range(3):
        assert throttle.retry_after("10.0.0.1") is None
        throttle.failed("10.0.0.1")
        now[0] += 10
    assert throttle.retry_after("10.0.0.1") == 30    # the first failure (t=1000) leaves the window at 1060
    assert throttle.retry_after("10.0.0.2") is None  # another address is not affected
    now[0] = 1060.5
    assert throttle.retry_after("10.0.0.1") is None


def test_an_address_that_fails_the_key_too_often_gets_429_with_retry_after(tmp_path):
    with running_app(tmp_path, api_key="s3cret", key_failures=3) as client:
        for _ in range(3):
            assert client.post("/models", json={}, headers={"X-API-Key": "guess"}).status_code == 401
        refused = client.post("/models", json={}, headers={"X-API-Key": "guess"})
        assert refused.status_code == 429 and 1 <= int(refused.headers["Retry-After"]) <= 60
        assert "LEARNEST_KEY_FAILURES" in refused.json()["detail"]
        signin = client.post("/ui/signin", data={"token": "guess"})   # the web sign-in counts along
        assert signin.status_code == 429
        assert client.get("/health").status_code == 200   # needs no token: never throttled


def test_a_500_says_connection_close(tmp_path):
    """After a 500 the server drops the connection: the answer says so."""
    with running_app(tmp_path) as client:
        def broken():
            raise RuntimeError("boom")

        client.app.add_api_route("/broken", broken)
        client.app.router.routes.insert(0, client.app.router.routes.pop())
        from fastapi.testclient import TestClient

        with TestClient(client.app, raise_server_exceptions=False) as raw:
            answer = raw.get("/broken", headers={"Host": "localhost"})
    assert answer.status_code == 500 and answer.headers["connection"] == "close"
