"""HTTP service, /flights: upload + dedupe, unreadable files, size limit, 404s, API key, concurrency,
raw and normalized downloads, delete — all over HTTP against a real SQLite file and blob folder."""
import io
import threading
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from utils.service import blob_files, flight_csv, running_app, settings_for, shared_pool, upload

from learnest.ingest import read_flights


def count_rows(home: Path, table=None) -> int:
    """Rows of ``table`` (default: flights) in the SQLite database under ``home``."""
    from sqlalchemy import create_engine, func, select

    from learnest.service.storage.tables import FlightRecord

    table = FlightRecord if table is None else table
    engine = create_engine(f"sqlite:///{home / 'learnest.db'}")
    with engine.connect() as connection:
        n = connection.scalar(select(func.count()).select_from(table))
    engine.dispose()
    return n


def test_upload_creates_then_dedupes(tmp_path, data_dir):
    home = tmp_path / "home"
    path = flight_csv(data_dir, 0)
    with running_app(home) as client:
        first = upload(client, path, vehicle="cf7", notes="circle")
        assert first.status_code == 201, first.text
        body = first.json()
        assert body["id"] >= 1 and body["adapter"] == "nanobench" and body["vehicle"] == "cf7"
        assert body["quality"] == {"ok": True, "issues": []} and body["duration_s"] > 5
        assert body["sources"][0]["name"] == path.name and first.headers["location"] == f"/flights/{body['id']}"

        # identical bytes under another name: the existing record, nothing new stored
        blobs_before = blob_files(home)
        again = upload(client, path, names=["renamed.csv"])
        assert again.status_code == 200 and again.json()["id"] == body["id"]
        assert blob_files(home) == blobs_before and count_rows(home) == 1

        detail = client.get(f"/flights/{body['id']}").json()
        assert detail["meta"]["adapter"] == "nanobench" and detail["clock_offset_s"] is None
        assert detail["meta"]["sources"][0]["path"] == path.name   # never our temp path
        assert str(tmp_path) not in str(detail)


