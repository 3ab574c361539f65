"""Hostile-input scenarios of `learnest serve` (the third round's high findings): loopback only, ~3 min.

1. Same-name upload race.  16 different simulated flights uploaded at once, every one named ``log.csv`` (16
   drones' logs), 20 times (the flights are deleted between rounds so that each round stores them anew): the
   201 answers, and the flights whose ``GET /flights/{id}/raw`` is not their own bytes (lost files).
2. A gap plan that never ends.  ``POST /evaluations`` with ``gap_s`` 1e-300 and ``gap_every_s`` 2e-300 (a
   registered model, a stored flight), one with gaps finer than the flights' 100 Hz grid, and ``learnest
   evaluate --gap-s 1e-300 --gap-every-s 2e-300``: status or exit code, seconds, the message.
3. Stalled export readers.  Six clients request the CSV export of an evaluation of two 60-s flights and read
   nothing (4-kB receive buffers), on a server with LEARNEST_SEND_TIMEOUT_S=3: the exports on disk while they
   stall (blobs/.exports and blobs/.tmp) against one export's size; whether the server dropped them (once the
   timeout has passed, each reads what is left: a dropped one gets less than the export, and its connection
   ends) and what stays on disk after they are done.

With ``--compare DIR`` (a folder holding another learnest install, e.g. the code before this change:
``pip install --no-deps --target DIR <its source>``) scenarios 1 and 3 run against that code first (not 2:
there the old code's evaluation job would grow without end).

Run:  .venv/bin/python benchmarks/bench_service_hostile.py [--compare DIR] [--rounds 20]
      (writes benchmarks/results/service_hostile.{json,md})
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from bench_service_faults import Server, make_flights

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results"
COMMAND = ".venv/bin/python benchmarks/bench_service_hostile.py"
RACE = 16
SEND_TIMEOUT_S = 3.0
READERS = 6


# -- 1. same-name uploads ----------------------------------------------------------------------------------
def same_name_race(root: Path, flights: list[Path], rounds: int, python_path: str | None, label: str) -> dict:
    server = Server(root / f"race-{label}", python_path)
    contents = [p.read_bytes() for p in flights]
    created = lost = errors = 0
    per_round = []
    try:
        with httpx.Client(base_url=server.url, timeout=120) as client:
            for _ in range(rounds):
                start = threading.Barrier(len(contents))

                with ThreadPoolExecutor(len(contents)) as pool:
                    answers = list(pool.map(lambda content, start=start: _upload(client, start, content), contents))
                lost_now = 0
                for content, answer in zip(contents, answers):
                    if answer.status_code != 201:
                        errors += 1
                        continue
                    created += 1
                    raw = client.get(f"/flights/{answer.json()['id']}/raw")
                    lost_now += raw.status_code != 200 or raw.content != content
                lost += lost_now
                per_round.append(lost_now)
                for answer in answers:
                    if answer.status_code == 201:
                        client.delete(f"/flights/{answer.json()['id']}")
    finally:
        server.stop()
    return {"code": label, "rounds": rounds, "uploads": rounds * len(contents), "created_201": created,
            "not_201": errors, "lost_files": lost, "lost_per_round": per_round}


def _upload(client: httpx.Client, start: threading.Barrier, content: bytes) -> httpx.Response:
    start.wait()   # all at once
    return client.post("/flights", files=[("files", ("log.csv", content))])


# -- 2. gap plans ------------------------------------------------------------------------------------------
def tiny_gaps(root: Path, flights: list[Path]) -> dict:
    server = Server(root / "gaps")
    out: dict = {}
    try:
        with httpx.Client(base_url=server.url, timeout=120) as client:
            flight = client.post("/flights", files=[("files", (flights[0].name, flights[0].read_bytes()))]).json()
            job = client.post("/models", json={"name": "quad", "flight_id": flight["id"], "epochs": 3}).json()
            _wait(client, job["job_id"])
            for name, gaps in (("api_1e-300", {"gap_s": 1e-300, "gap_every_s": 2e-300}),
                               ("api_finer_than_the_grid", {"gap_s": 0.002, "gap_every_s": 0.004})):
                started = time.perf_counter()
                answer = client.post("/evaluations", json={"model": "quad:1", "flights": [flight["id"]],
                                                           "methods": ["ukf"], **gaps})
                out[name] = {"status": answer.status_code, "seconds": round(time.perf_counter() - started, 3),
                             "detail": _detail(answer)}
    finally:
        server.stop()
    started = time.perf_counter()
    cli = subprocess.run([sys.executable, "-m", "learnest.service.cli", "evaluate", "--model", "quad:1",
                          str(flights[0]), "--no-store", "--gap-s", "1e-300", "--gap-every-s", "2e-300"],
                         capture_output=True, text=True, timeout=60, cwd=root,
                         env={**os.environ, "LEARNEST_HOME": str(root / "gaps")})
    out["cli_1e-300"] = {"exit": cli.returncode, "seconds": round(time.perf_counter() - started, 3),
                         "stderr": cli.stderr.strip().splitlines()[-1] if cli.stderr.strip() else ""}
    return out


def _detail(answer: httpx.Response) -> str:
    try:
        detail = answer.json().get("detail")
    except ValueError:
        return answer.text[:200]
    return json.dumps(detail)[:300] if not isinstance(detail, str) else detail[:300]


def _wait(client: httpx.Client, job_id: int, limit_s: float = 300.0) -> dict:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.2)
    raise RuntimeError(f"job {job_id} did not finish within {limit_s} s")


# -- 3. stalled export readers -----------------------------------------------------------------------------
def long_flights(directory: Path) -> list[Path]:
    """Two 60-s simulated circles (a CSV export of their evaluation: ~16 MB)."""
    from learnest.ingest.sim import Circle, simulate, write_flight

    paths = []
    for k in (0, 1):
        circle = Circle(radius=0.4 + 0.1 * k, speed=0.5, altitude=1.0, duration_s=60.0)
        paths += write_flight(simulate(circle, seed=900 + k, name=f"long_{k}"), "nanobench", directory, f"long_{k}")
    return paths


def _export_bytes(home: Path) -> dict[str, int]:
    blobs = home / "blobs"
    found = [p for p in (blobs / ".exports").glob("*") if not p.name.startswith(".")]
    found += [p for p in (blobs / ".tmp").rglob("*") if p.is_file()]
    return {p.name: p.stat().st_size for p in found if p.exists()}


def _stalled(port: int, path: str) -> socket.socket:
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    return sock


def _started(sock: socket.socket) -> bool:
    try:
        return bool(sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT))
    except BlockingIOError:
        return False


def _ended_within(sock: socket.socket, limit_s: float) -> tuple[int, bool]:
    sock.settimeout(limit_s)
    total = 0
    try:
        while chunk := sock.recv(1 << 16):
            total += len(chunk)
    except ConnectionResetError:
        pass
    except TimeoutError:
        return total, False
    return total, True


def stalled_exports(root: Path, flights: list[Path], training: Path, python_path: str | None, label: str) -> dict:
    home = root / f"exports-{label}"
    server = Server(home, python_path, {"LEARNEST_SEND_TIMEOUT_S": SEND_TIMEOUT_S})
    try:
        with httpx.Client(base_url=server.url, timeout=300) as client:
            ids = [client.post("/flights", files=[("files", (p.name, p.read_bytes()))]).json()["id"]
                   for p in [training, *flights]]
            _wait(client, client.post("/models", json={"name": "quad", "flight_id": ids[0], "epochs": 3})
                  .json()["job_id"])
            accepted = client.post("/evaluations", json={"model": "quad:1", "flights": ids[1:],
                                                         "methods": ["ukf", "knode-ukf"]}).json()
            _wait(client, accepted["job_id"])
        path = f"/evaluations/{accepted['evaluation_id']}/estimates?format=csv"
        started = time.perf_counter()
        readers = [_stalled(server.port, path) for _ in range(READERS)]
        deadline = time.monotonic() + 120
        while not all(map(_started, readers)) and time.monotonic() < deadline:
            time.sleep(0.05)
        first_bytes_s = round(time.perf_counter() - started, 2)
        time.sleep(0.5)
        stalled = _export_bytes(home)
        one = max(stalled.values())
        time.sleep(SEND_TIMEOUT_S + 1.0)
        ended = [_ended_within(sock, 5.0) for sock in readers]
        for sock in readers:
            sock.close()
        time.sleep(1.0)
        after = _export_bytes(home)
    finally:
        server.stop()
    return {"code": label, "export_bytes": one, "answers_started_s": first_bytes_s,
            "on_disk_while_stalled_bytes": sum(stalled.values()), "files_while_stalled": len(stalled),
            "times_one_export": round(sum(stalled.values()) / one, 2),
            # dropped: the connection ended before the whole export came (a reader that gets everything once
            # it reads again was waited for, not dropped)
            "dropped_within_timeout": sum(done and got < one for got, done in ended), "readers": READERS,
            "bytes_each_reader_got": [got for got, _ in ended],
            "on_disk_after_bytes": sum(after.values()), "files_after": len(after)}


# -- report ------------------------------------------------------------------------------------------------
def markdown(results: dict) -> str:
    lines = ["# Hostile input, third round: the high findings as scenarios", "",
             f"`{results['command']}` ({results['machine']}; {results['seconds']} s).  Loopback, fresh homes.", "",
             f"## 1. {RACE} uploads of different flights all named log.csv, at once, {results['race'][0]['rounds']} "
             "times", "", "| code | uploads | 201 | not 201 | lost raw files | lost per round |",
             "|---|---|---|---|---|---|"]
    for row in results["race"]:
        lines.append(f"| {row['code']} | {row['uploads']} | {row['created_201']} | {row['not_201']} | "
                     f"{row['lost_files']} | {' '.join(map(str, row['lost_per_round']))} |")
    lines += ["", "## 2. A gap plan that never ends (1e-300-s gaps every 2e-300 s)", "",
              "| request | status / exit | seconds | message |", "|---|---|---|---|"]
    for name, row in results["gaps"].items():
        status = row.get("status", row.get("exit"))
        message = (row.get("detail") or row.get("stderr") or "").replace("|", "\\|")
        lines.append(f"| {name} | {status} | {row['seconds']} | {message} |")
    lines += ["", f"## 3. {READERS} stalled readers of a CSV export (send timeout {SEND_TIMEOUT_S:g} s)", "",
              "| code | export (MB) | on disk while stalled (MB) | × one export | dropped within the timeout | "
              "on disk after (MB) | files after |", "|---|---|---|---|---|---|---|"]
    for row in results["exports"]:
        lines.append(f"| {row['code']} | {row['export_bytes'] / 1e6:.1f} | "
                     f"{row['on_disk_while_stalled_bytes'] / 1e6:.1f} | {row['times_one_export']} | "
                     f"{row['dropped_within_timeout']} of {row['readers']} | "
                     f"{row['on_disk_after_bytes'] / 1e6:.1f} | {row['files_after']} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--compare", metavar="DIR", help="also run scenarios 1 and 3 against the learnest in DIR")
    parser.add_argument("--rounds", type=int, default=20, help="same-name races (default 20)")
    args = parser.parse_args()
    started = time.perf_counter()
    results: dict = {"race": [], "exports": []}
    with tempfile.TemporaryDirectory(prefix="learnest-hostile-", ignore_cleanup_errors=True) as name:
        root = Path(name)
        logs = root / "logs"
        logs.mkdir()
        flights = make_flights(logs, RACE)
        long = long_flights(logs)
        codes = ([(str(Path(args.compare).resolve()), "compared")] if args.compare else []) + [(None, "this")]
        for python_path, label in codes:
            results["race"].append(same_name_race(root, flights, args.rounds, python_path, label))
            results["exports"].append(stalled_exports(root, long, flights[0], python_path, label))
        results["gaps"] = tiny_gaps(root, flights)
    results["command"] = COMMAND + (f" --compare {args.compare}" if args.compare else "") + \
        (f" --rounds {args.rounds}" if args.rounds != 20 else "")
    results["machine"] = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    results["seconds"] = round(time.perf_counter() - started, 1)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "service_hostile.json").write_text(json.dumps(results, indent=1) + "\n")
    (OUT / "service_hostile.md").write_text(markdown(results))
    print(markdown(results))
    this_race, this_exports = results["race"][-1], results["exports"][-1]
    ok = (this_race["lost_files"] == 0 and this_exports["times_one_export"] < 2
          and this_exports["dropped_within_timeout"] == READERS
          and all(row.get("status", 422) == 422 and row["seconds"] < 1 for row in results["gaps"].values()
                  if "status" in row)
          and results["gaps"]["cli_1e-300"]["exit"] == 2)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
