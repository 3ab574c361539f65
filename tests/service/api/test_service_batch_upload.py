"""POST /flights/batch and the upload form with the files of several flights: each file answered on its own
(stored / already stored / refused with its reason), one bad file not stopping the others, the kept stretch of
every stored flight as the simulator says, and the upload protections (API key before the body, size and count
limits) on the batch route too."""
from pathlib import Path

import pandas as pd
import pytest
import yaml
from utils.service import MULTIPART_XYZ, raw_post, running_app, settings_for

from learnest.ingest.sim.export import write_canonical_flight
from learnest.ingest.sim.recordings import flight_truth, recording

TOLERANCE_S = 0.1
SETTLE_S = 1.0     # ingest.align: take-off and landing transients trimmed


@pytest.fixture(scope="module")
def batch(sim, tmp_path_factory):
    """The files of four flights and two bad files, as a user picks them from a folder:
    a NanoBench CSV with its metadata sidecar, a uSD log that starts in the air, a Vicon export with its
    cfclient log, a ROS 2 bag's .db3 with its crazyflies.yaml; a NanoBench CSV without its accelerometer and a
    file that is no log at all."""
    folder = tmp_path_factory.mktemp("batch")
    truth = flight_truth(sim)
    whole = (truth.lift_off_s + SETTLE_S, truth.touch_down_s - SETTLE_S)        # simulation time, s
    in_air = truth.lift_off_s + 2.0
    files, expected = [], {}
    nb, = write_canonical_flight(recording(sim), "nanobench", folder, "hover_a")
    sidecar = folder / "hover_a_metadata.yaml"
    sidecar.write_text(yaml.safe_dump({"row_counts": {"vicon": len(pd.read_csv(nb)), "imu": len(pd.read_csv(nb))}}))
    files += [nb, sidecar]
    expected["hover_a"] = whole[1] - whole[0]
    usd, = write_canonical_flight(recording(sim, start_s=in_air, seed=1), "usd", folder, "log07")
    files.append(usd)
    expected["log07"] = whole[1] - in_air                    # kept from its start: it starts in the air
    pair = write_canonical_flight(recording(sim, seed=2), "vicon+cfclient", folder, "run3")
    files += pair
    expected["run3_vicon"] = whole[1] - whole[0]
    db3, = write_canonical_flight(recording(sim, hand_pickup=True, seed=4), "rosbag-db3", folder, "bag1")
    files += [db3, db3.with_name("bag1_crazyflies.yaml")]
    expected["bag1"] = whole[1] - whole[0]                    # the hand pick-up after landing is cut
    bad = folder / "log20.csv"
    pd.read_csv(nb).drop(columns=["imu_acc_x", "imu_acc_y", "imu_acc_z"]).to_csv(bad, index=False)
    junk = folder / "notes.bin"
    junk.write_bytes(b"\x00\xff" * 500)
    files[3:3] = [bad]           # the bad ones among the good ones, not at the end
    files.append(junk)
    return files, expected


def post_batch(client, paths, url="/flights/batch", **kwargs):
    return client.post(url, files=[("files", (p.name, Path(p).read_bytes())) for p in paths], **kwargs)


def test_a_batch_with_bad_files_stores_the_others_and_names_each_bad_one(batch, tmp_path):
    files, expected = batch
    with running_app(tmp_path / "home") as client:
        answer = post_batch(client, files)
        assert answer.status_code == 201, answer.text
        body = answer.json()
        by_file = {f["file"]: f for f in body["files"]}
        assert [f["file"] for f in body["files"]] == [p.name for p in files]     # one answer per file, in order
        refused = {name for name, f in by_file.items() if f["status"] == "refused"}
        assert refused == {"log20.csv", "notes.bin"}
        bad = by_file["log20.csv"]["message"]
        assert bad.startswith("log20.csv: ") and "imu_acc_x" in bad
        assert by_file["notes.bin"]["message"].startswith("notes.bin: unrecognised format")
        assert {e["file"] for e in body["errors"]} == refused
        # the others stored, grouped into flights as `learnest ingest` groups them
        assert sorted(f["name"] for f in body["flights"]) == sorted(expected)
        for flight in body["flights"]:
            assert flight["status"] == "stored"
            assert flight["duration_s"] == pytest.approx(expected[flight["name"]], abs=TOLERANCE_S), flight["name"]
        assert by_file["hover_a_metadata.yaml"]["flight_name"] == "hover_a"
        assert by_file["run3_cfclient.csv"]["flight_id"] == by_file["run3_vicon.csv"]["flight_id"]
        assert by_file["bag1_crazyflies.yaml"]["flight_name"] == "bag1"
        stored = client.get(f"/flights/{by_file['bag1.db3']['flight_id']}").json()
        assert "motor PWM" in stored["meta"]["flying_window"]["rule"]     # the sidecar named the motor topic
        assert client.get("/flights").json()["total"] == 4

        again = post_batch(client, files)             # the same files again: stored already, the bad ones as before
        assert again.status_code == 200, again.text
        statuses = {f["file"]: f["status"] for f in again.json()["files"]}
        assert {name for name, s in statuses.items() if s == "existing"} == set(by_file) - refused
        assert client.get("/flights").json()["total"] == 4

        nothing = post_batch(client, [files[3], files[-1]])
        assert nothing.status_code == 422 and len(nothing.json()["errors"]) == 2


