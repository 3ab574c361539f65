"""Service internals that HTTP alone cannot provoke: jobs and blobs left behind by a crashed server, leases
(one scheduler, job ownership across uvicorn workers), migrations, failing training jobs."""
import socket
import subprocess
import sys
import threading
import time

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from utils.service import blob_files, flight_csv, running_app, settings_for, upload, wait_for_job


def database_for(home):
    from learnest.service.storage.database import Database

    database = Database(settings_for(home).url)
    database.migrate()
    return database


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_jobs_left_running_by_a_crashed_server_are_failed_at_startup(tmp_path):
    from learnest.service.storage.tables import Job, Lease, ModelVersion, RegisteredModel

    home = tmp_path / "home"
    database = database_for(home)
    host = socket.gethostname()
    with database.transaction() as session:
        crashed = Job(kind="training", state="running", owner="gone-host:4242:abcd1234", progress=0.4)
        queued = Job(kind="evaluation", state="queued", owner=None, progress=0.0)
        restarted = Job(kind="evaluation", state="running", owner=f"{host}:{dead_pid()}:feedbeef", progress=0.1)
        alive = Job(kind="evaluation", state="running", owner="other-worker:1:cafe0000", progress=0.5)
        session.add_all([crashed, queued, restarted, alive])
        session.flush()
        session.add(RegisteredModel(name="ghost"))
        session.flush()
        session.add(ModelVersion(name="ghost", version=1, status="training", job_id=crashed.id, hyperparameters={}))
        # a live worker (another uvicorn process) and a same-host process that died within its lease
        session.add(Lease(name="runner:other-worker:1:cafe0000", owner="other-worker:1:cafe0000",
                          expires_at=time.time() + 600))
        session.add(Lease(name=f"runner:{restarted.owner}", owner=restarted.owner, expires_at=time.time() + 600))
        ids = {"crashed": crashed.id, "queued": queued.id, "restarted": restarted.id, "alive": alive.id}
    database.dispose()

    with running_app(home) as client:
        for key in ("crashed", "queued", "restarted"):
            job = client.get(f"/jobs/{ids[key]}").json()
            assert job["state"] == "failed" and job["error"] == "server restarted", (key, job)
        assert client.get(f"/jobs/{ids['alive']}").json()["state"] == "running"  # not ours to judge
        version = client.get("/models/ghost/versions/1").json()
        assert version["status"] == "failed" and version["error"] == "server restarted"
        assert client.put("/models/ghost/aliases/production", json={"version": 1}).status_code == 409
        refused = client.post("/evaluations", json={"model": "ghost:1", "flights": "all-other"})
        assert refused.status_code == 409 and "failed" in refused.json()["detail"]
        listed = client.get("/jobs", params={"state": "failed"}).json()
        assert listed["total"] == 3


def test_blobs_orphaned_by_an_interrupted_write_are_swept_at_startup_and_stored_ones_kept(tmp_path, data_dir):
    home = tmp_path / "home"
    with running_app(home) as client:
        flight = upload(client, flight_csv(data_dir, 0)).json()
        stored = blob_files(home)
        # a crash after the blob's fsync+rename but before its row's commit
        orphan = client.app.state.services.blobs.put_bytes(b"an upload whose row never committed")
    assert blob_files(home) == stored | {orphan}
    with running_app(home) as client:
        assert blob_files(home) == stored
        assert client.get(f"/flights/{flight['id']}/data").status_code == 200
        assert client.get(f"/flights/{flight['id']}/raw").status_code == 200


def test_a_failing_training_job_fails_its_version_with_the_reason(tmp_path, data_dir):
    from learnest.service.storage.tables import FlightRecord

    with running_app(tmp_path / "home") as client:
        flight = upload(client, flight_csv(data_dir, 0)).json()
        services = client.app.state.services
        with services.db.transaction() as session:
            blob = session.get(FlightRecord, flight["id"]).flight_blob
        services.blobs.path(blob).write_bytes(b"corrupt")
        accepted = client.post("/models", json={"name": "m", "flight_id": flight["id"], "epochs": 1}).json()
        job = wait_for_job(client, accepted["job_id"])
        assert job["state"] == "failed" and job["error"]
        assert "Traceback" not in job["error"] and "unreadable" in job["error"]
        version = client.get("/models/m/versions/1").json()
        assert version["status"] == "failed" and version["error"] == job["error"]
        assert client.get("/models/m").json()["latest_version"] is None


