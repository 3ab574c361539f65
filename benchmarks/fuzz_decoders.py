"""Fuzz benchmark of the ingest decoders: every generated or mutated input must either read or
be refused with `IngestError`; anything else is a crash, an input past the per-file time limit a hang.

Decoders, each fed through ``learnest.ingest.read_flights`` (content sniffing included):
  nanobench      a NanoBench CSV
  metadata_yaml  a valid NanoBench CSV with a mutated ``<stem>_metadata.yaml`` sidecar beside it
  usd            a Crazyflie uSD binary log (format versions 1 and 2)
  vicon_cfclient a Vicon CSV export + cfclient CSV log pair (one or both files mutated)
  mcap           MCAP recordings (ROS 2 CDR and JSON encodings)
  rosbag         ROS 2 sqlite3 .db3 and ROS 1 .bag

Seeds are short simulated flights (4.4 s, mocap 50 Hz, IMU 100 Hz) written by the project's own writers
(ingest.sim.write_flight,
rosbag BagWriter).  Inputs are made by a fixed-seed numpy RNG: byte-level mutations (bit flips, byte
insert/delete, "interesting" integers over length fields, truncation, splicing two seeds, random bytes)
stacked 1-3 deep, text-level ones for CSV/YAML (numbers replaced by huge/NaN/negative/empty/text values,
lines duplicated/deleted/swapped, header permutations, a column scaled or frozen, time stamps reversed or
repeated) and structured YAML documents of random types.

Each input runs in one of two worker processes (address space capped at MEMORY_LIMIT_BYTES, so a runaway
allocation shows as MemoryError); a worker that does not answer within TIME_LIMIT_S is killed and the
input counts as a hang; a worker that dies (segfault) counts as a crash.  Crashing inputs up to 64 kB are
saved under results/fuzz_crashes/<decoder>/ (first few per exception type).

Hostile cases (after the decoders; each in a fresh worker, so its peak RSS is its own): hand-made inputs
that a mutation would not find - a ROS 2 .db3 whose ``messages.data`` is a virtual generated column
``zeroblob(N)`` (80 rows x 25 MB from a 24-kB file), one such value of 1 GB, an endless recursive view as
``messages``; a NanoBench sidecar nested 260 deep as block sequences (``- - - ...``), 200 deep as block
mappings, and 3000 deep in flow brackets.  Each must be refused (or read) with peak RSS under HOSTILE_RSS_MB.

Run:  .venv/bin/python benchmarks/fuzz_decoders.py [--inputs 10000] [--decoders nanobench,usd,...] [--no-hostile]
      (writes benchmarks/results/fuzz_decoders.{json,md})
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import shlex
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent / "results"
CRASH_DIR = OUT / "fuzz_crashes"
TIME_LIMIT_S = 5.0
MEMORY_LIMIT_BYTES = 3 << 30
WORKERS = 2
SAVE_PER_TYPE = 3
SAVE_MAX_BYTES = 64 << 10
DECODERS = ("nanobench", "metadata_yaml", "usd", "vicon_cfclient", "mcap", "rosbag")
HOSTILE_RSS_MB = 500
INTERESTING = (0, 1, 2, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF,
               2**63 - 1, 2**64 - 1, 2**31, 4096, 65536)
BAD_NUMBERS = (b"", b"nan", b"NaN", b"inf", b"-inf", b"1e308", b"-1e308", b"1e999", b"-0", b"0", b"-1",
               b"99999999999999999999", b"abc", b"1,2", b'"', b"0x10", b"1e-320", b"--1", b" ", b"\x00")


# -- seeds -------------------------------------------------------------------------------------------------
def _metadata(rows: int) -> dict:
    """A NanoBench-like metadata record (keys as the recorder writes them)."""
    return {"battery_voltage_start": 4.08, "battery_voltage_end": 3.98, "category": "tracking",
            "crazyflie_id": "CF_01", "firmware_version": "2025.12.1",
            "params": {"altitude_m": 1.0, "duration_s": 2.0, "radius_m": 0.5, "speed_mps": 0.6},
            "recording_start_utc": "20260302T032318Z", "recording_end_utc": "20260302T032345Z", "repetition": 1,
            "row_counts": {"imu": rows, "vicon": rows, "motor": rows, "power": rows // 10, "setpoint": rows,
                           "pid_output": rows},
            "trajectory_id": "fuzz_circle", "trajectory_type": "circle"}


def make_seeds(directory: Path) -> dict[str, list[list[tuple[str, bytes]]]]:
    """{decoder: [seed]}, a seed being the [(file name, content)] given to read_flights together."""
    from learnest.ingest.formats.nanobench import writer as nanobench_writer
    from learnest.ingest.formats.rosbag.writer import BagWriter
    from learnest.ingest.sim import Circle, SensorModel, Timing, simulate, write_flight

    timing = Timing(sit_before_s=0.6, takeoff_s=0.6, hover_s=0.2, land_s=0.6, sit_after_s=0.4)
    sim = simulate(Circle(radius=0.5, speed=0.6, altitude=1.0, duration_s=2.0, ramp_s=0.5), timing=timing, seed=1,
                   sensors=SensorModel(mocap_rate_hz=50.0, imu_rate_hz=100.0))   # few rows: cheap inputs

    def files(fmt, stem, **options):
        return [(p.name, p.read_bytes()) for p in write_flight(sim, fmt, directory / fmt, stem, **options)]

    seeds: dict[str, list[list[tuple[str, bytes]]]] = {
        "nanobench": [files("nanobench", "flight")],
        "usd": [files("usd", "log00"), files("usd-v1", "log01"),
                files("usd", "log02", usd_pose_stream="event")],
        "vicon_cfclient": [files("vicon+cfclient", "flight")],
        "mcap": [files("mcap-ros2", "ros2"), files("mcap-json", "json")],
    }
    csv = directory / "meta" / "flight.csv"
    csv.parent.mkdir()
    t = sim.mocap.t
    acc = np.column_stack([np.interp(t, sim.imu.t, sim.imu.acc_g[:, j]) for j in range(3)])
    nanobench_writer.write(csv, 1.7e9 + t, sim.mocap.p, sim.mocap.quat, acc, metadata=_metadata(len(t)))
    seeds["metadata_yaml"] = [[(csv.name, csv.read_bytes()), ("flight_metadata.yaml",
                                                              (csv.with_name("flight_metadata.yaml")).read_bytes())]]
    bags = []
    for storage, name in (("sqlite3", "bag2"), ("ros1", "bag1.bag")):
        with BagWriter(directory / name, storage) as bag:
            bag.add_pose("/cf1/pose", sim.mocap.t, sim.mocap.p, sim.mocap.quat)
            bag.add_imu("/cf1/imu", sim.imu.t, sim.imu.acc_g)
        bags.append([(bag.storage_file.name, bag.storage_file.read_bytes())])
    seeds["rosbag"] = bags
    return seeds


# -- mutations ---------------------------------------------------------------------------------------------
def _bitflip(rng, data: bytes, _other) -> bytes:
    if not data:
        return data
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(len(buf)))
        buf[i] ^= 1 << int(rng.integers(8))
    return bytes(buf)


def _insert(rng, data: bytes, _other) -> bytes:
    i = int(rng.integers(len(data) + 1))
    return data[:i] + rng.bytes(int(rng.integers(1, 65))) + data[i:]


def _delete(rng, data: bytes, _other) -> bytes:
    if not data:
        return data
    i = int(rng.integers(len(data)))
    return data[:i] + data[i + int(rng.integers(1, 257)):]


def _truncate(rng, data: bytes, _other) -> bytes:
    return data[:int(rng.integers(len(data) + 1))]


def _splice(rng, data: bytes, other: bytes) -> bytes:
    return data[:int(rng.integers(len(data) + 1))] + other[int(rng.integers(len(other) + 1)):]


def _interesting(rng, data: bytes, _other) -> bytes:
    """An integer that breaks length and count fields, written over 1, 2, 4 or 8 bytes, either endianness."""
    width = int(rng.choice([1, 2, 4, 8]))
    if len(data) < width:
        return data
    value = int(rng.choice(INTERESTING)) % (1 << (8 * width))
    raw = value.to_bytes(width, str(rng.choice(["little", "big"])))   # type: ignore[arg-type]
    i = int(rng.integers(len(data) - width + 1))
    return data[:i] + raw + data[i + width:]


def _overwrite(rng, data: bytes, _other) -> bytes:
    if not data:
        return data
    i = int(rng.integers(len(data)))
    chunk = rng.bytes(int(rng.integers(1, 33)))
    return data[:i] + chunk + data[i + len(chunk):]


def _random_bytes(rng, _data: bytes, _other) -> bytes:
    return rng.bytes(int(rng.integers(0, 4096)))


BYTE_MUTATIONS = (_bitflip, _insert, _delete, _truncate, _splice, _interesting, _overwrite, _bitflip,
                  _interesting, _overwrite)


def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def _numbers(rng, data: bytes, _other) -> bytes:
    """Some fields of some lines replaced by huge / NaN / negative / empty / text values."""
    lines = _lines(data)
    for _ in range(int(rng.integers(1, 6))):
        k = int(rng.integers(len(lines)))
        fields = lines[k].split(b",")
        j = int(rng.integers(len(fields)))
        fields[j] = BAD_NUMBERS[int(rng.integers(len(BAD_NUMBERS)))] if rng.random() < 0.85 else \
            str(float(rng.standard_normal()) * 10 ** float(rng.integers(-5, 30))).encode()
        lines[k] = b",".join(fields)
    return b"\n".join(lines)


def _column_values(rng, data: bytes, _other) -> bytes:
    """One column over a run of rows: all one bad value, scaled by 1000, or constant."""
    lines = _lines(data)
    if len(lines) < 3:
        return data
    j = int(rng.integers(len(lines[0].split(b","))))
    start = int(rng.integers(1, len(lines)))
    stop = start + int(rng.integers(1, len(lines)))
    mode = int(rng.integers(3))
    bad = BAD_NUMBERS[int(rng.integers(len(BAD_NUMBERS)))]
    for k in range(start, min(stop, len(lines))):
        fields = lines[k].split(b",")
        if j >= len(fields):
            continue
        if mode == 0:
            fields[j] = bad
        elif mode == 1:
            try:
                fields[j] = repr(float(fields[j]) * 1000).encode()
            except ValueError:
                pass
        else:
            fields[j] = lines[start].split(b",")[j] if j < len(lines[start].split(b",")) else b""
        lines[k] = b",".join(fields)
    return b"\n".join(lines)


def _line_edits(rng, data: bytes, _other) -> bytes:
    """Duplicate, delete, swap or reverse lines (time stamps repeated, out of order, gaps)."""
    lines = _lines(data)
    if len(lines) < 3:
        return data
    mode = int(rng.integers(5))
    i = int(rng.integers(1, len(lines)))
    n = int(rng.integers(1, max(2, len(lines) // 4)))
    if mode == 0:
        lines[i:i] = lines[i:i + n] * int(rng.integers(1, 4))
    elif mode == 1:
        del lines[i:i + n]
    elif mode == 2:
        j = int(rng.integers(1, len(lines)))
        lines[i], lines[j] = lines[j], lines[i]
    elif mode == 3:
        lines[1:] = lines[:0:-1]
    else:
        lines = lines[:i]
    return b"\n".join(lines)


def _header(rng, data: bytes, _other) -> bytes:
    """Header line permuted, a name dropped, duplicated, renamed, or the header line removed or repeated."""
    lines = _lines(data)
    head = lines[0].split(b",")
    mode = int(rng.integers(5))
    if mode == 0:
        head = [head[k] for k in rng.permutation(len(head))]
    elif mode == 1 and len(head) > 1:
        del head[int(rng.integers(len(head)))]
    elif mode == 2:
        head.insert(int(rng.integers(len(head) + 1)), head[int(rng.integers(len(head)))])
    elif mode == 3:
        head[int(rng.integers(len(head)))] = rng.choice([b"", b"x", b"t", b"\xff\xfe", b"acc.x", b"pos_x"])
    else:
        return b"\n".join(lines[1:] if rng.random() < 0.5 else [lines[0]] + lines)
    return b"\n".join([b",".join(head)] + lines[1:])


def _encoding(rng, data: bytes, _other) -> bytes:
    """A BOM, CRLF line ends, a non-UTF-8 byte, a NUL or a very long line."""
    mode = int(rng.integers(5))
    if mode == 0:
        return b"\xef\xbb\xbf" + data
    if mode == 1:
        return data.replace(b"\n", b"\r\n")
    i = int(rng.integers(len(data) + 1))
    insert = (b"\xff\xfe\x80", b"\x00", b"9" * int(rng.integers(1000, 200_000)))[mode - 2]
    return data[:i] + insert + data[i:]


TEXT_MUTATIONS = (_numbers, _numbers, _column_values, _line_edits, _header, _encoding) + BYTE_MUTATIONS


def _yaml_value(rng, depth: int = 0):
    """A random YAML-able value: the types a sidecar field might wrongly hold."""
    kind = int(rng.integers(9 if depth < 3 else 6))
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.random() < 0.5)
    if kind == 2:
        return [0, 1, -1, 2**31, -2**63, 10**30, 10**400, -10**400][int(rng.integers(8))]
    if kind == 3:
        return float(rng.choice([0.0, -1.0, 1e308, float("nan"), float("inf"), -float("inf"), 2.5]))
    if kind == 4:
        return str(rng.choice(["", "imu", "x" * 1000, "2026-03-02", "1e3", "ünï"]))
    if kind == 5:
        return str(rng.integers(1 << 30))
    if kind == 6:
        return [_yaml_value(rng, depth + 1) for _ in range(int(rng.integers(4)))]
    return {str(rng.choice(["imu", "vicon", "motor", "row_counts", "a", "1"])): _yaml_value(rng, depth + 1)
            for _ in range(int(rng.integers(4)))}


def _yaml_structured(rng, data: bytes, _other) -> bytes:
    """The sidecar parsed, some fields (or the whole document) replaced by values of random types."""
    import yaml

    try:
        document = yaml.safe_load(data.decode("utf-8", "replace")) if rng.random() < 0.9 else None
    except Exception:  # noqa: BLE001 - an earlier mutation broke it: start from a random document
        document = None
    if not isinstance(document, dict) or rng.random() < 0.1:
        document = _yaml_value(rng)
    else:
        for _ in range(int(rng.integers(1, 4))):
            keys = list(document) + ["row_counts", "crazyflie_id"]
            key = keys[int(rng.integers(len(keys)))]
            if key == "row_counts" and isinstance(document.get(key), dict) and rng.random() < 0.6:
                sub = document[key]
                sub[str(rng.choice(list(sub) or ["imu"]))] = _yaml_value(rng, 1)
            else:
                document[key] = _yaml_value(rng, 1)
    return yaml.safe_dump(document, allow_unicode=True).encode()


YAML_SNIPPETS = (b"!!binary aGVsbG8=", b"!!set {x, y}", b"2026-03-02", b"2026-03-02 10:00:00", b".nan", b"-.inf",
                 b"1" + b"0" * 400, b"!!float 1e400", b"[1, [2, {a: b}]]", b"{}", b"~", b"0x1F", b"0o17", b"1_000",
                 b"!!python/object:os.system ls", b"&a [*a]", b"*undefined", b"\'", b"yes", b"|\n  text",
                 b"9" * 5000, b"[" * 20_000 + b"]" * 20_000, b"{a: " * 5000 + b"1" + b"}" * 5000)


def _yaml_tags(rng, data: bytes, _other) -> bytes:
    """A field's value replaced by a YAML tag, date, special float, huge integer, alias or flow collection."""
    lines = _lines(data)
    k = int(rng.integers(len(lines)))
    if b":" in lines[k]:
        key, _, _ = lines[k].partition(b":")
        lines[k] = key + b": " + YAML_SNIPPETS[int(rng.integers(len(YAML_SNIPPETS)))]
    return b"\n".join(lines)


