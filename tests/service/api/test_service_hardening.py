"""Service hardening.  With no API key (the default), a page on another site must not be
able to start jobs through the user's browser (CSRF), and a server on localhost must not answer requests for
other host names (DNS rebinding).  The real app, the real forms; the attack is what a browser would send.
Numbers and dates out of range are a 422, not a 500."""
import pytest
from utils.service import MULTIPART_XYZ, flight_csv, raw_post, running_app, settings_for, upload


@pytest.fixture(scope="module")
def app_with_a_flight(tmp_path_factory):
    home = tmp_path_factory.mktemp("guard")
    with running_app(home) as client:
        response = upload(client, flight_csv(home / "logs" / "f.csv", seed=1))
        assert response.status_code == 201, response.text
        yield client, response.json()["id"]


def _jobs(client) -> int:
    return len(client.get("/jobs").json()["items"])


@pytest.mark.parametrize("headers", [
    {"Origin": "http://evil.example"},
    {"Origin": "null"},                                   # sandboxed frames and data: URLs send this
    {"Origin": "http://testserver.evil.example"},         # a look-alike name is another site
    {"Sec-Fetch-Site": "cross-site"},
    {"Referer": "http://evil.example/attack.html"},
])
def test_a_cross_site_form_post_starts_no_job(app_with_a_flight, headers):
    client, flight_id = app_with_a_flight
    before = _jobs(client)
    response = client.post("/ui/models", data={"name": "pwned", "flight_id": str(flight_id), "epochs": "1"},
                           headers=headers, follow_redirects=False)
    assert response.status_code == 403
    assert "cross-site request refused" in response.json()["detail"]
    assert _jobs(client) == before
    # the JSON routes are guarded the same way (a browser can POST there too)
    assert client.post("/models", json={"name": "pwned", "flight_id": flight_id}, headers=headers).status_code == 403


def test_a_same_site_form_post_and_a_plain_client_still_work(app_with_a_flight):
    client, flight_id = app_with_a_flight
    before = _jobs(client)
    form = {"name": "ok", "flight_id": str(flight_id), "epochs": "1"}
    same_site = client.post("/ui/models", data=form, headers={"Origin": "http://testserver",
                                                              "Sec-Fetch-Site": "same-origin"},
                            follow_redirects=False)
    assert same_site.status_code == 303, same_site.text
    plain = client.post("/ui/models", data=form, follow_redirects=False)   # curl: no Origin, no Referer
    assert plain.status_code == 303, plain.text
    assert _jobs(client) == before + 2


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8000", "127.0.0.1.nip.io"])
def test_a_request_for_another_host_name_is_refused(app_with_a_flight, host):
    client, _ = app_with_a_flight
    response = client.get("/flights", headers={"Host": host})
    assert response.status_code == 400
    assert "is not served here" in response.json()["detail"] and "LEARNEST_ALLOWED_HOSTS" in response.json()["detail"]


def test_the_served_names_answer(app_with_a_flight):
    client, _ = app_with_a_flight
    for host in ("localhost:8000", "127.0.0.1", "[::1]:8000", "testserver"):
        assert client.get("/flights", headers={"Host": host}).status_code == 200, host


@pytest.mark.parametrize("header, name", [("localhost:8000", "localhost"), ("[::1]:8000", "::1"), ("::1", "::1"),
                                          ("Example.ORG", "example.org"), ("10.0.0.5:80", "10.0.0.5")])
def test_host_name_strips_the_port(header, name):
    from learnest.service.api.request_guard import host_name

    assert host_name(header) == name


# -- out-of-range ids and dates are a 422 that says so, never a 500 -------------------
@pytest.mark.parametrize("path", ["/flights/9223372036854775808", "/jobs/99999999999999999999",
                                  "/flights?offset=9223372036854775808", "/jobs?offset=18446744073709551616",
                                  "/models/quad/versions/9223372036854775808", "/evaluations/9223372036854775808",
                                  "/ui/flights/9223372036854775808", "/?offset=9223372036854775808",
                                  "/flights?since=0001-01-01T00:00:00%2B14:00",
                                  "/flights?until=9999-12-31T23:00:00-05:00"])
