"""Hostile input, second round: downloads past the body deadline, SQLite bags whose rows SQLite computes,
jobs whose failure cannot be recorded, quotas on the flights actually used, proxy headers, form uploads
without the key, large pages, deep YAML, huge integers, deletions during an evaluation, a full database.
The real app on SQLite files; the attacks are what a client would send."""
from __future__ import annotations

import asyncio
import time

import pytest
from utils.service import MULTIPART_XYZ, raw_post


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
        asyncio.run(BodyDeadline(app, timeout_s=0.3, min_rate=1e6)(
            {"type": "http", "headers": [(b"content-length", b"100000")]}, receive, send))
    assert err.value.status_code == 408


# -- a .db3 is bounded by the bytes SQLite yields, whatever it computes ---------------------------------------
def _small_bag(tmp_path):
    from utils.analytic_flight import accelerometer_g, imu_times, mocap_times, true_position, true_quaternion

    from learnest.ingest.formats.rosbag.writer import BagWriter

    t, t_acc = mocap_times(), imu_times()
    with BagWriter(tmp_path / "bag", "sqlite3") as bag:
        bag.add_pose("/cf1/pose", t, true_position(t), true_quaternion(t))
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc))
    return bag.storage_file


def _rebuild_messages(path, data_sql: str, rows: int | None = None) -> None:
    """Replace the bag's messages by ``rows`` of them (all if None) whose data column is ``data_sql``, a
    virtual generated column: the file stays small, what SQLite yields does not."""
    import sqlite3

    with sqlite3.connect(path) as db:
        db.executescript(f"""
            ALTER TABLE messages RENAME TO old_messages;
            CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
                                  size INTEGER, data BLOB GENERATED ALWAYS AS ({data_sql}) VIRTUAL);
            INSERT INTO messages(id, topic_id, timestamp, size)
                SELECT id, topic_id, timestamp, length(data) FROM old_messages {f'LIMIT {rows}' if rows else ''};
            DROP TABLE old_messages;""")
    with sqlite3.connect(path) as db:
        db.execute("VACUUM")


@pytest.mark.parametrize("data_sql, rows", [("zeroblob(1000000)", 60),      # 60 MB from a few kB
                                            ("zeroblob(200000000)", 1)])      # one value past the value cap
def test_a_db3_whose_rows_sqlite_computes_is_refused_by_what_it_yields(tmp_path, data_sql, rows):
    from learnest.ingest import read_flights
    from learnest.ingest.flight import IngestError

    path = _small_bag(tmp_path)
    _rebuild_messages(path, data_sql, rows)
    assert path.stat().st_size < 200_000
    with pytest.raises(IngestError) as err:
        read_flights([path])
    assert "yields more than" in str(err.value) or "larger than" in str(err.value), str(err.value)
    assert path.name in str(err.value)


def test_a_db3_bomb_whose_path_holds_a_uri_character_is_still_refused(tmp_path):
    """A '#' in the path must not cut the file's SQLite URI short: the check reads this file (and
    creates no other), so the bomb is refused as it is under a plain name."""
    from learnest.ingest import read_flights
    from learnest.ingest.flight import IngestError

    built = _small_bag(tmp_path)     # written under a plain name (the bag writer cuts URIs at '#' itself)
    _rebuild_messages(built, "zeroblob(1000000)", 60)
    folder = built.parent.rename(tmp_path / "run#1")
    path = folder / built.name
    before = sorted(p.name for p in tmp_path.rglob("*"))
    with pytest.raises(IngestError) as err:
        read_flights([path])
    assert "yields more than" in str(err.value) or "larger than" in str(err.value), str(err.value)
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_a_db3_whose_messages_are_a_view_is_refused(tmp_path):
    import sqlite3

    from learnest.ingest import read_flights
    from learnest.ingest.flight import IngestError

    path = _small_bag(tmp_path)
    with sqlite3.connect(path) as db:   # an endless view: rows x size unbounded from a small file
        db.executescript("""
            ALTER TABLE messages RENAME TO old_messages;
            CREATE VIEW messages AS WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n)
                SELECT i AS id, 1 AS topic_id, i AS timestamp, zeroblob(1000) AS data FROM n;""")
    with pytest.raises(IngestError) as err:
        read_flights([path])
    assert "view" in str(err.value)