YAML_MUTATIONS = (_yaml_structured, _yaml_structured, _yaml_tags, _yaml_tags, _numbers, _line_edits, _encoding) + \
    BYTE_MUTATIONS


def generate(decoder: str, seeds: list[list[tuple[str, bytes]]], rng) -> tuple[list[tuple[str, bytes]], str]:
    """One input for `decoder`: a seed with one of its files mutated (for the Vicon/cfclient pair sometimes
    both), and the mutation names."""
    seed = seeds[int(rng.integers(len(seeds)))]
    other_seed = seeds[int(rng.integers(len(seeds)))]
    files = list(seed)
    if decoder == "metadata_yaml":
        targets, table = [1], YAML_MUTATIONS
    elif decoder in ("nanobench", "vicon_cfclient"):
        targets = [int(rng.integers(len(files)))] if rng.random() < 0.8 else list(range(len(files)))
        table = TEXT_MUTATIONS
    else:
        targets, table = [0], BYTE_MUTATIONS + (_random_bytes,) if rng.random() < 0.02 else BYTE_MUTATIONS
    names = []
    for k in targets:
        data, other = files[k][1], other_seed[min(k, len(other_seed) - 1)][1]
        for _ in range(int(rng.integers(1, 4))):
            mutation = table[int(rng.integers(len(table)))]
            data = mutation(rng, data, other)
            names.append(mutation.__name__.lstrip("_"))
        files[k] = (files[k][0], data)
    return files, "+".join(names)