def test_leases_give_one_owner_at_a_time(tmp_path):
    from learnest.service.storage.leases import acquire_lease, lease_holder, release_lease

    database = database_for(tmp_path / "home")
    # long leases where the test needs them held (a busy machine may pause between two calls), a short
    # one only where it must expire
    assert acquire_lease(database, "scheduler", "a", ttl_s=30)
    assert not acquire_lease(database, "scheduler", "b", ttl_s=30)
    assert acquire_lease(database, "scheduler", "a", ttl_s=1.0)          # renewal, now for 1 s
    assert lease_holder(database, "scheduler") == "a"
    time.sleep(1.2)
    assert lease_holder(database, "scheduler") is None
    assert acquire_lease(database, "scheduler", "b", ttl_s=5)            # expired: taken over
    release_lease(database, "scheduler", "a")                            # not a's any more: no effect
    assert lease_holder(database, "scheduler") == "b"

    # many processes racing for a free lease: exactly one wins
    winners = []
    threads = [threading.Thread(target=lambda k=k: winners.append(acquire_lease(database, "race", f"o{k}", 5)))
               for k in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert winners.count(True) == 1
    database.dispose()


def test_a_second_runner_never_fails_a_live_runners_jobs(tmp_path):
    from learnest.service.jobs.runner import JobRunner
    from learnest.service.storage.leases import release_lease
    from learnest.service.storage.tables import Job

    database = database_for(tmp_path / "home")
    first, second = JobRunner(database), JobRunner(database)
    first.start()
    with database.transaction() as session:
        job_id = first.create(session, "evaluation").id
    first._mark_running(job_id)
    assert second.start() == []                   # another uvicorn worker starting up
    with database.transaction() as session:
        assert session.get(Job, job_id).state == "running"
    first._stop.set()
    release_lease(database, first.lease_name, first.owner)   # first dies without cleaning up
    assert second.sweep() == [job_id]
    second.shutdown()
    database.dispose()


def test_migrations_build_exactly_the_tables_of_the_models(tmp_path):
    from sqlalchemy import inspect

    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Base

    home = tmp_path / "home"
    home.mkdir()
    databases = [Database(settings_for(home).url) for _ in range(3)]
    threads = [threading.Thread(target=d.migrate) for d in databases]   # several workers start at once
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    database = databases[0]
    with database.engine.connect() as connection:
        differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
        tables = set(inspect(connection).get_table_names())
    assert differences == []
    assert set(Base.metadata.tables) | {"alembic_version"} == tables
    database.migrate()   # idempotent
    for d in databases:
        d.dispose()


def test_an_unfinished_evaluation_answers_202_with_its_state(tmp_path, data_dir):
    from learnest.service.storage.tables import Evaluation, ModelVersion, RegisteredModel

    with running_app(tmp_path / "home") as client:
        services = client.app.state.services
        with services.db.transaction() as session:
            session.add(RegisteredModel(name="m"))
            session.flush()
            version = ModelVersion(name="m", version=1, status="ready", hyperparameters={})
            session.add(version)
            job = services.runner.create(session, "evaluation")
            session.flush()
            evaluation = Evaluation(job_id=job.id, model_ref="m:1", model_version_id=version.id, flight_ids=[],
                                    settings={})
            session.add(evaluation)
            session.flush()
            ids = job.id, evaluation.id
        pending = client.get(f"/evaluations/{ids[1]}")
        assert pending.status_code == 202
        assert pending.json() == {"evaluation_id": ids[1], "job_id": ids[0], "state": "queued", "progress": 0.0}
        assert client.get(f"/evaluations/{ids[1]}/report.html").status_code == 202
        services.runner.mark_failed(ids[0], "broken on purpose")
        failed = client.get(f"/evaluations/{ids[1]}")
        assert failed.status_code == 409 and "broken on purpose" in failed.json()["detail"]