def test_a_vicon_export_without_its_cfclient_log_is_refused_alone(batch, tmp_path):
    files, _ = batch
    vicon = next(p for p in files if p.name == "run3_vicon.csv")
    nanobench = next(p for p in files if p.name == "hover_a.csv")
    with running_app(tmp_path / "home") as client:
        body = post_batch(client, [vicon, nanobench]).json()
        assert [f["status"] for f in body["files"]] == ["refused", "stored"]
        assert body["files"][0]["message"] == "run3_vicon.csv: needs a cfclient log of the same flight given with it"


def test_the_upload_form_answers_per_file(batch, tmp_path):
    files, expected = batch
    with running_app(tmp_path / "home") as client:
        page = post_batch(client, files, url="/ui/flights", follow_redirects=False)
        assert page.status_code == 201 and page.headers["content-type"].startswith("text/html")
        assert "4 new flight(s) stored, 0 already stored, 2 file(s) refused" in page.text
        assert "log20.csv: a NanoBench CSV without the column(s) imu_acc_x" in page.text
        assert "notes.bin: unrecognised format" in page.text
        for name in expected:
            assert f">{name}</a>" in page.text
        assert client.get("/flights").json()["total"] == 4
        one = post_batch(client, files[:2], url="/ui/flights", follow_redirects=False)   # one flight: its page
        assert one.status_code == 303 and one.headers["location"].startswith("/ui/flights/")
        bad = post_batch(client, [files[3]], url="/ui/flights", follow_redirects=False)  # one refused: the error
        assert bad.status_code == 422 and "log20.csv" in bad.text and "upload-results" not in bad.text


def test_the_batch_route_keeps_the_upload_limits(batch, tmp_path, monkeypatch):
    files, _ = batch
    from learnest.service.api.routes import flights as routes

    with running_app(tmp_path / "small", max_upload_mb=0.05) as client:      # the size limit of every upload
        too_big = post_batch(client, files)
        assert too_big.status_code == 413 and "LEARNEST_MAX_UPLOAD_MB" in too_big.json()["detail"]
        assert client.get("/flights").json()["total"] == 0
    monkeypatch.setattr(routes, "MAX_BATCH_FILES", 3)
    with running_app(tmp_path / "count") as client:                          # the parser stops past the count
        too_many = client.post("/flights/batch", files=[("files", (f"x{i}.csv", b"t\n1\n")) for i in range(4)])
        assert too_many.status_code == 400 and "Too many files" in too_many.text
        assert client.get("/flights").json()["total"] == 0
    with running_app(tmp_path / "keyed", api_key="sesame") as client:        # the key, as on POST /flights
        assert post_batch(client, files[:2]).status_code == 401
        assert post_batch(client, files[:2], headers={"X-API-Key": "sesame"}).status_code == 201


def test_the_batch_key_is_checked_before_its_body_is_read(tmp_path):
    """Raw ASGI, so the test sees how much of the body the app pulls: none without the key."""

    from fastapi.testclient import TestClient
    from utils.service import shared_pool

    from learnest.service.app.factory import create_app

    app = create_app(settings_for(tmp_path, api_key="sesame"), executor=shared_pool(), scheduler=False)
    head = (b'--xyz\r\nContent-Disposition: form-data; name="files"; filename="big.csv"\r\n'
            b"Content-Type: text/csv\r\n\r\n")
    chunks = [head] + [b"1" * (1 << 16)] * 64 + [b"\r\n--xyz--\r\n"]

    def post(headers: list) -> tuple[int, int]:
        return raw_post(app, "/flights/batch", chunks, [MULTIPART_XYZ, *headers])[:2]

    with TestClient(app):
        assert post([]) == (401, 0)
        assert post([(b"x-api-key", b"wrong")]) == (401, 0)
        status, pulled = post([(b"x-api-key", b"sesame")])     # with the key the body is read (and is no flight)
        assert status == 422 and pulled == len(chunks)


def test_two_same_named_files_of_two_flights_in_one_batch_are_two_flights(sim, tmp_path):
    """A folder's worth posted with its sub-folders in the names (runA/eckart06.csv, runB/eckart06.csv): two
    flights, the second named with its content hash, each cut as the simulator says."""
    truth = flight_truth(sim)
    paths = [write_canonical_flight(recording(sim, seed=k), "nanobench", tmp_path / run, "eckart06")[0]
             for k, run in enumerate(("runA", "runB"))]
    with running_app(tmp_path / "home") as client:
        answer = client.post("/flights/batch", files=[("files", (f"{p.parent.name}/{p.name}", p.read_bytes()))
                                                      for p in paths])
        assert answer.status_code == 201, answer.text
        body = answer.json()
        assert [f["status"] for f in body["files"]] == ["stored", "stored"]
        first, second = body["flights"]
        assert first["name"] == "eckart06" and second["name"] == f"eckart06-{second['sha256'][:8]}"
        for flight in (first, second):
            assert flight["duration_s"] == pytest.approx(truth.touch_down_s - truth.lift_off_s - 2 * SETTLE_S,
                                                         abs=TOLERANCE_S)