# -- hostile cases -----------------------------------------------------------------------------------------
def _db3(seed: bytes, script: str) -> bytes:
    """The seed .db3 with ``script`` (SQL) applied, as bytes."""
    import sqlite3

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bag.db3"
        path.write_bytes(seed)
        with sqlite3.connect(path) as db:
            db.executescript(script)
        with sqlite3.connect(path) as db:
            db.execute("VACUUM")
        return path.read_bytes()


def _generated(data_sql: str, rows: int) -> str:
    return f"""ALTER TABLE messages RENAME TO old_messages;
        CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
                              data BLOB GENERATED ALWAYS AS ({data_sql}) VIRTUAL);
        INSERT INTO messages(id, topic_id, timestamp) SELECT id, topic_id, timestamp FROM old_messages LIMIT {rows};
        DROP TABLE old_messages;"""


ENDLESS_VIEW = """ALTER TABLE messages RENAME TO old_messages;
    CREATE VIEW messages AS WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n)
        SELECT i AS id, 1 AS topic_id, i AS timestamp, zeroblob(100000) AS data FROM n;"""


def hostile_cases(seeds) -> dict[str, list[tuple[str, bytes]]]:
    """{case: the files given to read_flights together} (module docstring)."""
    [(bag_name, bag)] = next(s for s in seeds["rosbag"] if s[0][0].endswith(".db3"))
    csv, sidecar = seeds["metadata_yaml"][0]
    deep_mapping = "".join(" " * k + f"k{k}:\n" for k in range(200)) + " " * 200 + "1\n"
    return {
        "db3_generated_zeroblob_80x25MB": [(bag_name, _db3(bag, _generated("zeroblob(25000000)", 80)))],
        "db3_generated_zeroblob_1GB": [(bag_name, _db3(bag, _generated("zeroblob(1000000000)", 1)))],
        "db3_endless_view": [(bag_name, _db3(bag, ENDLESS_VIEW))],
        "yaml_block_sequence_260_deep": [csv, (sidecar[0], ("- " * 260 + "x\n").encode())],
        "yaml_block_mapping_200_deep": [csv, (sidecar[0], deep_mapping.encode())],
        "yaml_flow_3000_deep": [csv, (sidecar[0], ("a: " + "[" * 3000 + "\n").encode())],
    }


