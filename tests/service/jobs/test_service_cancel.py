"""Quotas on the work a request may ask for, and cancelling a job.

A real training job on the real worker pool is cancelled mid-run: it ends "cancelled", its reserved version
is failed without weights, the worker stops by itself (same process, free for the next job at once), and an
interrupted `learnest train` leaves no version at all.
"""
import time

import pytest
from utils.service import blob_files, flight_csv, running_app, settings_for, shared_pool, upload, wait_for_job

LONG_EPOCHS = 5000   # minutes of training on the test flight: a job that is surely cancelled mid-run


@pytest.fixture(scope="module")
def app_with_a_flight(tmp_path_factory):
    home = tmp_path_factory.mktemp("cancel")
    with running_app(home, max_training_work=0) as client:
        response = upload(client, flight_csv(home / "logs", seed=1))
        assert response.status_code == 201, response.text
        yield client, response.json()["id"], home


def _wait_for_progress(client, job_id: int, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] == "running" and job["progress"] > 0:
            return job
        assert job["state"] in ("queued", "running"), job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} made no progress in {timeout} s")


# -- quotas ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("body, setting", [({"epochs": 100_000}, "LEARNEST_MAX_EPOCHS"),
                                           ({"hidden": 4096}, "LEARNEST_MAX_HIDDEN")])
def test_a_training_past_a_limit_is_a_422_naming_the_setting(app_with_a_flight, body, setting):
    client, flight_id, _ = app_with_a_flight
    jobs_before = client.get("/jobs").json()["total"]
    response = client.post("/models", json={"name": "huge", "flight_id": flight_id, **body})
    assert response.status_code == 422, response.text
    assert setting in response.json()["detail"]
    assert client.get("/jobs").json()["total"] == jobs_before          # no job, no reserved version
    assert client.get("/models/huge").status_code == 404


def test_the_work_limit_counts_epochs_samples_and_hidden_units(tmp_path):
    from learnest.service.jobs.quotas import QuotaExceeded, check_training

    settings = settings_for(tmp_path, max_training_work=1e6)
    check_training(settings, epochs=100, hidden=10, samples=1000)      # exactly 1e6: allowed
    with pytest.raises(QuotaExceeded,
                       match=r"100 x 1001 x 10 = 1,001,000, above .* 1,000,000 \(LEARNEST_MAX_TRAINING_WORK"):
        check_training(settings, epochs=100, hidden=10, samples=1001)
    check_training(settings_for(tmp_path, max_training_work=0), epochs=5000, hidden=256, samples=10**6)  # 0: off


def test_a_diagnosis_past_the_epoch_limit_is_a_422(app_with_a_flight):
    client, flight_id, _ = app_with_a_flight
    response = client.post("/diagnoses", json={"flights": [flight_id], "epochs": 6000})
    assert response.status_code == 422 and "LEARNEST_MAX_EPOCHS" in response.json()["detail"], response.text


# -- cancel ------------------------------------------------------------------------------------------------
def test_a_running_training_is_cancelled_and_its_worker_is_free_for_the_next_job(app_with_a_flight):
    client, flight_id, home = app_with_a_flight
    blobs_before = blob_files(home)
    accepted = client.post("/models", json={"name": "stopped", "flight_id": flight_id, "epochs": LONG_EPOCHS})
    assert accepted.status_code == 202, accepted.text
    job_id = accepted.json()["job_id"]
    _wait_for_progress(client, job_id)
    workers = set(shared_pool()._pool._processes)

    cancelled = client.post(f"/jobs/{job_id}/cancel")
    assert cancelled.status_code == 200, cancelled.text
    assert cancelled.json()["state"] == "cancelled" and cancelled.json()["error"] == "cancelled by request"
    # the worker stops by itself between epochs: the next job runs at once, on the same worker process
    started = time.monotonic()
    nxt = client.post("/models", json={"name": "after", "flight_id": flight_id, "epochs": 2})
    assert wait_for_job(client, nxt.json()["job_id"], timeout=60)["state"] == "succeeded"
    assert time.monotonic() - started < 30
    assert set(shared_pool()._pool._processes) == workers

    job = client.get(f"/jobs/{job_id}").json()
    assert job["state"] == "cancelled" and job["result"] is None
    version = client.get("/models/stopped/versions/1").json()
    assert version["status"] == "failed" and version["weights_sha256"] is None
    assert "cancelled" in version["error"]
    assert client.get("/models/stopped/versions/1/weights").status_code == 409
    # the only new blob is the weights of the job that succeeded
    assert len(blob_files(home) - blobs_before) == 1
    assert client.get("/jobs", params={"state": "cancelled"}).json()["total"] >= 1