def test_a_db3_with_its_data_stored_or_computed_within_the_budget_still_reads(tmp_path):
    """The data column computed as itself (a generated copy of stored bytes): within budget, it reads."""
    from learnest.ingest import read_flights

    path = _small_bag(tmp_path)
    plain = read_flights([path])[0]
    import sqlite3

    with sqlite3.connect(path) as db:
        db.executescript("""
            ALTER TABLE messages RENAME TO old_messages;
            CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
                                  stored BLOB, data BLOB GENERATED ALWAYS AS (stored) VIRTUAL);
            INSERT INTO messages(id, topic_id, timestamp, stored) SELECT id, topic_id, timestamp, data
                FROM old_messages;
            DROP TABLE old_messages;""")
    again = read_flights([path])[0]
    assert again.p.shape == plain.p.shape and abs(again.p - plain.p).max() == 0.0


# -- nesting limits on every YAML shape ------------------------------------------------------------------------
DEEP_BLOCK_SEQUENCE = "- " * 260 + "x\n"
DEEP_BLOCK_MAPPING = "".join(" " * k + f"k{k}:\n" for k in range(200)) + " " * 200 + "1\n"


@pytest.mark.parametrize("text", [DEEP_BLOCK_SEQUENCE, DEEP_BLOCK_MAPPING, "a: " + "[" * 50 + "]" * 50 + "\n"])
def test_deep_yaml_of_every_shape_is_refused(tmp_path, text):
    from learnest.ingest.flight import IngestError
    from learnest.ingest.sidecar import read_sidecar

    path = tmp_path / "f_metadata.yaml"
    path.write_text(text)
    with pytest.raises(IngestError, match="nested more than 32 deep"):
        read_sidecar(path)
    path.write_text("a:\n  b:\n    - [1, {c: 2}]\n")   # a record's usual nesting reads
    assert read_sidecar(path) == {"a": {"b": [[1, {"c": 2}]]}}


def test_a_flight_with_a_deep_block_yaml_sidecar_is_refused_naming_the_sidecar(tmp_path):
    """A nesting cap refuses the upload, as docs/deployment.md says (it was stored, the sidecar dropped)."""
    from utils.service import flight_csv, running_app, upload

    csv = flight_csv(tmp_path / "logs", seed=2)
    sidecar = csv.with_name(f"{csv.stem}_metadata.yaml")
    sidecar.write_text(DEEP_BLOCK_SEQUENCE)
    with running_app(tmp_path / "home") as client:
        response = upload(client, csv, sidecar)
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert detail.startswith(sidecar.name) and "nested more than 32 deep" in detail
        assert "/" not in detail   # the file's name, not the server's folder it was staged in


# -- one integer-range rule for path, query, JSON and form values --------------------------------------------
HUGE = 99999999999999999999


@pytest.fixture(scope="module")
def app_with_a_model(tmp_path_factory):
    from utils.service import flight_csv, running_app, train, upload

    home = tmp_path_factory.mktemp("ints")
    with running_app(home) as client:
        flight_id = upload(client, flight_csv(home / "logs", seed=3)).json()["id"]
        train(client, "quad", flight_id)
        yield client, flight_id


@pytest.mark.parametrize("method, path, body", [
    ("post", "/evaluations", {"model": "quad:1", "flights": [HUGE]}),
    ("post", "/evaluations", {"model": "quad:1", "flights": [2**63]}),
    ("post", "/models", {"name": "quad", "flight_id": HUGE}),
    ("post", "/diagnoses", {"flights": [HUGE]}),
    ("put", "/models/quad/aliases/production", {"version": HUGE}),
])
def test_huge_integers_in_json_bodies_are_a_422(app_with_a_model, method, path, body):
    client, _ = app_with_a_model
    response = getattr(client, method)(path, json=body)
    assert response.status_code == 422, (path, response.status_code, response.text[:300])
    assert "9223372036854775807" in response.text