def test_normalized_data_and_raw_file(tmp_path, data_dir):
    path = flight_csv(data_dir, 1)
    expected = read_flights([path])[0]
    with running_app(tmp_path / "home") as client:
        flight_id = upload(client, path).json()["id"]
        data = client.get(f"/flights/{flight_id}/data")
        assert data.status_code == 200 and data.headers["content-type"].startswith("text/csv")
        table = pd.read_csv(io.StringIO(data.text))
        assert list(table.columns) == ["t", "px", "py", "pz", "ax", "ay", "az", "qx", "qy", "qz", "qw"]
        np.testing.assert_allclose(table[["px", "py", "pz"]].to_numpy(), expected.p, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(table[["ax", "ay", "az"]].to_numpy(), expected.a_meas, rtol=1e-8, atol=1e-8)
        raw = client.get(f"/flights/{flight_id}/raw")
        assert raw.status_code == 200 and raw.content == path.read_bytes()
        assert path.name in raw.headers["content-disposition"]


def test_nanobench_metadata_sidecar_travels_with_its_csv(tmp_path, data_dir):
    path = flight_csv(data_dir, 2, name="B9_circle_rep1.csv")
    sidecar = data_dir / "B9_circle_rep1_metadata.yaml"
    sidecar.write_text(yaml.safe_dump({"crazyflie_id": "cf42", "row_counts": {"vicon": 1100, "imu": 1100}}))
    with running_app(tmp_path / "home") as client:
        response = upload(client, path, sidecar)
        assert response.status_code == 201, response.text
        body = response.json()
        assert body["vehicle"] == "cf42" and body["name"] == "B9_circle_rep1"
        assert [s["role"] for s in body["sources"]] == ["log", "sidecar"]
        raw = client.get(f"/flights/{body['id']}/raw")
        assert raw.headers["content-type"] == "application/zip"
        with zipfile.ZipFile(io.BytesIO(raw.content)) as bundle:
            assert sorted(bundle.namelist()) == sorted([path.name, sidecar.name])
            assert bundle.read(path.name) == path.read_bytes()


def test_unreadable_upload_is_422_and_stores_nothing(tmp_path, data_dir):
    from learnest.service.storage.tables import FlightFile

    home = tmp_path / "home"
    rng = np.random.default_rng(1)
    with running_app(home) as client:
        upload(client, flight_csv(data_dir, 3))
        rows, blobs = count_rows(home), blob_files(home)

        junk = client.post("/flights", files=[("files", ("mystery.bin", rng.bytes(5000)))])
        assert junk.status_code == 422 and junk.json()["detail"].startswith("mystery.bin: ")

        empty = client.post("/flights", files=[("files", ("empty.csv", b""))])
        assert empty.status_code == 422 and "empty.csv" in empty.json()["detail"]

        two = upload(client, flight_csv(data_dir, 4), flight_csv(data_dir, 5))
        assert two.status_code == 422 and "one flight per upload" in two.json()["detail"]

        missing = client.post("/flights", data={"vehicle": "cf1"})
        assert missing.status_code == 422 and "files" in missing.json()["detail"]

        assert count_rows(home) == rows and count_rows(home, FlightFile) == 1 and blob_files(home) == blobs
        assert not any((home / "blobs" / ".tmp").iterdir())   # staging folders are cleaned up


def test_client_file_names_are_never_paths(tmp_path, data_dir):
    home = tmp_path / "home"
    with running_app(home) as client:
        response = upload(client, flight_csv(data_dir, 6), names=["../../../etc/evil name.csv"])
        assert response.status_code == 201, response.text
        assert response.json()["sources"][0]["name"] == "evil name.csv"
        assert response.json()["name"] == "evil_name"
    assert not (tmp_path / "etc").exists() and not list(tmp_path.rglob("evil*"))


def test_upload_size_limit_is_413(tmp_path, data_dir):
    home = tmp_path / "home"
    path = flight_csv(data_dir, 7)   # ~240 kB
    with running_app(home, max_upload_mb=0.05) as client:
        response = upload(client, path)
        assert response.status_code == 413 and "LEARNEST_MAX_UPLOAD_MB" in response.json()["detail"]

        # a chunked body (no Content-Length) is cut off while it streams in
        def chunks():
            yield b"--b\r\nContent-Disposition: form-data; name=\"files\"; filename=\"x.csv\"\r\n\r\n"
            for _ in range(20):
                yield b"0" * 10_000
            yield b"\r\n--b--\r\n"
        streamed = client.post("/flights", content=chunks(),
                               headers={"content-type": "multipart/form-data; boundary=b"})
        assert streamed.status_code == 413
        assert count_rows(home) == 0 and blob_files(home) == set()


def test_list_filters_and_paging(tmp_path, data_dir):
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, flight_csv(data_dir, seed), vehicle=vehicle).json()["id"]
               for seed, vehicle in ((10, "cf1"), (11, "cf2"), (12, "cf1"))]
        page = client.get("/flights", params={"limit": 2}).json()
        assert page["total"] == 3 and [f["id"] for f in page["items"]] == ids[:2]
        assert [f["id"] for f in client.get("/flights", params={"offset": 2}).json()["items"]] == ids[2:]
        assert client.get("/flights", params={"vehicle": "cf1"}).json()["total"] == 2
        assert client.get("/flights", params={"quality": "ok"}).json()["total"] == 3
        assert client.get("/flights", params={"quality": "bad"}).json()["total"] == 0
        assert client.get("/flights", params={"since": "2000-01-01T00:00:00Z"}).json()["total"] == 3
        assert client.get("/flights", params={"until": "2000-01-01T00:00:00+02:00"}).json()["total"] == 0
        bad = client.get("/flights", params={"quality": "great", "limit": 0})
        assert bad.status_code == 422 and "quality (query)" in bad.json()["detail"] and "limit" in bad.json()["detail"]