def hostile(seeds, root: Path) -> dict:
    """Each hostile case in a fresh worker: outcome, exception type, message, seconds, peak RSS (MB)."""
    context = mp.get_context("fork")
    results = {}
    for k, (case, files) in enumerate(hostile_cases(seeds).items()):
        worker = Worker(context, root / "hostile", k, seeds["nanobench"][0])
        worker.submit(files)
        answer = None
        while answer is None:
            time.sleep(0.01)
            answer = worker.poll()
        worker.stop()
        outcome, kind, message, seconds, rss_kb = answer
        results[case] = {"outcome": outcome, "type": kind, "message": message[:200], "seconds": round(seconds, 3),
                         "peak_rss_mb": round(rss_kb / 1024, 1), "input_bytes": sum(len(d) for _, d in files)}
        print(f"hostile {case}: {outcome} ({kind}) in {seconds:.2f} s, peak RSS {rss_kb / 1024:.0f} MB, "
              f"{results[case]['input_bytes']} bytes: {message[:120]}", flush=True)
    return results


# -- workers -----------------------------------------------------------------------------------------------
def _worker(connection, directory: str, warm_up) -> None:
    """Read each input given with read_flights; answer (outcome, exception type, message, seconds, maxrss kB).
    A valid seed is read first, untimed: the lazy imports (scipy, pandas) are not charged to an input."""
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    import warnings

    from learnest.ingest import IngestError, read_flights, summary

    warnings.simplefilter("ignore")
    work = Path(directory)
    first = True
    while True:
        try:
            job = warm_up if first else connection.recv()
        except EOFError:      # the parent is gone
            return
        if job is None:
            return
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        paths = []
        for name, data in job:
            (work / name).write_bytes(data)
            paths.append(work / name)
        read = [p for p in paths if not p.name.endswith("_metadata.yaml")]
        start = time.perf_counter()
        try:
            warned = []
            for flight in read_flights(read):    # an accepted input must give a Flight the service can store
                flight.to_bytes()
                json.dumps(summary(flight), allow_nan=False)
                warned += [str(w) for w in flight.meta.get("warnings") or []]
            outcome, kind, message = "ok", "", "; ".join(warned)[:300]
        except IngestError as err:
            outcome, kind, message = "rejected", type(err).__name__, str(err)[:300]
        except BaseException as err:  # noqa: BLE001 - the point is to catch everything else
            tb = traceback.extract_tb(err.__traceback__)
            where = next((f"{Path(f.filename).name}:{f.lineno}" for f in reversed(tb) if "learnest" in f.filename),
                         f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "")
            outcome, kind, message = "crash", type(err).__name__, f"{where}: {str(err)[:300]}"
        seconds = time.perf_counter() - start
        if first:
            first = False
            connection.send("ready")
            continue
        connection.send((outcome, kind, message, seconds, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss))


