"""Load and fault benchmark of `learnest serve`: loopback only, bounded in count and time (~3 min).

1. Uploads vs /health.  40 concurrent "bomb-ish" uploads (20 MCAP files whose zstd chunks claim 16 MiB of
   zeros each - 64 MiB in a few kB, refused by the expansion cap - and 20 distinct simulated NanoBench flights)
   while one client polls GET /health every 50 ms: /health latency p50/p99/max and the uploads' status codes.
   With ``--compare DIR`` (a folder holding another learnest install, e.g. main before this change:
   ``pip install --no-deps --target DIR /work/main``) the same phase runs against that code first.
2. Load during training.  A training job runs (LEARNEST_POOL_WORKERS=1) while 8 clients read (GET /flights,
   /flights/{id}, /, /health) and upload 10 more flights: p50/p99 per kind, errors (5xx or no answer).
   The job is then cancelled.
3. kill -9 during a job.  A training job is running and an upload is in flight when the server gets SIGKILL;
   then: the server's child processes (pool workers, upload decoders) must all be gone within a few seconds
   (0 orphaned processes); the server is restarted on the same folder and must report the running job as
   failed (0 stuck jobs), keep no blob that no row names and no temp entry (0 orphaned blobs or temp files),
   and the SQLite file must pass ``PRAGMA integrity_check``.
4. Large downloads past the body deadline, and a large real flight's pages.  A server with a 5-s body deadline
   (LEARNEST_BODY_TIMEOUT_S=5) stores a ~150-MB, ~224k-sample flight made of real NanoBench flights
   (../shared/data/nanobench*, concatenated in time, kept whole: cut=none).  A client reads its raw file at
   ~8 MB/s (~19 s, well past the deadline) and an evaluation's CSV export of it the same way: both must arrive
   byte for byte (sha256 against a fast read), with the status and length the server announced.  The flight's
   page and the evaluation's report page: seconds of the first and of later views, and bytes of HTML.
5. kill -9 during an export: the server gets SIGKILL while a slow client is reading the large export; then no
   child process stays, and after a restart no temp entry, no stuck job, ``integrity_check`` ok.
6. A full database.  The SQLite file on a 16-MB tmpfs of its own (this benchmark re-runs itself in a user and
   mount namespace, `unshare -rm`, to mount it; blobs stay on disk): a training job runs, a file fills the
   tmpfs, an upload and a second training are tried while it is full (507 expected, never 500, no SQL in any
   answer or job error) and the first training ends (neither its result nor its failure can be stored), the
   file is removed, and every job must reach a final state within 60 s.

Run:  .venv/bin/python benchmarks/bench_service_faults.py [--compare DIR] [--phases 1,2,3,4,5,6]
      (writes benchmarks/results/service_faults.{json,md}; phases not run keep their committed results)
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import psutil
from served import free_port, wait_until_up

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results"
COMMAND = ".venv/bin/python benchmarks/bench_service_faults.py"
BOMBS, FLIGHTS, READERS, LOAD_UPLOADS = 20, 20, 8, 10
PHASE_LIMIT_S = 60.0    # each phase stops by then whatever happens


# -- inputs ----------------------------------------------------------------------------------------------
def make_flights(directory: Path, count: int, first: int = 0) -> list[Path]:
    """Distinct short simulated NanoBench flights (6-s circles)."""
    from learnest.ingest.sim import Circle, simulate, write_flight

    paths = []
    for k in range(first, first + count):
        circle = Circle(radius=0.3 + 0.01 * k, speed=0.4 + 0.01 * (k % 8), altitude=1.0, duration_s=6.0)
        paths += write_flight(simulate(circle, seed=500 + k, name=f"fault_{k:02d}"), "nanobench", directory,
                              f"fault_{k:02d}")
    return paths


def make_bomb(path: Path, seed: int, chunks: int = 4, uncompressed: int = 16 << 20) -> Path:
    """An MCAP file whose zstd chunks hold `uncompressed` zero bytes each (the issue's chunk bomb)."""
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, Header

    zeros = bytes(uncompressed)
    data = zstandard.ZstdCompressor().compress(zeros)
    builder = RecordBuilder()
    Header(profile="ros2", library=f"bomb{seed}").write(builder)   # distinct bytes: no dedupe shortcut
    for _ in range(chunks):
        Chunk(compression="zstd", data=data, message_start_time=0, message_end_time=0,
              uncompressed_crc=zlib.crc32(zeros), uncompressed_size=uncompressed).write(builder)
    path.write_bytes(b"\x89MCAP0\r\n" + builder.end())
    return path


# -- a real server ---------------------------------------------------------------------------------------
class Server:
    """`learnest serve` in a subprocess on 127.0.0.1:<free port> with its own LEARNEST_HOME."""

    def __init__(self, home: Path, python_path: str | None = None, settings: dict | None = None):
        self.home, self.port = home, free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "LEARNEST_HOME": str(home), "LEARNEST_POOL_WORKERS": "1", "NO_PROXY": "127.0.0.1"}
        for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY", "LEARNEST_SCHEDULE_SECONDS"):
            env.pop(name, None)
        env.update({k: str(v) for k, v in (settings or {}).items()})
        if python_path:
            env["PYTHONPATH"] = python_path
        home.mkdir(parents=True, exist_ok=True)
        self.log = open(home.parent / f"server-{self.port}.log", "wb")
        self.process = subprocess.Popen([sys.executable, "-m", "learnest.service.cli", "serve", "--port",
                                         str(self.port)], cwd=home.parent, env=env, stdout=self.log,
                                        stderr=subprocess.STDOUT)
        self._wait_until_up()

    def _wait_until_up(self, timeout: float = 120.0) -> None:
        wait_until_up(self.process, self.url, self.log.name, timeout)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=60)
        self.log.close()


