"""The upload + model + evaluation flow once against PostgreSQL (LEARNEST_DATABASE_URL), on a throwaway
server started here — skipped when initdb/pg_ctl or the psycopg driver are not installed."""
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest
from utils.service import evaluate, flight_csv, running_app, train, upload

pytestmark = pytest.mark.postgres


def _postgres_bin() -> Path | None:
    found = shutil.which("initdb")
    if found and shutil.which("pg_ctl"):
        return Path(found).resolve().parent
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(candidates[-1]).parent if candidates else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def postgres_url(tmp_path):
    pytest.importorskip("psycopg", reason="the psycopg driver is not installed")
    bin_dir = _postgres_bin()
    if bin_dir is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) not found")
    run_as: list[str] = []
    base = tmp_path
    if os.geteuid() == 0:
        # initdb refuses to run as root: run the server as the "postgres" user, in a folder it can reach
        # (pytest's tmp_path lives under a root-only 0700 directory)
        try:
            user = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no 'postgres' user to run the server as")
        base = Path(tempfile.mkdtemp(prefix="learnest-pg-"))
        os.chown(base, user.pw_uid, user.pw_gid)
        run_as = ["runuser", "-u", "postgres", "--"]
    data, port = base / "data", _free_port()
    try:
        subprocess.run(run_as + [str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "learnest",
                                 "--no-sync"], check=True, capture_output=True)
        subprocess.run(run_as + [str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(base / "server.log"), "-w",
                                 "-o", f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off", "start"],
                       check=True, capture_output=True)
    except subprocess.CalledProcessError as err:
        shutil.rmtree(base, ignore_errors=True) if base != tmp_path else None
        pytest.skip(f"could not start a throwaway PostgreSQL: {err.stderr.decode(errors='replace')[-300:]}")
    try:
        yield f"postgresql+psycopg://learnest@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(run_as + [str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
                       capture_output=True)
        if base != tmp_path:
            shutil.rmtree(base, ignore_errors=True)


def test_upload_train_evaluate_on_postgresql(tmp_path, data_dir, postgres_url):
    with running_app(tmp_path / "home", database_url=postgres_url) as client:
        assert client.get("/health").json()["database"] == "postgresql"
        first = upload(client, flight_csv(data_dir, 0))
        assert first.status_code == 201, first.text
        assert upload(client, flight_csv(data_dir, 0), names=["copy.csv"]).status_code == 200
        other = upload(client, flight_csv(data_dir, 1)).json()
        assert client.post("/flights", files=[("files", ("x.bin", b"\x00junk"))]).status_code == 422
        assert client.get("/flights").json()["total"] == 2

        assert train(client, "pgquad", first.json()["id"])["version"] == 1
        assert client.put("/models/pgquad/aliases/production", json={"version": 1}).status_code == 200
        accepted, report = evaluate(client, "pgquad@production", "all-other")
        assert report["model"] == "pgquad:1" and [f["flight"] for f in report["flights"]] == [other["name"]]
        assert report["flights"][0]["excluded"] is False and report["median"]
        again = client.post("/evaluations", json={"model": "pgquad:1", "flights": [other["id"]],
                                                  "methods": ["ukf", "knode-ukf"]}).json()
        assert again["state"] == "succeeded"                        # from the results cache
        assert client.get("/models/pgquad/versions/9").status_code == 404
