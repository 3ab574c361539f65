"""Hostile input, second round: downloads past the body deadline, SQLite bags whose rows SQLite computes,
jobs whose failure cannot be recorded, quotas on the flights actually used, proxy headers, form uploads
without the key, large pages, deep YAML, huge integers, deletions during an evaluation, a full database.
The real app on SQLite files; the attacks are what a client would send."""
from __future__ import annotations

import asyncio
import time

import pytest


# -- the body deadline covers receiving a body, never sending a response -----------------------------------
def _serve_file(path, deadline_s: float, send_delay_s: float, body: list[bytes] | None = None):
    """Run a FileResponse of ``path`` behind BodyDeadline with a client that takes ``send_delay_s`` per chunk
    and never disconnects; -> (status, bytes received, whether the response ended normally)."""
    from starlette.applications import Starlette
    from starlette.responses import FileResponse
    from starlette.routing import Route

    from learnest.service.api.server import BodyDeadline

    async def download(request):
        if body is not None:
            await request.body()
        return FileResponse(path)

    app = BodyDeadline(Starlette(routes=[Route("/f", download, methods=["GET", "POST"])]), timeout_s=deadline_s,
                       min_rate=1e6)
    parts = list(body or [b""])   # a GET: uvicorn hands the app one empty body part
    status, received, ended = [None], bytearray(), [False]

    async def receive():
        if parts:
            return {"type": "http.request", "body": parts.pop(0), "more_body": bool(parts)}
        await asyncio.sleep(3600)   # a client that stays connected says nothing more

    async def send(message):
        if message["type"] == "http.response.start":
            status[0] = message["status"]
        elif message["type"] == "http.response.body":
            received.extend(message.get("body", b""))
            ended[0] = not message.get("more_body", False)
            await asyncio.sleep(send_delay_s)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST" if body else "GET",
             "scheme": "http", "path": "/f", "raw_path": b"/f", "query_string": b"", "root_path": "",
             "server": ("testserver", 80), "client": ("127.0.0.1", 5000), "headers": [(b"host", b"testserver")]}

    async def run():
        try:
            await asyncio.wait_for(app(scope, receive, send), 30)
        except Exception:   # the old middleware's 408 escaped mid-response
            pass

    asyncio.run(run())
    return status[0], bytes(received), ended[0]


@pytest.mark.parametrize("with_body", [False, True])
def test_a_slow_download_outlives_the_body_deadline(tmp_path, with_body):
    """A 2-MB file sent in Starlette's chunks at 50 ms each behind a 0.2-s body deadline: every byte."""
    path = tmp_path / "big.bin"
    data = bytes(range(256)) * (2 * 4096)
    path.write_bytes(data)
    start = time.monotonic()
    status, received, ended = _serve_file(path, deadline_s=0.2, send_delay_s=0.05,
                                          body=[b"a" * 10, b"b" * 10] if with_body else None)
    assert time.monotonic() - start > 0.4   # the response did outlive the deadline
    assert status == 200 and ended and received == data


def test_a_body_that_never_ends_still_gets_its_408(tmp_path):
    from starlette.exceptions import HTTPException

    from learnest.service.api.server import BodyDeadline

    async def app(scope, receive, send):
        while (await receive()).get("more_body"):
            pass

    async def receive():
        await asyncio.sleep(0.05)
        return {"type": "http.request", "body": b"x", "more_body": True}

    async def send(message):
        pass

    with pytest.raises(HTTPException) as err:
        asyncio.run(BodyDeadline(app, timeout_s=0.3, min_rate=1e6)({"type": "http"}, receive, send))
    assert err.value.status_code == 408