def percentiles(values: list[float]) -> dict:
    if not values:
        return {"n": 0}
    ms = np.asarray(values) * 1000
    return {"n": len(values), "p50_ms": round(float(np.percentile(ms, 50)), 1),
            "p99_ms": round(float(np.percentile(ms, 99)), 1), "max_ms": round(float(ms.max()), 1)}


class Poller(threading.Thread):
    """GET `path` every `every_s` until stopped; latencies and failures."""

    def __init__(self, url: str, path: str, every_s: float = 0.05):
        super().__init__(daemon=True)
        self.url, self.path, self.every_s = url, path, every_s
        self.latencies: list[float] = []
        self.errors = 0
        self.stopped = threading.Event()

    def run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=30) as client:
            while not self.stopped.is_set():
                started = time.perf_counter()
                try:
                    ok = client.get(self.path).status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.latencies.append(time.perf_counter() - started)
                self.errors += not ok
                self.stopped.wait(self.every_s)


def post_file(url: str, path: Path) -> tuple[int, float]:
    started = time.perf_counter()
    try:
        with httpx.Client(base_url=url, timeout=PHASE_LIMIT_S) as client:
            code = client.post("/flights", files=[("files", (path.name, path.read_bytes()))]).status_code
    except httpx.HTTPError:
        code = 0   # no answer
    return code, time.perf_counter() - started


def status_counts(codes: list[int]) -> dict:
    return {str(code): codes.count(code) for code in sorted(set(codes))}


# -- 1. uploads vs /health --------------------------------------------------------------------------------
def uploads_vs_health(root: Path, uploads: list[Path], python_path: str | None, label: str) -> dict:
    server = Server(root / f"home-{label}", python_path)
    try:
        idle = Poller(server.url, "/health")
        idle.start()
        time.sleep(2)
        idle.stopped.set()
        idle.join()
        poller = Poller(server.url, "/health")
        poller.start()
        started = time.perf_counter()
        with ThreadPoolExecutor(len(uploads)) as pool:
            results = list(pool.map(lambda p: post_file(server.url, p), uploads))
        seconds = time.perf_counter() - started
        poller.stopped.set()
        poller.join()
    finally:
        server.stop()
    codes = [code for code, _ in results]
    return {"code": label, "uploads": len(uploads), "seconds": round(seconds, 2),
            "upload_status": status_counts(codes), "upload_latency": percentiles([s for _, s in results]),
            "health_idle": percentiles(idle.latencies), "health_during_uploads": percentiles(poller.latencies),
            "health_errors": poller.errors}