def test_unknown_ids_are_404(tmp_path):
    with running_app(tmp_path / "home") as client:
        for method, url in [("get", "/flights/999"), ("get", "/flights/999/data"), ("get", "/flights/999/raw"),
                            ("delete", "/flights/999"), ("get", "/jobs/999"), ("get", "/models/nope"),
                            ("get", "/models/nope/versions/1"), ("get", "/models/nope/aliases/production"),
                            ("delete", "/models/nope/aliases/production"), ("get", "/evaluations/999"),
                            ("get", "/evaluations/999/report.html"), ("get", "/diagnoses/999/report.html")]:
            response = getattr(client, method)(url)
            assert response.status_code == 404, (method, url, response.text)
            assert "detail" in response.json()
        training = client.post("/models", json={"name": "m", "flight_id": 12345})
        assert training.status_code == 404 and "flight 12345" in training.json()["detail"]
        evaluation = client.post("/evaluations", json={"model": "nope:1", "flights": [1]})
        assert evaluation.status_code == 404


def test_bad_json_names_the_field(tmp_path):
    with running_app(tmp_path / "home") as client:
        response = client.post("/models", json={"name": "quad", "flight_id": "first", "epochs": 3})
        assert response.status_code == 422 and response.json()["detail"].startswith("flight_id: ")
        typo = client.post("/models", json={"name": "quad", "flight_id": 1, "epoch": 3})
        assert typo.status_code == 422 and "epoch:" in typo.json()["detail"]
        name = client.post("/models", json={"name": "../x", "flight_id": 1})
        assert name.status_code == 422 and "name:" in name.json()["detail"]
        broken = client.post("/models", content=b"{not json", headers={"content-type": "application/json"})
        assert broken.status_code == 422 and "JSON" in broken.json()["detail"]
        methods = client.post("/evaluations", json={"model": "m:1", "flights": [1], "methods": ["kalman"]})
        assert methods.status_code == 422 and "methods" in methods.json()["detail"]


def test_api_key_guards_every_write(tmp_path, data_dir):
    path = flight_csv(data_dir, 13)
    with running_app(tmp_path / "home", api_key="s3cret") as client:
        assert upload(client, path).status_code == 401
        assert upload(client, path, headers={"X-API-Key": "wrong"}).status_code == 401
        for method, url, body in [("post", "/models", {"name": "m", "flight_id": 1}),
                                  ("put", "/models/m/aliases/production", {"version": 1}),
                                  ("post", "/evaluations", {"model": "m:1", "flights": [1]})]:
            assert getattr(client, method)(url, json=body).status_code == 401, url
        assert client.delete("/flights/1").status_code == 401
        assert client.delete("/models/m/aliases/production").status_code == 401
        created = upload(client, path, headers={"X-API-Key": "s3cret"})
        assert created.status_code == 201
        assert client.get("/flights").status_code == 401                    # reads need it too
        assert client.get("/flights", headers={"X-API-Key": "s3cret"}).json()["total"] == 1
        assert client.delete(f"/flights/{created.json()['id']}", headers={"X-API-Key": "s3cret"}).status_code == 204


def test_concurrent_uploads_leave_exactly_the_right_rows(tmp_path, data_dir):
    from learnest.service.storage.tables import FlightFile

    home = tmp_path / "home"
    paths = [flight_csv(data_dir, 20 + k) for k in range(5)]
    jobs = [paths[k % 5] for k in range(20)]          # 5 different files, each uploaded 4 times at once
    statuses, ids, errors = [], {}, []
    with running_app(home) as client:
        def send(path):
            try:
                response = upload(client, path)
                statuses.append(response.status_code)
                ids.setdefault(path.name, set()).add(response.json()["id"])
            except Exception as err:  # pragma: no cover - reported below
                errors.append(err)
        threads = [threading.Thread(target=send, args=(p,)) for p in jobs]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert not errors
        assert sorted(statuses) == [200] * 15 + [201] * 5
        assert all(len(v) == 1 for v in ids.values()) and len({i for v in ids.values() for i in v}) == 5
        assert client.get("/flights").json()["total"] == 5
    assert count_rows(home) == 5 and count_rows(home, FlightFile) == 5
    assert len(blob_files(home)) == 10   # 5 raw files + 5 normalized flights, nothing half-written