@pytest.mark.parametrize("path, form", [
    ("/ui/models", {"name": "quad", "flight_id": str(HUGE), "epochs": "1"}),
    ("/ui/evaluations", {"model": "quad:1", "flights": [str(HUGE)], "methods": ["ukf"]}),
    ("/ui/models/quad/aliases", {"alias": "production", "version": str(HUGE)}),
])
def test_huge_integers_in_forms_are_a_422_page(app_with_a_model, path, form):
    client, _ = app_with_a_model
    response = client.post(path, data=form, follow_redirects=False)
    assert response.status_code == 422, (path, response.status_code, response.text[:300])
    assert "9223372036854775807" in response.text


def test_the_largest_id_is_a_plain_404(app_with_a_model):
    client, _ = app_with_a_model
    response = client.post("/evaluations", json={"model": "quad:1", "flights": [2**63 - 1], "methods": ["ukf"]})
    assert response.status_code == 404, response.text


# -- the token of a form upload is checked before its body is read -------------------------------------------
def _upload_form(key: str | None, key_first: bool = True, size: int = 8 << 20) -> list[bytes]:
    """A multipart upload of one ``size``-byte file in 64-kB chunks, an api_key field before or after it."""
    field = (b'--xyz\r\nContent-Disposition: form-data; name="api_key"\r\n\r\n' + key.encode() + b"\r\n"
             if key else b"")
    head = (b'--xyz\r\nContent-Disposition: form-data; name="files"; filename="big.csv"\r\n'
            b"Content-Type: text/csv\r\n\r\n")
    chunks = [head] + [b"1" * (1 << 16)] * (size >> 16) + [b"\r\n"]
    if field:
        chunks = ([field] + chunks) if key_first else (chunks + [field])
    return chunks + [b"--xyz--\r\n"]


def _session_cookie(app, token: str) -> list[tuple[bytes, bytes]]:
    """The cookie header of a web session signed in with ``token`` (as POST /ui/signin makes it)."""
    from learnest.service.storage import tokens

    session_id = tokens.start_session(app.state.services.db, tokens.hash_token(token), 1.0)
    return [(b"cookie", f"learnest_session={session_id}".encode())]


def test_a_form_upload_without_a_session_is_refused_before_its_body_is_read(tmp_path):
    from fastapi.testclient import TestClient
    from utils.service import settings_for, shared_decoder, shared_pool

    from learnest.service.app.factory import create_app

    app = create_app(settings_for(tmp_path, api_key="sesame", key_failures=0), executor=shared_pool(),
                     decoder=shared_decoder(), scheduler=False)
    with TestClient(app):
        status, pulled, answer = raw_post(app, "/ui/flights", _upload_form(None), [MULTIPART_XYZ])
        assert (status, pulled) == (401, 0) and b"sign in" in answer        # not a byte of the body
        # a key typed into a form field is no way in any more: only the session's cookie (or a token header)
        status, pulled, _ = raw_post(app, "/ui/flights", _upload_form("sesame"), [MULTIPART_XYZ])
        assert (status, pulled) == (401, 0)
        stale = [(b"cookie", b"learnest_session=not-a-session")]
        assert raw_post(app, "/ui/flights", _upload_form(None), [MULTIPART_XYZ, *stale])[:2] == (401, 0)
        # signed in: the body is read
        chunks = _upload_form(None)
        status, pulled, answer = raw_post(app, "/ui/flights", chunks, [MULTIPART_XYZ, *_session_cookie(app, "sesame")])
        assert status == 422 and pulled == len(chunks), (status, answer[:200])   # read, and no flight


def test_a_throttled_address_gets_429_before_its_form_files_are_read(tmp_path):
    """Its wrong tokens get 429 before any byte of the body; a right session still passes."""
    from fastapi.testclient import TestClient
    from utils.service import settings_for, shared_decoder, shared_pool

    from learnest.service.app.factory import create_app

    app = create_app(settings_for(tmp_path, api_key="sesame", key_failures=2), executor=shared_pool(),
                     decoder=shared_decoder(), scheduler=False)
    wrong = [(b"authorization", b"Bearer guess")]
    with TestClient(app):
        for _ in range(2):
            assert raw_post(app, "/ui/flights", _upload_form(None), [MULTIPART_XYZ, *wrong])[0] == 401
        status, pulled, _ = raw_post(app, "/ui/flights", _upload_form(None), [MULTIPART_XYZ, *wrong])
        assert (status, pulled) == (429, 0)
        chunks = _upload_form(None, size=1 << 16)
        status, pulled, _ = raw_post(app, "/ui/flights", chunks, [MULTIPART_XYZ, *_session_cookie(app, "sesame")])
        assert status != 429 and pulled == len(chunks)   # the whole form read: past the guard