class Worker:
    """One worker process with its pipe; restarted after a hang or a death."""

    def __init__(self, context, root: Path, index: int, warm_up):
        self.context, self.directory, self.warm_up = context, str(root / f"w{index}"), warm_up
        self.peak_kb = 0
        self._start()

    def _start(self):
        self.connection, child = self.context.Pipe()
        self.process = self.context.Process(target=_worker, args=(child, self.directory, self.warm_up), daemon=True)
        self.process.start()
        child.close()
        if not self.connection.poll(120) or self.connection.recv() != "ready":   # the warm-up read
            raise RuntimeError("fuzz worker did not start")

    def submit(self, job):
        self.connection.send(job)
        self.started = time.perf_counter()

    def poll(self):
        """The answer, ("hang", ...) past the limit, ("crash", "WorkerDied", ...) if the process died, or None."""
        if self.connection.poll():
            try:
                answer = self.connection.recv()
                self.peak_kb = max(self.peak_kb, answer[4])
                return answer
            except EOFError:
                pass
        elapsed = time.perf_counter() - self.started
        if not self.process.is_alive():
            code = self.process.exitcode
            self._start()
            return ("crash", "WorkerDied", f"exit code {code}", elapsed, 0)
        if elapsed > TIME_LIMIT_S:
            self.process.kill()
            self.process.join()
            self._start()
            return ("hang", "Timeout", f"no answer within {TIME_LIMIT_S:g} s", elapsed, 0)
        return None

    def stop(self):
        try:
            self.connection.send(None)
        except OSError:
            pass
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()