def test_delete_removes_row_and_blobs(tmp_path, data_dir):
    home = tmp_path / "home"
    with running_app(home) as client:
        keep = upload(client, flight_csv(data_dir, 30)).json()
        gone = upload(client, flight_csv(data_dir, 31)).json()
        assert client.delete(f"/flights/{gone['id']}").status_code == 204
        assert client.get(f"/flights/{gone['id']}").status_code == 404
        assert keep["sha256"] in blob_files(home) and gone["sha256"] not in blob_files(home)
        assert len(blob_files(home)) == 2   # the kept flight's raw file and normalized flight
        assert client.get(f"/flights/{keep['id']}/raw").status_code == 200


def test_unexpected_errors_show_no_traceback(tmp_path, data_dir, monkeypatch):
    from fastapi.testclient import TestClient  # the app stack loads when a test runs, not at collection

    import learnest.service.operations.uploads as uploads
    from learnest.service.app.factory import create_app

    def explode(*_args):
        raise RuntimeError("secret internals /srv/path")
    monkeypatch.setattr(uploads, "find_by_sha", explode)   # in the server process (decoding is in a worker)
    app = create_app(settings_for(tmp_path / "home"), executor=shared_pool(), scheduler=False)
    with TestClient(app, raise_server_exceptions=False) as client:
        response = upload(client, flight_csv(data_dir, 32))
        assert response.status_code == 500
        assert "Traceback" not in response.text and "secret" not in response.text
        assert "incident" in response.json()["detail"]


def test_openapi_docs_are_served(tmp_path):
    with running_app(tmp_path / "home") as client:
        assert client.get("/docs").status_code == 200
        paths = client.get("/openapi.json").json()["paths"]
        assert {"/flights", "/flights/{flight_id}/data", "/models", "/jobs/{job_id}", "/evaluations",
                "/evaluations/{evaluation_id}/report.html", "/diagnoses/{diagnosis_id}/report.html",
                "/models/{name}/aliases/{alias}"} <= set(paths)


SAMPLE_LOGS = Path(__file__).resolve().parents[3] / "sample_logs"


@pytest.mark.skipif(not (SAMPLE_LOGS / "pair_circle_vicon.csv").is_file(), reason="sample_logs/ not present")
def test_every_sample_log_format_uploads(tmp_path):
    pair = [SAMPLE_LOGS / "pair_circle_vicon.csv", SAMPLE_LOGS / "pair_circle_cfclient.csv"]
    documents = (".md", ".txt", ".yaml")   # README, the NanoBench licence and sidecars (uploaded with their CSV)
    singles = [p for p in sorted(SAMPLE_LOGS.iterdir()) if p.is_file() and p not in pair and p.suffix not in documents]
    with running_app(tmp_path / "home") as client:
        lone = upload(client, pair[0])
        assert lone.status_code == 422 and lone.json()["detail"].startswith("pair_circle_vicon.csv: ")
        both = upload(client, *pair)
        assert both.status_code == 201 and both.json()["adapter"] == "vicon+cfclient"
        assert both.json()["clock_offset_s"] is not None and len(both.json()["sources"]) == 2
        adapters = {upload(client, path).json()["adapter"] for path in singles}
        assert {"nanobench", "usd"} <= adapters and any(a.startswith("mcap") for a in adapters)
        assert client.get("/flights").json()["total"] == len(singles) + 1
        raw = client.get(f"/flights/{both.json()['id']}/raw")
        with zipfile.ZipFile(io.BytesIO(raw.content)) as bundle:
            assert sorted(bundle.namelist()) == sorted(p.name for p in pair)