def test_the_upload_form_carries_no_key_field_the_session_is_the_key(tmp_path):
    from utils.service import running_app

    with running_app(tmp_path, api_key="sesame") as client:
        assert client.post("/ui/signin", data={"token": "sesame"}).status_code == 200   # 303 to /, followed
        page = client.get("/").text
        assert "type='file'" in page and "name='api_key'" not in page and "signed in as <b>api-key</b>" in page


# -- proxy headers are believed only from configured proxies ---------------------------------------------------
def _post_with_forwarded(port: int, key: str, forwarded: str) -> int:
    import http.client

    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    connection.request("POST", "/models", body=b"{}", headers={"Host": "localhost", "X-API-Key": key,
                                                               "X-Forwarded-For": forwarded,
                                                               "Content-Type": "application/json"})
    status = connection.getresponse().status
    connection.close()
    return status


def test_a_rotating_x_forwarded_for_does_not_escape_the_key_throttle(tmp_path):
    from utils.service import live_server

    with live_server(tmp_path, api_key="s3cret", key_failures=3) as port:
        answers = [_post_with_forwarded(port, "guess", f"10.0.0.{k}") for k in range(6)]
        assert answers == [401, 401, 401, 429, 429, 429]
        # nor can a chosen header lock out another address: the throttle counts the peer (here: loopback)


def test_a_configured_proxy_names_the_client(tmp_path):
    from utils.service import live_server

    with live_server(tmp_path, api_key="s3cret", key_failures=2, trusted_proxies="127.0.0.1") as port:
        assert [_post_with_forwarded(port, "guess", "10.0.0.1") for _ in range(3)] == [401, 401, 429]
        assert _post_with_forwarded(port, "guess", "10.0.1.2") == 401   # another client network behind the proxy


# -- a job reaches "failed" even when recording its failure fails --------------------------------------------
def _arm_refusal(db, armed: bool) -> None:
    """A real SQLite trigger that refuses to record a job's failure while armed, as a full disk refuses
    every write (the database itself says no; nothing in Python is replaced)."""
    from sqlalchemy import text

    with db.engine.begin() as connection:
        connection.execute(text("CREATE TABLE IF NOT EXISTS refusal (armed INTEGER NOT NULL)"))
        connection.execute(text("DELETE FROM refusal"))
        connection.execute(text("INSERT INTO refusal VALUES (:armed)"), {"armed": int(armed)})
        connection.execute(text(
            "CREATE TRIGGER IF NOT EXISTS refuse_failed BEFORE UPDATE OF state ON jobs "
            "WHEN NEW.state = 'failed' AND (SELECT armed FROM refusal) "
            "BEGIN SELECT RAISE(ABORT, 'database or disk is full'); END"))


def test_a_job_whose_failure_cannot_be_recorded_fails_once_the_database_takes_it(tmp_path, monkeypatch):
    from learnest.service.jobs import runner as runner_module
    from learnest.service.jobs.runner import JobRunner
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Job

    monkeypatch.setattr(runner_module, "RECORD_RETRIES_S", (0.05,))   # fewer waits before the heartbeat's turn
    db = Database(f"sqlite:///{tmp_path / 'learnest.db'}")
    db.migrate()
    runner = JobRunner(db)
    runner.start()
    try:
        with db.transaction() as session:
            job_id = runner.create(session, "training").id
        _arm_refusal(db, True)

        def work(_ctx):
            raise RuntimeError("training diverged")

        runner.run(job_id, work)   # the failure cannot be recorded: the job row still says running
        with db.transaction() as session:
            assert session.get(Job, job_id).state == "running"
        runner.beat()              # still refused: kept, and the sweep does not fail it as an orphan
        with db.transaction() as session:
            assert session.get(Job, job_id).state == "running"
        _arm_refusal(db, False)    # space again
        runner.beat()
        with db.transaction() as session:
            job = session.get(Job, job_id)
            assert job.state == "failed" and job.error == "RuntimeError: training diverged"
    finally:
        runner.shutdown()