def test_out_of_range_numbers_are_a_422_not_a_500(app_with_a_flight, path):
    client, _ = app_with_a_flight
    response = client.get(path)
    assert response.status_code == 422, (path, response.status_code, response.text[:300])
    # the largest id that can exist is a plain 404
    assert client.get("/flights/9223372036854775807").status_code == 404


# -- the API key is checked before an upload's body is read ------------------------------
def _multipart(boundary: bytes, size: int, chunk: int = 1 << 16) -> list[bytes]:
    head = (b"--" + boundary + b'\r\nContent-Disposition: form-data; name="files"; filename="big.csv"\r\n'
            b"Content-Type: text/csv\r\n\r\n")
    return [head] + [b"1" * chunk] * (size // chunk) + [b"\r\n--" + boundary + b"--\r\n"]


def test_an_upload_without_the_key_is_refused_before_its_body_is_read(tmp_path):
    """Raw ASGI, so the test sees how much of the body the app pulls: none (FastAPI used to spool all of it to
    a temp file - an unnamed one on Linux, so watching the temp folder would prove nothing)."""

    from fastapi.testclient import TestClient
    from utils.service import shared_pool

    from learnest.service.app.factory import create_app

    app = create_app(settings_for(tmp_path, api_key="sesame"), executor=shared_pool(), scheduler=False)
    chunks = _multipart(b"xyz", 8 << 20)

    def post(headers: list) -> tuple[int, int]:
        return raw_post(app, "/flights", chunks, [MULTIPART_XYZ, *headers])[:2]

    with TestClient(app):   # the lifespan: database, services
        assert post([]) == (401, 0)
        assert post([(b"x-api-key", b"wrong")]) == (401, 0)
        status, pulled = post([(b"x-api-key", b"sesame")])   # with the key the body is read (and is no flight)
        assert status == 422 and pulled == len(chunks)


# -- no orphan blob on a name collision; a crashed upload's temp folder goes ---------------
def _blob_state(home):
    from utils.service import blob_files

    from learnest.service.storage.database import Database, referenced_blobs

    db = Database(settings_for(home).url)
    try:
        return blob_files(home), referenced_blobs(db)
    finally:
        db.dispose()


def test_a_flight_name_collision_leaves_no_orphan_blob(tmp_path):
    with running_app(tmp_path) as client:
        first = upload(client, flight_csv(tmp_path / "a", seed=3), names=["same.csv"])
        second = upload(client, flight_csv(tmp_path / "b", seed=4), names=["same.csv"])
        assert (first.status_code, second.status_code) == (201, 201)
        assert first.json()["name"] == "same" and second.json()["name"] == f"same-{second.json()['sha256'][:8]}"
        stored, referenced = _blob_state(tmp_path)
    assert stored == referenced and len(stored) == 4   # two raw files, two normalized flights


CRASHING_UPLOAD = """
import sys, time
from pathlib import Path
from learnest.service.storage.blobs import BlobStore
with BlobStore(Path(sys.argv[1])).temp_dir() as directory:
    (directory / "upload_0.csv").write_bytes(b"1" * 100_000)
    print(directory.name, flush=True)
    time.sleep(600)
"""


def test_a_crashed_uploads_temp_folder_is_removed_when_the_store_opens(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from learnest.service.storage.blobs import BlobStore

    root = tmp_path / "blobs"
    crashed = subprocess.Popen([sys.executable, "-c", CRASHING_UPLOAD, str(root)], stdout=subprocess.PIPE, text=True)
    name = crashed.stdout.readline().strip()
    os.kill(crashed.pid, signal.SIGKILL)   # no cleanup: what a crash or an OOM kill does
    crashed.wait()
    assert (root / ".tmp" / name).is_dir()
    with BlobStore(root).temp_dir() as ours:   # a live upload of this process ...
        BlobStore(root)                        # ... while another server process starts
        assert ours.is_dir()
        assert not (root / ".tmp" / name).exists()


# -- a blob folder that cannot be written; DELETE; server paths in job errors ------------
def test_an_upload_to_a_blob_folder_that_cannot_be_written_is_a_507_storing_nothing(tmp_path):
    from learnest.ingest.flight import sha256_file

    log = flight_csv(tmp_path / "logs", seed=5)
    with running_app(tmp_path / "home") as client:
        blocked = tmp_path / "home" / "blobs" / sha256_file(log)[:2]
        blocked.write_text("")   # a file where the raw file's blob folder must go: mkdir fails (even as root)
        response = upload(client, log)
        assert response.status_code == 507, response.text
        detail = response.json()["detail"]
        assert "nothing was stored" in detail and str(tmp_path) not in detail
        assert client.get("/flights").json()["total"] == 0
        stored, _ = _blob_state(tmp_path / "home")
        assert stored == set()   # the normalized flight written before the failure was removed again
        assert list((tmp_path / "home" / "blobs" / ".tmp").iterdir()) == []
        blocked.unlink()
        assert upload(client, log).status_code == 201


def test_delete_answers_204_when_a_blob_cannot_be_removed_and_the_sweep_removes_it_later(tmp_path, monkeypatch):
    import pathlib

    from learnest.service.jobs.services import sweep_orphan_blobs
    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database

    blobs_root = str(tmp_path / "blobs")
    unlink = pathlib.Path.unlink

    def read_only_blobs(path, *args, **kwargs):   # what a read-only blob folder does to unlink
        if str(path).startswith(blobs_root) and "/.tmp" not in str(path):
            raise PermissionError(13, "Read-only file system")
        return unlink(path, *args, **kwargs)

    with running_app(tmp_path) as client:
        flight_id = upload(client, flight_csv(tmp_path / "logs", seed=6)).json()["id"]
        kept = set(_blob_state(tmp_path)[0])
        with monkeypatch.context() as patch:
            patch.setattr(pathlib.Path, "unlink", read_only_blobs)
            response = client.delete(f"/flights/{flight_id}")
        assert response.status_code == 204, response.text   # the row is gone: say so, not 500
        assert client.get(f"/flights/{flight_id}").status_code == 404
    stored, referenced = _blob_state(tmp_path)
    assert stored == kept and referenced == set()            # orphans now, harmless
    db = Database(settings_for(tmp_path).url)
    try:
        assert set(sweep_orphan_blobs(db, BlobStore(tmp_path / "blobs"))) == kept
    finally:
        db.dispose()


def test_a_job_error_shows_no_server_path(tmp_path):
    from utils.service import wait_for_job

    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import FlightRecord

    with running_app(tmp_path) as client:
        flight_id = upload(client, flight_csv(tmp_path / "logs", seed=7)).json()["id"]
        db = Database(settings_for(tmp_path).url)
        with db.transaction() as session:
            sha = session.get(FlightRecord, flight_id).flight_blob
        db.dispose()
        (tmp_path / "blobs" / sha[:2] / sha[2:]).unlink()   # the normalized flight is gone from the disk
        job_id = client.post("/models", json={"name": "lost", "flight_id": flight_id, "epochs": 1}).json()["job_id"]
        job = wait_for_job(client, job_id)
        assert job["state"] == "failed"
        assert "FileNotFoundError" in job["error"] and sha[2:] in job["error"]   # still says what is missing
        assert str(tmp_path) not in job["error"] and "/blobs/" not in job["error"]
        version = client.get("/models/lost/versions/1").json()
        assert str(tmp_path) not in version["error"]
        assert str(tmp_path) not in client.get(f"/ui/jobs/{job_id}").text


def test_error_message_keeps_file_names_and_drops_folders():
    from learnest.service.jobs.runner import error_message

    err = FileNotFoundError(2, "No such file or directory", "/srv/learnest/blobs/ab/cdef")
    assert error_message(err) == "FileNotFoundError: [Errno 2] No such file or directory: '.../cdef'"
    assert error_message(ValueError("velocity in m/s/s, 1/2 of it")) == "velocity in m/s/s, 1/2 of it"