# -- 2. load during training ----------------------------------------------------------------------------------
def wait_for_state(client: httpx.Client, job_id: int, states: set[str], timeout: float = PHASE_LIMIT_S) -> str:
    deadline = time.monotonic() + timeout
    state = ""
    while time.monotonic() < deadline:
        state = client.get(f"/jobs/{job_id}").json()["state"]
        if state in states:
            return state
        time.sleep(0.1)
    return state


def load_during_training(root: Path, flights: list[Path], extra: list[Path]) -> dict:
    server = Server(root / "home-load")
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            ids = [client.post("/flights", files=[("files", (p.name, p.read_bytes()))]).json()["id"]
                   for p in flights[:3]]
            job = client.post("/models", json={"name": "load", "flight_id": ids[0], "epochs": 3000}).json()
            training_state = wait_for_state(client, job["job_id"], {"running", "failed", "succeeded"})
        paths = {"/flights": [], f"/flights/{ids[1]}": [], "/": [], "/health": []}
        errors: dict[str, int] = {path: 0 for path in paths}
        stop = time.monotonic() + 20

        def reader(k: int) -> None:
            path = list(paths)[k % len(paths)]
            with httpx.Client(base_url=server.url, timeout=30) as client:
                while time.monotonic() < stop:
                    started = time.perf_counter()
                    try:
                        ok = client.get(path).status_code == 200
                    except httpx.HTTPError:
                        ok = False
                    paths[path].append(time.perf_counter() - started)
                    errors[path] += not ok

        threads = [threading.Thread(target=reader, args=(k,)) for k in range(READERS)]
        for thread in threads:
            thread.start()
        with ThreadPoolExecutor(4) as pool:
            uploaded = list(pool.map(lambda p: post_file(server.url, p), extra))
        for thread in threads:
            thread.join()
        with httpx.Client(base_url=server.url, timeout=60) as client:
            still = client.get(f"/jobs/{job['job_id']}").json()["state"]
            client.post(f"/jobs/{job['job_id']}/cancel")
            cancelled = wait_for_state(client, job["job_id"], {"cancelled", "failed", "succeeded"})
    finally:
        server.stop()
    codes = [code for code, _ in uploaded]
    return {"training_state_during_load": [training_state, still], "training_after_cancel": cancelled,
            "readers": READERS, "seconds": 20,
            "reads": {path: {**percentiles(values), "errors": errors[path]} for path, values in paths.items()},
            "uploads": {"status": status_counts(codes), **percentiles([s for _, s in uploaded]),
                        "errors": sum(1 for c in codes if c == 0 or c >= 500)}}