def test_cancel_answers_for_finished_and_unknown_jobs(app_with_a_flight):
    client, flight_id, _ = app_with_a_flight
    accepted = client.post("/models", json={"name": "short", "flight_id": flight_id, "epochs": 1})
    job_id = accepted.json()["job_id"]
    assert wait_for_job(client, job_id)["state"] == "succeeded"
    finished = client.post(f"/jobs/{job_id}/cancel")
    assert finished.status_code == 409 and "already succeeded" in finished.json()["detail"]
    assert client.post("/jobs/999999/cancel").status_code == 404


def test_the_job_page_has_a_cancel_button_that_cancels(app_with_a_flight):
    client, flight_id, _ = app_with_a_flight
    accepted = client.post("/models", json={"name": "button", "flight_id": flight_id, "epochs": LONG_EPOCHS})
    job_id = accepted.json()["job_id"]
    page = client.get(f"/ui/jobs/{job_id}").text
    assert f"action='/ui/jobs/{job_id}/cancel'" in page
    # the same cross-site guard as every form
    refused = client.post(f"/ui/jobs/{job_id}/cancel", headers={"Origin": "http://evil.example"},
                          follow_redirects=False)
    assert refused.status_code == 403 and client.get(f"/jobs/{job_id}").json()["state"] in ("queued", "running")
    pressed = client.post(f"/ui/jobs/{job_id}/cancel", headers={"Origin": "http://testserver"},
                          follow_redirects=False)
    assert pressed.status_code == 303 and pressed.headers["location"] == f"/ui/jobs/{job_id}"
    assert wait_for_job(client, job_id, timeout=30)["state"] == "cancelled"
    after = client.get(f"/ui/jobs/{job_id}").text
    assert "cancel-form" not in after and "cancelled by request" in after


def test_cancelling_needs_the_api_key_when_the_server_has_one(tmp_path):
    with running_app(tmp_path, api_key="sesame") as client:
        assert client.post("/jobs/1/cancel").status_code == 401
        assert client.post("/jobs/1/cancel", headers={"X-API-Key": "sesame"}).status_code == 404


# -- the CLI -------------------------------------------------------------------------------------------------
def test_an_interrupted_cli_training_leaves_no_version(tmp_path):
    from sqlalchemy import select

    from learnest.service.local import cli_settings, train
    from learnest.service.storage.database import Database, referenced_blobs
    from learnest.service.storage.tables import Job, ModelVersion, RegisteredModel

    settings = cli_settings().model_copy(update={"home": tmp_path / "home"})
    log = flight_csv(tmp_path, seed=2)

    def ctrl_c(fraction: float) -> None:  # what Ctrl-C does to the waiting CLI once training runs
        if fraction > 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train([log], "interrupted", epochs=LONG_EPOCHS, progress=ctrl_c, settings=settings)
    db = Database(settings.url)
    try:
        with db.transaction() as session:
            assert session.scalars(select(ModelVersion)).all() == []
            assert session.get(RegisteredModel, "interrupted") is None
            assert [(j.kind, j.state, j.error) for j in session.scalars(select(Job))] == \
                [("training", "cancelled", "interrupted")]
        # the flight stays stored (it was complete); no weights blob was left
        assert blob_files(settings.home) == referenced_blobs(db)
    finally:
        db.dispose()
