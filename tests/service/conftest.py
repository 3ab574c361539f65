"""Fixtures for the service's tests: a throwaway PostgreSQL server, for any test that runs the service on
PostgreSQL rather than its default SQLite file (pass the URL to `utils.service.running_app(database_url=...)`)."""
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest


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