def _save_crash(decoder: str, kind: str, count: int, files, message: str) -> str | None:
    if count > SAVE_PER_TYPE or sum(len(d) for _, d in files) > SAVE_MAX_BYTES:
        return None
    folder = CRASH_DIR / decoder / f"{kind}_{count}"
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files:
        (folder / name).write_bytes(data)
    (folder / "error.txt").write_text(message + "\n")
    return str(folder.relative_to(OUT.parent))


def fuzz(decoder: str, seeds, count: int, seed: int, root: Path) -> dict:
    rng = np.random.default_rng(seed)
    context = mp.get_context("fork")
    workers = [Worker(context, root / decoder, k, seeds[0]) for k in range(WORKERS)]
    counts = {"ok": 0, "rejected": 0, "crash": 0, "hang": 0}
    crashes: dict[str, dict] = {}
    times: list[float] = []
    busy: dict[int, tuple] = {}
    made, started = 0, time.perf_counter()
    while made < count or busy:
        for k, worker in enumerate(workers):
            if k not in busy and made < count:
                job, how = generate(decoder, seeds, rng)
                worker.submit(job)
                busy[k] = (job, how)
                made += 1
        time.sleep(0.0005)
        for k in list(busy):
            answer = workers[k].poll()
            if answer is None:
                continue
            job, how = busy.pop(k)
            outcome, kind, message, seconds, _ = answer
            counts[outcome] += 1
            times.append(seconds)
            if outcome in ("crash", "hang"):
                key = f"{kind} at {message.split(': ')[0]}" if outcome == "crash" else "hang"
                entry = crashes.setdefault(key, {"type": kind, "count": 0, "example": message, "mutation": how,
                                                 "reproducers": []})
                entry["count"] += 1
                saved = _save_crash(decoder, kind, entry["count"], job, f"{message}\nmutations: {how}")
                if saved:
                    entry["reproducers"].append(saved)
    for worker in workers:
        worker.stop()
    array = np.array(times)
    return {"inputs": count, **counts, "crash_classes": crashes,
            "max_s": float(array.max()), "p99_s": float(np.percentile(array, 99)),
            "median_s": float(np.median(array)), "wall_s": time.perf_counter() - started,
            "peak_rss_mb": max(w.peak_kb for w in workers) / 1024,
            "seed_files": sorted({name for s in seeds for name, _ in s}),
            "seed_bytes": sorted({len(d) for s in seeds for _, d in s})}