# -- 3. kill -9 during a job ------------------------------------------------------------------------------
def kill_during_job(root: Path, flights: list[Path], slow_upload: Path) -> dict:
    home = root / "home-kill"
    server = Server(home)
    with httpx.Client(base_url=server.url, timeout=60) as client:
        flight_id = client.post("/flights", files=[("files", (flights[0].name, flights[0].read_bytes()))]).json()["id"]
        job = client.post("/models", json={"name": "killed", "flight_id": flight_id, "epochs": 3000}).json()
        state_before = wait_for_state(client, job["job_id"], {"running"})
        time.sleep(2)   # well into training
    children = psutil.Process(server.process.pid).children(recursive=True)
    in_flight = threading.Thread(target=post_file, args=(server.url, slow_upload), daemon=True)
    in_flight.start()   # an upload being received or decoded when the server dies
    time.sleep(0.3)
    os.kill(server.process.pid, signal.SIGKILL)
    server.process.wait()
    server.log.close()
    deadline, alive = time.monotonic() + 10, children
    while time.monotonic() < deadline:
        alive = [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
        if not alive:
            break
        time.sleep(0.2)
    orphans_after_s = round(10 - max(0.0, deadline - time.monotonic()), 1)
    for process in alive:   # leave nothing behind on the machine running the benchmark
        process.kill()
    temp_before_restart = sorted(p.name for p in (home / "blobs" / ".tmp").iterdir())

    server = Server(home)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            restarted = client.get(f"/jobs/{job['job_id']}").json()
            jobs = client.get("/jobs", params={"limit": 100}).json()["items"]
            versions = client.get("/models/killed").json() if client.get("/models/killed").status_code == 200 else {}
    finally:
        server.stop()
    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database, referenced_blobs

    database = Database(f"sqlite:///{home / 'learnest.db'}")
    referenced = referenced_blobs(database)
    database.dispose()
    stored = set(BlobStore(home / "blobs").all_blobs())
    with sqlite3.connect(home / "learnest.db") as connection:
        integrity = connection.execute("PRAGMA integrity_check").fetchone()[0]
    return {"job_state_before_kill": state_before, "server_children_before_kill": len(children),
            "orphaned_processes": len(alive), "children_gone_within_s": orphans_after_s,
            "job_after_restart": {"state": restarted["state"], "error": restarted.get("error")},
            "stuck_jobs": sum(1 for j in jobs if j["state"] in ("queued", "running")),
            "versions_of_killed_model": [(v.get("version"), v.get("status")) for v in versions.get("versions", [])],
            "temp_entries_before_restart": len(temp_before_restart),
            "temp_entries_after_restart": len(list((home / "blobs" / ".tmp").iterdir())),
            "orphaned_blobs": len(stored - referenced), "missing_blobs": len(referenced - stored),
            "integrity_check": integrity}


# -- 4. large downloads past the body deadline; a large real flight's pages -----------------------------------
BODY_TIMEOUT_S = 5
READ_RATE = 8 << 20            # bytes/s of the slow client
REAL_DATA = REPO.parent / "shared" / "data"
LARGE_BYTES = 150 << 20


def large_real_flight(path: Path, target_bytes: int = LARGE_BYTES) -> Path:
    """Real NanoBench flights concatenated in time (each flight's clock shifted to follow the last row written,
    10 ms later) until the CSV holds ``target_bytes``: one long flight of real data."""
    sources = sorted((REAL_DATA / "nanobench").glob("*.csv")) + sorted((REAL_DATA / "nanobench-more").glob("*.csv"))
    written, t_end = 0, None
    with open(path, "w") as out:
        while written < target_bytes:
            for source in sources:
                lines = source.read_text().splitlines()
                if t_end is None:
                    out.write(lines[0] + "\n")
                rows = lines[1:]
                t0 = float(rows[0].split(",", 1)[0])
                shift = 0.0 if t_end is None else t_end + 0.01 - t0
                for row in rows:
                    t, rest = row.split(",", 1)
                    text = f"{float(t) + shift:.6f},{rest}\n"
                    out.write(text)
                    written += len(text)
                t_end = float(rows[-1].split(",", 1)[0]) + shift
                if written >= target_bytes:
                    break
    return path


def slow_read(url: str, path: str, rate: float = READ_RATE, timeout: float = 600) -> dict:
    """GET ``path`` reading at most ``rate`` bytes/s: status, bytes, sha256, seconds, and how it ended."""
    import hashlib

    digest, received, status, ended, length = hashlib.sha256(), 0, None, "complete", None
    started = time.perf_counter()
    try:
        with httpx.Client(base_url=url, timeout=timeout) as client, client.stream("GET", path) as response:
            status, length = response.status_code, response.headers.get("content-length")
            for chunk in response.iter_raw(1 << 16):
                digest.update(chunk)
                received += len(chunk)
                behind = received / rate - (time.perf_counter() - started)
                if behind > 0:
                    time.sleep(behind)
    except httpx.HTTPError as err:
        ended = f"transport error: {type(err).__name__}"
    return {"status": status, "content_length": int(length) if length else None, "bytes": received,
            "sha256": digest.hexdigest(), "seconds": round(time.perf_counter() - started, 1), "ended": ended}


def fast_sha(url: str, path: str) -> tuple[str, int]:
    import hashlib

    digest, size = hashlib.sha256(), 0
    with httpx.Client(base_url=url, timeout=600) as client, client.stream("GET", path) as response:
        for chunk in response.iter_raw(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return digest.hexdigest(), size


def timed_views(client: httpx.Client, path: str, views: int = 3) -> dict:
    seconds, sizes, codes = [], [], []
    for _ in range(views):
        started = time.perf_counter()
        answer = client.get(path)
        seconds.append(round(time.perf_counter() - started, 2))
        sizes.append(len(answer.content))
        codes.append(answer.status_code)
    return {"status": codes, "seconds": seconds, "html_bytes": sizes}


def large_downloads(root: Path, small: Path) -> dict:
    import hashlib

    big = large_real_flight(root / "logs" / "real_long.csv")
    home = root / "home-large"
    server = Server(home, settings={"LEARNEST_BODY_TIMEOUT_S": BODY_TIMEOUT_S, "LEARNEST_DECODE_TIMEOUT_S": 900})
    results: dict = {"body_timeout_s": BODY_TIMEOUT_S, "read_rate_mb_s": READ_RATE / 2**20,
                     "flight_csv_bytes": big.stat().st_size}
    try:
        with httpx.Client(base_url=server.url, timeout=900) as client:
            started = time.perf_counter()
            with open(big, "rb") as handle:
                stored = client.post("/flights", files=[("files", (big.name, handle))], data={"cut": "none"})
            results["upload"] = {"status": stored.status_code, "seconds": round(time.perf_counter() - started, 1)}
            flight = stored.json()
            results["flight_samples"] = flight["samples"]
            results["flight_page"] = timed_views(client, f"/ui/flights/{flight['id']}")
            expected = hashlib.sha256(big.read_bytes()).hexdigest()
            raw = slow_read(server.url, f"/flights/{flight['id']}/raw")
            results["raw_download"] = {**raw, "byte_for_byte": raw["sha256"] == expected,
                                       "expected_bytes": big.stat().st_size}
            small_id = client.post("/flights", files=[("files", (small.name, small.read_bytes()))]).json()["id"]
            trained = client.post("/models", json={"name": "large", "flight_id": small_id, "epochs": 3}).json()
            results["training"] = wait_for_state(client, trained["job_id"], {"succeeded", "failed"}, 300)
            started = time.perf_counter()
            evaluation = client.post("/evaluations", json={"model": "large:1", "flights": [flight["id"]],
                                                           "methods": ["ukf"], "include_bad": True}).json()
            results["evaluation"] = {"state": wait_for_state(client, evaluation["job_id"],
                                                             {"succeeded", "failed", "cancelled"}, 900),
                                     "seconds": round(time.perf_counter() - started, 1)}
            report = f"/evaluations/{evaluation['evaluation_id']}/report.html"
            results["report_page"] = timed_views(client, report)
            export = f"/evaluations/{evaluation['evaluation_id']}/estimates?format=csv"
            started = time.perf_counter()
            expected_sha, expected_size = fast_sha(server.url, export)
            fast_s = time.perf_counter() - started
            read = slow_read(server.url, export)
            results["export_download"] = {**read, "byte_for_byte": read["sha256"] == expected_sha,
                                          "expected_bytes": expected_size, "fast_read_s": round(fast_s, 1)}
            results["evaluation_id"], results["flight_id"] = evaluation["evaluation_id"], flight["id"]
    finally:
        server.stop()
    return results


# -- 5. kill -9 during an export ------------------------------------------------------------------------------
def kill_during_export(root: Path, evaluation_id: int) -> dict:
    home = root / "home-large"
    server = Server(home, settings={"LEARNEST_BODY_TIMEOUT_S": BODY_TIMEOUT_S})
    reader: dict = {}
    thread = threading.Thread(target=lambda: reader.update(slow_read(
        server.url, f"/evaluations/{evaluation_id}/estimates?format=csv", rate=2 << 20)), daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    temp = home / "blobs" / ".tmp"
    while time.monotonic() < deadline and not any(temp.iterdir()):
        time.sleep(0.05)
    time.sleep(3)   # the export is being written or sent
    temp_during = len(list(temp.iterdir()))
    # the server's children as the kill finds them: its workers start on demand, after the server is up
    children = psutil.Process(server.process.pid).children(recursive=True)
    os.kill(server.process.pid, signal.SIGKILL)
    server.process.wait()
    server.log.close()
    thread.join(30)
    deadline, alive = time.monotonic() + 10, children
    while time.monotonic() < deadline:
        alive = [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
        if not alive:
            break
        time.sleep(0.2)
    for process in alive:
        process.kill()
    temp_before = len(list(temp.iterdir()))
    server = Server(home)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            jobs = client.get("/jobs", params={"limit": 100}).json()["items"]
    finally:
        server.stop()
    with sqlite3.connect(home / "learnest.db") as connection:
        integrity = connection.execute("PRAGMA integrity_check").fetchone()[0]
    return {"client_saw": {k: reader.get(k) for k in ("status", "content_length", "bytes", "ended")},
            "temp_entries_during_export": temp_during, "server_children_at_kill": len(children),
            "orphaned_processes": len(alive),
            "temp_entries_before_restart": temp_before, "temp_entries_after_restart": len(list(temp.iterdir())),
            "stuck_jobs": sum(1 for j in jobs if j["state"] in ("queued", "running")), "integrity_check": integrity}


# -- 6. a full database ---------------------------------------------------------------------------------------
TMPFS_MB = 16
FULL_ATTEMPTS, FULL_EVERY_S = 4, 8.0   # requests tried while the tmpfs is full (~32 s)


def full_database(root: Path, flights: list[Path]) -> dict:
    """Run in a mount namespace (see main): the database on a TMPFS_MB tmpfs, filled during a training."""
    mount = root / "dbfs"
    mount.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_MB}m", "none", str(mount)], check=True)
    server = Server(root / "home-full", settings={"LEARNEST_DATABASE_URL": f"sqlite:///{mount / 'learnest.db'}"})
    answers: list[tuple[str, int, str]] = []
    states_while_full: list[str | None] = []
    try:
        with httpx.Client(base_url=server.url, timeout=120) as client:
            first_file = [("files", (flights[0].name, flights[0].read_bytes()))]
            flight_id = client.post("/flights", files=first_file).json()["id"]
            # a training that ends while the database is full: its result cannot be stored, nor (at first) its
            # failure
            first = client.post("/models", json={"name": "full", "flight_id": flight_id, "epochs": 1000}).json()
            wait_for_state(client, first["job_id"], {"running"})
            time.sleep(3)
            filler = mount / "filler"
            with open(filler, "wb", buffering=0) as handle:
                try:
                    while True:
                        handle.write(bytes(1 << 16))
                except OSError:
                    pass
            filled_at = time.monotonic()
            for attempt in range(FULL_ATTEMPTS):
                time.sleep(FULL_EVERY_S)
                upload = client.post("/flights", files=[("files", (flights[1 + attempt].name,
                                                                    flights[1 + attempt].read_bytes()))])
                answers.append(("POST /flights", upload.status_code, upload.text[:300]))
                train = client.post("/models", json={"name": "full", "flight_id": flight_id, "epochs": 5})
                answers.append(("POST /models", train.status_code, train.text[:300]))
                state = client.get(f"/jobs/{first['job_id']}")
                answers.append(("GET /jobs/{id}", state.status_code, state.text[:300]))
                states_while_full.append(state.json().get("state") if state.status_code == 200 else None)
            full_for_s = time.monotonic() - filled_at
            filler.unlink()
            freed_at = time.monotonic()
            final = {"succeeded", "failed", "cancelled"}
            while time.monotonic() - freed_at < 90:
                jobs = client.get("/jobs", params={"limit": 100}).json()["items"]
                if all(j["state"] in final for j in jobs):
                    break
                time.sleep(0.5)
            settled_s = time.monotonic() - freed_at
            jobs = client.get("/jobs", params={"limit": 100}).json()["items"]
            after = client.post("/flights", files=[("files", (flights[9].name, flights[9].read_bytes()))])
            versions = client.get("/models/full").json().get("versions", [])
    finally:
        children = psutil.Process(server.process.pid).children(recursive=True) if server.process.poll() is None else []
        server.stop()
        psutil.wait_procs(children, timeout=15)
        for _ in range(20):   # its worker processes may hold the database open a moment longer
            if subprocess.run(["umount", str(mount)], capture_output=True).returncode == 0:
                break
            time.sleep(0.5)
        else:
            subprocess.run(["umount", "-l", str(mount)], check=False)
    texts = [text for _, _, text in answers] + [j.get("error") or "" for j in jobs]
    return {"tmpfs_mb": TMPFS_MB, "full_for_s": round(full_for_s, 1),
            "answers_while_full": status_counts([code for _, code, _ in answers]),
            "answers": [(what, code) for what, code, _ in answers],
            "training_state_while_full": states_while_full,
            "server_errors_while_full": sum(1 for _, code, _ in answers if code >= 500 and code != 507),
            "sql_in_any_answer_or_error": any("[SQL" in t or "BEGIN IMMEDIATE" in t for t in texts),
            "all_jobs_final_within_s": round(settled_s, 1),
            "jobs": [(j["id"], j["kind"], j["state"], (j.get("error") or "")[:120]) for j in jobs],
            "upload_after_freeing": after.status_code,
            "model_versions": [(v.get("version"), v.get("status")) for v in versions]}


# -- report ---------------------------------------------------------------------------------------------------
def markdown(results: dict) -> str:
    commands = results.get("phase_commands") or {}
    made = "; ".join(f"phase {phase}: `{command}`" for phase, command in sorted(commands.items())) or \
        f"`{results['command']}`"
    lines = [f"# Service load and fault benchmark\n\nOn {results['machine']}; made by {made} (the last run: "
             f"{results['seconds']:.0f} s).  Loopback only, defaults of `learnest serve` "
             f"(LEARNEST_POOL_WORKERS=1) unless a phase says otherwise.\n",
             "## 1. 40 concurrent bomb-ish uploads vs GET /health\n",
             "| code | uploads: status counts | upload p50 / max (ms) | /health idle p50 | /health during p50 / p99 "
             "/ max (ms) | /health errors |", "|---|---|---|---|---|---|"]
    for phase in results["uploads_vs_health"]:
        up, idle, busy = phase["upload_latency"], phase["health_idle"], phase["health_during_uploads"]
        lines.append(f"| {phase['code']} | {phase['upload_status']} | {up['p50_ms']} / {up['max_ms']} | "
                     f"{idle['p50_ms']} | {busy['p50_ms']} / {busy['p99_ms']} / {busy['max_ms']} | "
                     f"{phase['health_errors']} |")
    load = results["load_during_training"]
    lines += ["", f"## 2. {load['readers']} readers + {LOAD_UPLOADS} uploads for {load['seconds']} s during a "
                  f"training job (state {load['training_state_during_load']}, then {load['training_after_cancel']})\n",
              "| request | n | p50 (ms) | p99 (ms) | max (ms) | errors |", "|---|---|---|---|---|---|"]
    for path, row in {**load["reads"], "POST /flights": load["uploads"]}.items():
        lines.append(f"| {path} | {row.get('n')} | {row.get('p50_ms')} | {row.get('p99_ms')} | {row.get('max_ms')} | "
                     f"{row['errors']} |")
    lines.append(f"\nupload status counts: {load['uploads']['status']}\n")
    kill = results["kill_during_job"]
    lines += ["## 3. kill -9 during a training job (and an upload in flight), then restart\n",
              "| check | result |", "|---|---|"]
    lines += [f"| {key} | {value} |" for key, value in kill.items()]
    large = results.get("large_downloads")
    if large:
        lines += ["", f"## 4. Large downloads past a {large['body_timeout_s']}-s body deadline; a large real "
                      f"flight's pages\n",
                  f"Flight: real NanoBench flights concatenated in time, {large['flight_csv_bytes'] / 2**20:.0f} MB "
                  f"of CSV, {large['flight_samples']} samples (upload {large['upload']}).  Slow client: "
                  f"{large['read_rate_mb_s']:g} MB/s.\n", "| download | status | announced bytes | received bytes | "
                  "byte for byte | seconds | ended |", "|---|---|---|---|---|---|---|"]
        for name in ("raw_download", "export_download"):
            d = large[name]
            lines.append(f"| {name.replace('_', ' ')} | {d['status']} | {d['content_length']} | {d['bytes']} | "
                         f"{d['byte_for_byte']} | {d['seconds']} | {d['ended']} |")
        lines += ["", f"Evaluation of the flight (UKF): {large['evaluation']}; training of the model: "
                      f"{large['training']}.\n", "| page | status | seconds (1st, 2nd, 3rd view) | HTML bytes |",
                  "|---|---|---|---|"]
        for name in ("flight_page", "report_page"):
            v = large[name]
            lines.append(f"| {name.replace('_', ' ')} | {v['status']} | {v['seconds']} | {v['html_bytes']} |")
    export_kill = results.get("kill_during_export")
    if export_kill:
        lines += ["", "## 5. kill -9 during an export (a slow client reading the large CSV export), then restart\n",
                  "| check | result |", "|---|---|"]
        lines += [f"| {key} | {value} |" for key, value in export_kill.items()]
    full = results.get("full_database")
    if full:
        lines += ["", "## 6. The database on a small tmpfs, filled during a training, then freed\n",
                  "| check | result |", "|---|---|"]
        lines += [f"| {key} | {value} |" for key, value in full.items()]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--compare", metavar="DIR", help="also run phase 1 against the learnest installed in DIR")
    parser.add_argument("--phases", default="1,2,3,4,5,6", help="which phases to run (the others keep their "
                                                                 "committed results)")
    args = parser.parse_args()
    phases = {int(p) for p in args.phases.split(",") if p.strip()}
    if 6 in phases and os.environ.get("LEARNEST_BENCH_NAMESPACE") != "1":
        # a tmpfs needs a mount namespace of our own: run this benchmark again inside one
        if subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0:
            os.environ["LEARNEST_BENCH_NAMESPACE"] = "1"
            os.execvp("unshare", ["unshare", "-rm", sys.executable, *sys.argv])
        print("phase 6 needs `unshare -rm` (user and mount namespaces) to mount a tmpfs: skipped")
        phases.discard(6)
    started = time.perf_counter()
    path = OUT / "service_faults.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    with tempfile.TemporaryDirectory(prefix="learnest-faults-", ignore_cleanup_errors=True) as name:
        root = Path(name)
        logs = root / "logs"
        logs.mkdir()
        flights = make_flights(logs, FLIGHTS + LOAD_UPLOADS)
        if 1 in phases:
            bombs = [make_bomb(logs / f"bomb_{k:02d}.mcap", k) for k in range(BOMBS)]
            mixed = [p for pair in zip(bombs, flights[:FLIGHTS], strict=True) for p in pair]
            runs = []
            if args.compare:
                runs.append(uploads_vs_health(root, mixed, str(Path(args.compare).resolve()), "compared"))
            runs.append(uploads_vs_health(root, mixed, None, "this"))
            results["uploads_vs_health"] = runs
        if 2 in phases:
            results["load_during_training"] = load_during_training(root, flights[:3], flights[FLIGHTS:])
        if 3 in phases:
            results["kill_during_job"] = kill_during_job(root, flights, flights[5])
        if 4 in phases or 5 in phases:
            large = large_downloads(root, flights[0])
            results["large_downloads"] = large
            if 5 in phases:
                results["kill_during_export"] = kill_during_export(root, large["evaluation_id"])
        if 6 in phases:
            results["full_database"] = full_database(root, flights)
    results["command"] = COMMAND + (f" --compare {args.compare}" if args.compare else "") + \
        (f" --phases {args.phases}" if args.phases != "1,2,3,4,5,6" else "")
    results.setdefault("phase_commands", {}).update({str(phase): results["command"] for phase in phases})
    results["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    results["seconds"] = round(time.perf_counter() - started, 1)
    OUT.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1) + "\n")
    (OUT / "service_faults.md").write_text(markdown(results))
    print(markdown(results))
    checks = []
    kill = results.get("kill_during_job")
    if kill:
        checks.append(kill["orphaned_processes"] == 0 and kill["stuck_jobs"] == 0 and kill["orphaned_blobs"] == 0
                      and kill["temp_entries_after_restart"] == 0 and kill["integrity_check"] == "ok")
    large = results.get("large_downloads")
    if large:
        checks.append(large["raw_download"]["byte_for_byte"] and large["export_download"]["byte_for_byte"])
    export_kill = results.get("kill_during_export")
    if export_kill:
        checks.append(export_kill["orphaned_processes"] == 0 and export_kill["temp_entries_after_restart"] == 0
                      and export_kill["stuck_jobs"] == 0 and export_kill["integrity_check"] == "ok")
    full = results.get("full_database")
    if full:
        checks.append(full["server_errors_while_full"] == 0 and not full["sql_in_any_answer_or_error"]
                      and full["all_jobs_final_within_s"] <= 60)
    return 0 if all(checks) else 1


if __name__ == "__main__":
    sys.exit(main())
