"""Load and fault benchmark of `learnest serve` (issue 10): loopback only, bounded in count and time (~3 min).

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

Run:  .venv/bin/python benchmarks/bench_service_faults.py [--compare DIR]
      (writes benchmarks/results/service_faults.{json,md})
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

    def __init__(self, home: Path, python_path: str | None = None):
        self.home, self.port = home, free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "LEARNEST_HOME": str(home), "LEARNEST_POOL_WORKERS": "1", "NO_PROXY": "127.0.0.1"}
        for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY", "LEARNEST_SCHEDULE_SECONDS"):
            env.pop(name, None)
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


# -- report ---------------------------------------------------------------------------------------------------
def markdown(results: dict) -> str:
    lines = [f"# Service load and fault benchmark\n\n`{results['command']}` on {results['machine']}; "
             f"{results['seconds']:.0f} s in all.  Loopback only, defaults of `learnest serve` "
             f"(LEARNEST_POOL_WORKERS=1).\n", "## 1. 40 concurrent bomb-ish uploads vs GET /health\n",
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
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--compare", metavar="DIR", help="also run phase 1 against the learnest installed in DIR")
    args = parser.parse_args()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="learnest-faults-") as name:
        root = Path(name)
        logs = root / "logs"
        logs.mkdir()
        flights = make_flights(logs, FLIGHTS + LOAD_UPLOADS)
        bombs = [make_bomb(logs / f"bomb_{k:02d}.mcap", k) for k in range(BOMBS)]
        mixed = [p for pair in zip(bombs, flights[:FLIGHTS], strict=True) for p in pair]
        phases = []
        if args.compare:
            phases.append(uploads_vs_health(root, mixed, str(Path(args.compare).resolve()), "compared"))
        phases.append(uploads_vs_health(root, mixed, None, "this"))
        load = load_during_training(root, flights[:3], flights[FLIGHTS:])
        kill = kill_during_job(root, flights, flights[5])
    results = {"command": COMMAND + (f" --compare {args.compare}" if args.compare else ""),
               "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
               "seconds": round(time.perf_counter() - started, 1), "uploads_vs_health": phases,
               "load_during_training": load, "kill_during_job": kill}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "service_faults.json").write_text(json.dumps(results, indent=1) + "\n")
    (OUT / "service_faults.md").write_text(markdown(results))
    print(markdown(results))
    ok = (kill["orphaned_processes"] == 0 and kill["stuck_jobs"] == 0 and kill["orphaned_blobs"] == 0
          and kill["temp_entries_after_restart"] == 0 and kill["integrity_check"] == "ok")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