def write_report(report: dict) -> None:
    OUT.mkdir(exist_ok=True)
    (OUT / "fuzz_decoders.json").write_text(json.dumps(report, indent=2) + "\n")
    md = ["# Fuzz benchmark of the ingest decoders (benchmarks/fuzz_decoders.py)", "",
          f"Command: `{report['command']}`", "",
          f"Machine: {report['machine']}; {WORKERS} worker processes, per-input limit {TIME_LIMIT_S:g} s, "
          f"address space {MEMORY_LIMIT_BYTES >> 30} GiB per worker; RNG seed {report['rng_seed']}.", "",
          "Outcome per input: ok (a Flight), rejected (`IngestError`, the CLI's one-line error), crash "
          "(any other exception, or the worker died), hang (no answer within the limit).  Peak RSS is the "
          "workers' ru_maxrss (the interpreter with numpy/pandas/learnest loaded included).", "",
          "| decoder | inputs | ok | rejected | crashes | hangs | median | p99 | max | peak RSS |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in report["decoders"].items():
        md.append(f"| {name} | {r['inputs']} | {r['ok']} | {r['rejected']} | {r['crash']} | {r['hang']} | "
                  f"{r['median_s'] * 1e3:.1f} ms | {r['p99_s'] * 1e3:.0f} ms | {r['max_s'] * 1e3:.0f} ms | "
                  f"{r['peak_rss_mb']:.0f} MB |")
    md += ["", "Wall time per decoder (s, 2 workers, on a machine shared with other jobs): "
           + ", ".join(f"{name} {r['wall_s']:.0f}" for name, r in report["decoders"].items()), ""]
    commands = sorted({r.get("command", report["command"]) for r in report["decoders"].values()})
    if len(commands) > 1:
        md += ["Rows come from several runs: " + "; ".join(f"`{c}`" for c in commands), ""]
    classes = [(name, key, c) for name, r in report["decoders"].items() for key, c in r["crash_classes"].items()]
    if classes:
        md += ["## Crash classes", "", "| decoder | class | count | example | reproducer |", "|---|---|---|---|---|"]
        for name, key, c in classes:
            example = c["example"].replace("|", "\\|").replace("\n", " ")[:160]
            md.append(f"| {name} | {key} | {c['count']} | {example} | {', '.join(c['reproducers'][:1])} |")
    else:
        md += ["No crashes and no hangs."]
    if report.get("hostile"):
        md += ["", f"## Hostile cases (each in a fresh worker; peak RSS must stay under {HOSTILE_RSS_MB} MB)", "",
               f"Command: `{report.get('hostile_command', report['command'])}`", "",
               "| case | input bytes | outcome | seconds | peak RSS | message |", "|---|---|---|---|---|---|"]
        for case, r in report["hostile"].items():
            message = r["message"].replace("|", "\\|").replace("\n", " ")[:140]
            md.append(f"| {case} | {r['input_bytes']} | {r['outcome']} ({r['type']}) | {r['seconds']:.2f} | "
                      f"{r['peak_rss_mb']:.0f} MB | {message} |")
    md += ["", "Seeds (a simulated 4.4-s flight: a 2-s circle with short take-off/landing, mocap 50 Hz, IMU "
           "100 Hz, written by the project's writers):", ""]
    md += [f"- {name}: {', '.join(r['seed_files'])} ({', '.join(map(str, r['seed_bytes']))} bytes)"
           for name, r in report["decoders"].items()]
    (OUT / "fuzz_decoders.md").write_text("\n".join(md) + "\n")


def merged(report: dict) -> dict:
    """The report with the committed results of the decoders this run did not cover (each keeps its command)."""
    path = OUT / "fuzz_decoders.json"
    if not path.exists():
        return report
    committed = json.loads(path.read_text())
    earlier = committed.get("decoders", {})
    kept = {k: committed[k] for k in ("hostile", "hostile_command") if k in committed and k not in report}
    return {**kept, **report, "decoders": {**{k: v for k, v in earlier.items() if k not in report["decoders"]},
                                           **report["decoders"]}}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inputs", type=int, default=10_000, help="inputs per decoder")
    parser.add_argument("--decoders", default=",".join(DECODERS))
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--no-report", action="store_true", help="print only (do not overwrite the results)")
    parser.add_argument("--no-hostile", action="store_true", help="skip the hostile cases")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    report = {"command": "python benchmarks/fuzz_decoders.py " + shlex.join(argv if argv is not None else sys.argv[1:]),
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count()}, "rng_seed": args.seed,
              "time_limit_s": TIME_LIMIT_S, "decoders": {}}
    if not args.no_report:
        for decoder in [d for d in args.decoders.split(",") if d]:
            shutil.rmtree(CRASH_DIR / decoder, ignore_errors=True)
    with tempfile.TemporaryDirectory(dir="/dev/shm" if os.path.isdir("/dev/shm") else None) as tmp:
        root = Path(tmp)
        seeds = make_seeds(root / "seeds")
        for k, decoder in enumerate([d for d in args.decoders.split(",") if d]):
            result = fuzz(decoder, seeds[decoder], args.inputs, args.seed + k, root / "work")
            result["command"] = report["command"]
            report["decoders"][decoder] = result
            report["wall_s"] = time.perf_counter() - started
            if not args.no_report:     # after every decoder: a run cut short keeps what it measured
                write_report(merged(report))
            print(f"{decoder}: {result['inputs']} inputs, ok {result['ok']}, rejected {result['rejected']}, "
                  f"crash {result['crash']}, hang {result['hang']}, median {result['median_s'] * 1e3:.0f} ms, "
                  f"p99 {result['p99_s'] * 1e3:.0f} ms, "
                  f"max {result['max_s'] * 1e3:.0f} ms, peak RSS {result['peak_rss_mb']:.0f} MB, "
                  f"{result['wall_s']:.0f} s", flush=True)
            for key, c in result["crash_classes"].items():
                print(f"    {c['count']:5d}  {key}  | {c['example'][:200]}", flush=True)
        if not args.no_hostile:
            report["hostile"] = hostile(seeds, root / "work")
            report["hostile_command"] = report["command"]
            if not args.no_report:
                write_report(merged(report))


if __name__ == "__main__":
    main()