def test_the_sweep_fails_a_running_job_that_no_thread_runs(tmp_path):
    """A job of this server left "running" with no thread on it (its worker stopped without a word): the lease
    is alive, yet the heartbeat's sweep fails it."""
    from sqlalchemy import update

    from learnest.service.jobs.runner import ORPHAN_REASON, JobRunner
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Job

    db = Database(f"sqlite:///{tmp_path / 'learnest.db'}")
    db.migrate()
    runner = JobRunner(db)
    runner.start()
    try:
        with db.transaction() as session:
            orphan = runner.create(session, "training").id
            queued = runner.create(session, "training").id
        with db.transaction() as session:
            session.execute(update(Job).where(Job.id == orphan).values(state="running"))
        assert runner.sweep() == [orphan]
        with db.transaction() as session:
            assert session.get(Job, orphan).state == "failed" and session.get(Job, orphan).error == ORPHAN_REASON
            assert session.get(Job, queued).state == "queued"
    finally:
        runner.shutdown()


# -- a full database: 507, and no SQL in a job's error ---------------------------------------------------------
def test_an_upload_to_a_full_database_is_a_507_and_stores_nothing(tmp_path):
    """The database on a 1-MB tmpfs (its own mount namespace: `unshare`), the blobs beside the test: a file
    fills the tmpfs, an upload gets 507 naming the full database (no SQL); the file removed, it stores."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    if shutil.which("unshare") is None or subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode:
        pytest.skip("needs `unshare -rm` (user and mount namespaces) to mount a small tmpfs")
    from utils.service import flight_csv

    csv = flight_csv(tmp_path / "logs", seed=4)
    script = Path(__file__).resolve().parents[2] / "utils" / "full_database.py"
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(["unshare", "-rm", sys.executable, str(script), str(mount), str(tmp_path / "home"),
                           str(csv)], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    answers = dict(line.split(" ", 1) for line in done.stdout.splitlines() if line[:1].isupper())
    status, detail = answers["FULL"].split(" ", 1)
    assert status == "507" and "database is full" in detail and "SQL" not in detail, answers["FULL"]
    assert answers["LISTED"] == "0" and answers["FREED"].split()[0] == "201"


def test_a_job_error_from_the_database_shows_no_sql():
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from learnest.service.jobs.runner import error_message

    full = OperationalError("BEGIN IMMEDIATE", {}, sqlite3.OperationalError("database or disk is full"))
    assert "[SQL: BEGIN IMMEDIATE]" in str(full)
    message = error_message(full)
    assert "database is full" in message and "SQL" not in message and "BEGIN" not in message
    other = OperationalError("UPDATE jobs SET state=?", ["failed"], sqlite3.OperationalError("disk I/O error"))
    assert error_message(other) == "database error: disk I/O error"


# -- quotas on the flights a job actually uses ------------------------------------------------------------------
def test_the_diagnosis_quota_is_charged_on_the_flights_it_fits(tmp_path):
    """A short flight that fails the quality checks named first is dropped by the diagnosis, which then fits
    the big one: the quota must see the big one ([bad, big] refused exactly as [big] is)."""
    import math

    from utils.service import flight_csv, running_app, upload

    from learnest.service.jobs.training import training_config

    budget = 2e7
    with running_app(tmp_path / "home", max_training_work=budget) as client:
        bad = upload(client, flight_csv(tmp_path / "logs", seed=5, seconds=7.0)).json()
        big = upload(client, flight_csv(tmp_path / "logs", seed=6, seconds=40.0)).json()
        assert not bad["quality"]["ok"] and big["quality"]["ok"], (bad["quality"], big["quality"])
        hidden = training_config({})["hidden"]
        epochs = math.floor(budget / (big["samples"] * hidden)) + 1       # just past the budget on the big one
        assert epochs * bad["samples"] * hidden <= budget                   # ... well within it on the bad one
        for flights in ([big["id"]], [bad["id"], big["id"]]):
            refused = client.post("/diagnoses", json={"flights": flights, "epochs": epochs})
            assert refused.status_code == 422, (flights, refused.status_code, refused.text[:300])
            assert "LEARNEST_MAX_TRAINING_WORK" in refused.json()["detail"]
            assert f"x {big['samples']} x" in refused.json()["detail"]
        accepted = client.post("/diagnoses", json={"flights": [bad["id"], big["id"]], "epochs": epochs - 1})
        assert accepted.status_code == 202, accepted.text
        client.post(f"/jobs/{accepted.json()['job_id']}/cancel")


# -- a flight deleted during its evaluation takes its cached results with it ------------------------------------
def _results_of(db, sha: str) -> list:
    from sqlalchemy import select

    from learnest.service.storage.tables import Result

    with db.transaction() as session:
        return list(session.scalars(select(Result.id).where(Result.flight_sha256 == sha)))


def test_a_result_stored_after_its_flight_was_deleted_is_not_cached(app_with_a_model):
    """The moment an evaluation finishes a flight that was deleted meanwhile: nothing is cached, and the
    estimates blob is handed back to be collected."""
    from utils.service import flight_csv, upload

    from learnest.service.jobs.result_cache import store_result
    from learnest.service.operations.deletion import delete_flight
    from learnest.service.storage.database import discard_blobs

    client, _ = app_with_a_model
    services = client.app.state.services
    flight = upload(client, flight_csv(services.settings.home / "logs", seed=7)).json()
    from learnest.service.storage.registry import get_version

    with services.db.transaction() as session:
        version_id = get_version(session, "quad", 1).id
    blob = services.blobs.put_bytes(b"estimates of a flight that is gone")
    delete_flight(services.db, services.blobs, flight["id"])
    returned = store_result(services.db, flight["sha256"], version_id, "key", flight["id"], {"flight": "x"}, None,
                            blob)
    assert returned == blob and _results_of(services.db, flight["sha256"]) == []
    discard_blobs(services.db, services.blobs, [returned])
    assert not services.blobs.path(blob).exists()


def test_deleting_a_flight_while_its_evaluation_runs_leaves_no_cached_result(app_with_a_model):
    from utils.service import blob_files, flight_csv, upload, wait_for_job

    client, _ = app_with_a_model
    services = client.app.state.services
    flight = upload(client, flight_csv(services.settings.home / "logs", seed=8, seconds=30.0)).json()
    before = blob_files(services.settings.home)
    accepted = client.post("/evaluations", json={"model": "quad:1", "flights": [flight["id"]],
                                                 "methods": ["ukf", "knode-ukf", "mhe"]}).json()
    deadline = time.monotonic() + 60
    while client.get(f"/jobs/{accepted['job_id']}").json()["state"] == "queued" and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)   # the flight's task is under way (the MHE takes seconds on a 30-s flight)
    assert client.delete(f"/flights/{flight['id']}").status_code == 204
    job = wait_for_job(client, accepted["job_id"])
    assert job["state"] == "succeeded", job
    assert _results_of(services.db, flight["sha256"]) == []
    # the flight's own blobs went with it, and no estimates blob stayed behind
    flight_blobs = before - blob_files(services.settings.home)
    assert flight_blobs and blob_files(services.settings.home) == before - flight_blobs


# -- page figures decimated to what a screen shows, and cached ------------------------------------------------
def test_decimation_keeps_every_peak_in_bounded_points():
    import numpy as np

    from learnest.service.web.zoomable import MAX_POINTS, decimation

    rng = np.random.default_rng(0)
    y = rng.normal(size=226_000)
    y[123_457], y[200_001] = 50.0, -40.0          # single-sample spikes
    y[50_000:50_010] = np.nan                       # a gap
    index = decimation(y)
    assert index is not None and len(index) <= MAX_POINTS + MAX_POINTS // 2 + 2
    assert 123_457 in index and 200_001 in index and index[0] == 0 and index[-1] == len(y) - 1
    assert np.isnan(y[index]).any()                 # the gap stays a gap
    assert np.all(np.diff(index) > 0)
    assert decimation(np.arange(MAX_POINTS)) is None


def test_a_long_flights_page_is_bounded_and_served_from_the_cache(tmp_path):
    import json
    import re

    from utils.service import flight_csv, running_app, upload

    from learnest.service.web.page_cache import pages
    from learnest.service.web.zoomable import MAX_POINTS

    pages.clear()
    with running_app(tmp_path / "home") as client:
        flight = upload(client, flight_csv(tmp_path / "logs", seed=9, seconds=300.0), cut="none").json()
        assert flight["samples"] > 25_000
        first = client.get(f"/ui/flights/{flight['id']}")
        assert first.status_code == 200
        stored = []                                       # what the second request draws and stores: nothing
        store = pages._store
        pages._store = lambda key, value: (stored.append(key), store(key, value))[1]   # type: ignore[method-assign]
        try:
            again = client.get(f"/ui/flights/{flight['id']}")
        finally:
            pages._store = store                          # type: ignore[method-assign]
    assert len(pages) >= 1 and stored == [] and again.text == first.text
    assert len(first.content) < 2_000_000, len(first.content)
    block = re.search(r"<script type='application/json'[^>]*>(.*?)</script>", first.text, re.DOTALL)
    spec = json.loads(block[1])
    assert spec["data"] and all(len(trace["y"]) <= MAX_POINTS + MAX_POINTS // 2 + 2 for trace in spec["data"])
    assert all(len(trace["x"]) == len(trace["y"]) for trace in spec["data"])


def test_a_download_that_starts_after_the_body_deadline_is_complete(tmp_path):
    """A GET whose answer takes longer than the body deadline to prepare (a large export is written first):
    its file still arrives whole (the first body part, asked for late, is no client's delay)."""
    from starlette.applications import Starlette
    from starlette.responses import FileResponse
    from starlette.routing import Route

    from learnest.service.api.server import BodyDeadline

    path = tmp_path / "export.csv"
    data = b"x,y\n" * 300_000
    path.write_bytes(data)

    async def export(request):
        await asyncio.sleep(0.5)     # writing the export
        return FileResponse(path)

    app = BodyDeadline(Starlette(routes=[Route("/e", export)]), timeout_s=0.2, min_rate=1e6)
    for headers in ([], [(b"content-length", b"0")]):
        assert _get_late(app, headers) == (True, data)


def _get_late(app, headers: list) -> tuple[bool, bytes]:
    """GET /e from ``app`` with a client that sends its (empty) body at once and then stays connected;
    -> (whether the response ended normally, its body)."""
    asked, received, ended = [0], bytearray(), [False]

    async def receive():
        asked[0] += 1
        if asked[0] == 1:
            return {"type": "http.request", "body": b"", "more_body": False}
        await asyncio.sleep(3600)

    async def send(message):
        if message["type"] == "http.response.body":
            received.extend(message.get("body", b""))
            ended[0] = not message.get("more_body", False)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET",
             "scheme": "http", "path": "/e", "raw_path": b"/e", "query_string": b"", "root_path": "",
             "server": ("testserver", 80), "client": ("127.0.0.1", 5000),
             "headers": [(b"host", b"testserver"), *headers]}
    asyncio.run(asyncio.wait_for(app(scope, receive, send), 30))
    return ended[0], bytes(received)


