"""Uploads are decoded in worker processes, bounded in number, waiting room and time."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from utils.service import blob_files, flight_csv, running_app, settings_for, shared_pool, upload
from utils.slow_decode import sleepy_read


@pytest.fixture(scope="module")
def sleepy_pool():
    from learnest.service.jobs.decoding import DecodePool

    pool = DecodePool(workers=1, waiting=0, timeout_s=0.5, read=sleepy_read)
    pool.start()
    pool.wait_started()
    yield pool
    pool.shutdown()


def test_a_decode_past_the_time_limit_is_refused_naming_it_and_stores_nothing(tmp_path, data_dir, sleepy_pool):
    from fastapi.testclient import TestClient

    from learnest.service.app.factory import create_app

    app = create_app(settings_for(tmp_path / "home"), executor=shared_pool(), decoder=sleepy_pool, scheduler=False)
    with TestClient(app) as client:
        started = time.monotonic()
        answer = upload(client, flight_csv(data_dir, 3))
        assert time.monotonic() - started < 10   # the limit (0.5 s), not the 60 s the decode would take
        assert answer.status_code == 422
        assert "LEARNEST_DECODE_TIMEOUT_S" in answer.json()["detail"] and "flight3.csv" in answer.json()["detail"]
        assert client.get("/flights").json()["total"] == 0
    assert blob_files(tmp_path / "home") == set()
    assert not any((tmp_path / "home" / "blobs" / ".tmp").iterdir())   # the staged copy is gone too


def test_the_killed_decoder_is_replaced_and_the_next_upload_is_decoded(tmp_path, data_dir):
    """After a refusal the pool's worker was killed; the shared pool of the other tests still decodes, and a
    pool whose worker timed out decodes a real file again (no slot is lost)."""
    from learnest.service.jobs.decoding import DecodePool
    from learnest.service.jobs.reading import StagedFile, read_uploaded_flight

    pool = DecodePool(workers=1, waiting=0, timeout_s=0.5, read=sleepy_read)
    path = flight_csv(data_dir, 4)
    staged = [StagedFile("flight4.csv", path, "0" * 64, path.stat().st_size, "log")]
    try:
        with pytest.raises(Exception, match="0.5 s limit"):
            pool.decode(staged)
        pool.read, pool.timeout_s = read_uploaded_flight, 60   # a cold process imports the readers: seconds
        assert len(pool.decode(staged).t) > 100   # the replacement process decodes the file
    finally:
        pool.shutdown()


def test_uploads_beyond_the_workers_and_the_waiting_room_get_503_at_once(sleepy_pool, tmp_path):
    from learnest.service.jobs.decoding import DecodeBusy

    outcome: list[str] = []

    def occupy():
        try:
            sleepy_pool.decode([])
        except Exception as err:   # the time limit
            outcome.append(str(err))

    first = threading.Thread(target=occupy)
    first.start()
    time.sleep(0.1)     # the one worker is busy and there is no waiting room
    started = time.monotonic()
    with pytest.raises(DecodeBusy, match="LEARNEST_DECODE_QUEUE") as refused:
        sleepy_pool.decode([])
    assert refused.value.status == 503 and time.monotonic() - started < 0.2
    assert refused.value.headers == {"Retry-After": "5"}
    first.join(5)
    assert outcome and "limit" in outcome[0]


def test_an_upload_is_decoded_in_another_process(tmp_path, data_dir):
    """The server process never runs the readers: a flight comes back from the worker, stored."""
    import os

    with running_app(tmp_path / "home") as client:
        answer = upload(client, flight_csv(data_dir, 5))
        assert answer.status_code == 201, answer.text
        decoder = client.app.state.services.decoder
        pids = {p.pid for pool in decoder._all for p in (pool._processes or {}).values()}
        assert pids and os.getpid() not in pids
    assert Path(tmp_path / "home" / "learnest.db").exists()