def test_the_sweep_fails_a_job_whose_worker_is_wedged_and_stops_it(tmp_path):
    """A job whose executor task never returns and writes no progress (a wedged worker): after ``stall_s`` the
    sweep fails it, and its thread stops the task (the worker process is killed)."""
    from learnest.service.jobs.executors import LocalPoolExecutor
    from learnest.service.jobs.runner import JobRunner
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Job

    db = Database(f"sqlite:///{tmp_path / 'learnest.db'}")
    db.migrate()
    runner = JobRunner(db, cancel_grace_s=0.5, stall_s=1.0)
    runner.start()
    executor = LocalPoolExecutor(max_workers=1)
    try:
        with db.transaction() as session:
            job_id = runner.create(session, "evaluation").id
        thread = runner.launch(job_id, lambda ctx: ctx.wait(executor, executor.submit(time.sleep, 3600)))
        deadline = time.monotonic() + 60
        while not runner.is_running(job_id) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        assert runner.sweep() == []               # within stall_s: a slow job is left alone
        time.sleep(1.2)
        assert runner.sweep() == [job_id]
        with db.transaction() as session:
            job = session.get(Job, job_id)
            assert job.state == "failed" and "no progress for 1 s" in job.error
        thread.result(timeout=30)                 # the thread stopped the task and returned
    finally:
        executor.shutdown()
        runner.shutdown()
