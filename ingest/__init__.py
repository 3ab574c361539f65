"""Raw flight logs -> canonical Flights.

`read_flights(paths)` looks at each file's content (never only its extension), pairs files that belong to
one flight (a Vicon export with a cfclient log), runs the adapter and the quality checks, and returns one
Flight per flight.  Every problem is an `IngestError` naming the file.
"""
from __future__ import annotations

import fnmatch
import importlib
from collections.abc import Iterable
from pathlib import Path

from .flight import Flight, IngestError, existing_file

# adapter name -> (reader module, sniff function); the reader module's `read` reads the file.  Order matters
# only for speed (cheap binary magic first).
SINGLE_FILE_ADAPTERS = {
    "usd": (".formats.crazyflie_usd.reader", "sniff"),
    "mcap": (".formats.mcap.reader", "sniff"),
    "rosbag": (".formats.rosbag.reader", "sniff"),
    "nanobench": (".formats.nanobench.reader", "sniff"),
}
PAIR_ROLES = {"vicon": (".formats.vicon_cfclient.vicon", "sniff_vicon"),
              "cfclient": (".formats.vicon_cfclient.cfclient", "sniff_cfclient")}


def _sniffer(module: str, function: str):
    return getattr(importlib.import_module(module, __name__), function)  # imported on first use: CLI start stays fast


def detect(path: str | Path) -> str:
    """The adapter (or pair role) that reads this file, decided from its content.

    Returns
    -------
    str
        ``"usd"``, ``"mcap"``, ``"rosbag"``, ``"nanobench"``, ``"vicon"`` or ``"cfclient"``.

    Raises
    ------
    IngestError
        If the file is missing or empty, or no adapter recognises it.
    """
    path = existing_file(path, "flight log")
    for name, (module, function) in {**SINGLE_FILE_ADAPTERS, **PAIR_ROLES}.items():
        sniff = _sniffer(module, function)
        if sniff(path):
            return name
    missing = _sniffer(".formats.nanobench.reader", "missing_columns")(path)
    if missing:   # most of a NanoBench header: say what is missing, not "unrecognised"
        raise IngestError(path, f"a NanoBench CSV without the column(s) {', '.join(missing)} (it needs "
                                f"{', '.join(_sniffer('.formats.nanobench.reader', 'REQUIRED_COLUMNS'))})")
    raise IngestError(path, "unrecognised format (expected a NanoBench CSV, a Crazyflie uSD log, an MCAP "
                            "file, a ROS bag (ROS 1 .bag or ROS 2 .db3), or a Vicon CSV export together with a "
                            "cfclient CSV log)")


# Files in a folder that are documents, not logs (READMEs, licences, logging configurations).
DOCUMENT_SUFFIXES = (".md", ".txt", ".rst", ".pdf", ".png", ".jpg", ".html")
DOCUMENT_NAMES = ("license", "licence", "readme", "citation", "notice")


def collect_logs(paths: Iterable[str | Path]) -> tuple[list[Path], list[str]]:
    """The log files among ``paths`` (a folder stands for the files in it) and what was left out, and why.

    Metadata sidecars (NanoBench ``*_metadata.yaml``, crazyswarm2 ``infoNNN.yaml`` and ``crazyflies.yaml``) are
    left out: their log's reader reads them from beside the log.  In a folder, documents and files no adapter recognises
    are left out too (as `learnest demo` does); of the files named on their own, documents (LICENSE,
    README.md, ...: what a shell glob brings along) are left out, and any other must be a log.

    Returns
    -------
    (logs, notes)
        The log files in the order given (a folder's in name order), and one line per file left out.

    Raises
    ------
    IngestError
        A path that does not exist, or a file named on its own that no adapter recognises.
    """
    from .sidecar import sidecar_log_names

    logs: list[Path] = []
    notes: list[str] = []
    sidecars: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            for member in sorted(m for m in path.iterdir() if m.is_file()):
                if sidecar_log_names(member.name) is not None:
                    sidecars.append(member)
                elif _is_document(member) or member.name.startswith("."):
                    notes.append(f"skipped {member}: not a flight log")
                else:
                    try:
                        detect(member)
                        logs.append(member)
                    except IngestError as err:
                        notes.append(f"skipped {err}")
        elif sidecar_log_names(path.name) is not None and path.is_file():
            sidecars.append(path)
        elif path.is_file() and _is_document(path):   # a shell glob brings the folder's LICENSE, README...
            notes.append(f"skipped {path}: not a flight log")
        else:
            logs.append(path)
    names = {log.name for log in logs} | {str(log) for log in logs}
    for sidecar in sidecars:
        owners = sidecar_log_names(sidecar.name) or []
        if any(fnmatch.filter(names, name) or fnmatch.filter(names, str(sidecar.with_name(name))) for name in owners):
            notes.append(f"{sidecar.name}: metadata of {owners[0]}, read with it")
        else:
            notes.append(f"skipped {sidecar}: metadata sidecar without its log ({owners[0]}) among the files given")
    return logs, notes


def _is_document(path: Path) -> bool:
    return path.suffix.lower() in DOCUMENT_SUFFIXES or path.stem.lower() in DOCUMENT_NAMES


def group_files(paths: Iterable[str | Path]) -> list[tuple[str, list[Path]]]:
    """[(adapter, [files])]: one entry per flight.  Vicon exports and cfclient logs given together are
    paired in name order (each pair is one flight); every other file is a flight of its own.  A cfclient log
    that carries the received mocap pose (locSrv.*) is a flight of its own ("cfclient") unless Vicon exports
    come with as many cfclient logs.  Metadata sidecars among ``paths`` are skipped (`collect_logs`): the
    readers read them from beside their logs.

    Raises
    ------
    IngestError
        If a file is not recognised, or Vicon exports and cfclient logs do not come in equal numbers.
    """
    from .formats.vicon_cfclient.cfclient import has_pose
    from .sidecar import sidecar_log_names

    singles: list[tuple[str, list[Path]]] = []
    roles: dict[str, list[tuple[str, list[Path]]]] = {"vicon": [], "cfclient": []}
    given = [Path(path) for path in paths]
    logs = [path for path in given if not (path.is_file() and sidecar_log_names(path.name) is not None)]
    if given and not logs:
        raise IngestError(given[0], "a metadata sidecar, not a flight log: give the log it belongs to "
                                    f"({(sidecar_log_names(given[0].name) or ['?'])[0]})")
    for path in logs:
        kind = detect(path)
        (roles[kind] if kind in roles else singles).append((kind, [path]))
    vicon, cfclient = sorted(roles["vicon"]), sorted(roles["cfclient"])
    if len(vicon) != len(cfclient):   # cfclient logs with their own pose need no Vicon export
        own = [entry for entry in cfclient if has_pose(entry[1][0])]
        if len(cfclient) - len(own) == len(vicon):
            singles += [("cfclient", files) for _, files in own]
            cfclient = [entry for entry in cfclient if entry not in own]
    if len(vicon) != len(cfclient):
        longer, shorter = (vicon, cfclient) if len(vicon) > len(cfclient) else (cfclient, vicon)
        missing = "cfclient log" if longer is vicon else "Vicon export"
        raise IngestError(longer[len(shorter)][1][0], f"needs a {missing} of the same flight given with it")
    pairs = [("vicon+cfclient", [v[1][0], c[1][0]]) for v, c in zip(vicon, cfclient)]
    return singles + pairs


# adapters whose recordings hold named topics: the only ones a pose/IMU topic choice applies to
TOPIC_ADAPTERS = ("mcap", "rosbag")


def check_topic_choice(adapter: str, files: list[Path], pose_topic: str | None, imu_topic: str | None) -> None:
    """IngestError when a topic is chosen for a file that has no topics (a CSV, a uSD log)."""
    if (pose_topic or imu_topic) and adapter not in TOPIC_ADAPTERS:
        raise IngestError(files[0], f"a pose/IMU topic was chosen, but this is a {adapter} log, which has no "
                                    f"topics (topics apply to MCAP recordings and ROS bags)")


def read_group(adapter: str, files: list[Path], rate_hz: float = 100.0, *, pose_topic: str | None = None,
               imu_topic: str | None = None, cut: str | bool | tuple | None = None) -> Flight:
    """Read one flight with its adapter, resampled to ``rate_hz``, and run the quality checks.

    Parameters
    ----------
    adapter : str
        A key of ``SINGLE_FILE_ADAPTERS`` or ``"vicon+cfclient"`` (as `group_files` gives).
    files : list of Path
        The flight's file, or [Vicon export, cfclient log].
    rate_hz : float
        Grid rate of the Flight, Hz.
    pose_topic, imu_topic : str, optional
        For MCAP recordings and ROS bags: the pose topic ("topic:body" for one body of a TFMessage or
        NamedPoseArray topic) and the acceleration topic, when the automatic choice is not wanted or ambiguous.
    cut : str, optional
        The stretch to keep: "auto" (default: the flying part, `ingest.flight_span.find_flight`), "none" (the
        whole recording) or "START:STOP" in seconds from the recording's start (`ingest.align.parse_cut`).

    Returns
    -------
    Flight
        With ``meta["quality"]`` = the adapter's issues plus `quality.assess`'s, and ``meta["name"]``
        defaulting to the first file's stem.
    """
    from .align import parse_cut
    from .quality import assess

    check_topic_choice(adapter, files, pose_topic, imu_topic)
    window = parse_cut(cut)
    if adapter == "vicon+cfclient":
        from .formats.vicon_cfclient.reader import read_pair
        flight = read_pair(files[0], files[1], rate_hz=rate_hz, cut=window)
    elif adapter == "cfclient":
        from .formats.vicon_cfclient.reader import read_single
        flight = read_single(files[0], rate_hz=rate_hz, cut=window)
    else:
        module = importlib.import_module(SINGLE_FILE_ADAPTERS[adapter][0], __name__)
        topics = {"pose_topic": pose_topic, "accel_topic": imu_topic} if adapter in TOPIC_ADAPTERS else {}
        flight = module.read(files[0], rate_hz=rate_hz, cut=window, **topics)
    # the adapter may already know of problems (e.g. an ambiguous clock alignment): keep them
    earlier = flight.meta.get("quality", {}).get("issues", [])
    checked = assess(flight)
    issues = list(dict.fromkeys(earlier + checked["issues"]))
    flight.meta["quality"] = {"ok": not issues, "issues": issues}
    flight.meta.setdefault("name", files[0].stem)
    if pose_topic or imu_topic:   # what was asked for (meta["topics"] says what was read): a re-read repeats it
        flight.meta["topic_choice"] = {"pose_topic": pose_topic, "imu_topic": imu_topic}
    if window is not True:        # likewise the cut, when it was not the automatic one
        flight.meta["cut_choice"] = flight.meta["flying_window"]["cut"]
    from .profile import flight_profile

    flight.meta["profile"] = flight_profile(flight)   # vehicle, sensor rates, attitude source: models record it
    return flight


def read_flights(paths: Iterable[str | Path], rate_hz: float = 100.0, *, pose_topic: str | None = None,
                 imu_topic: str | None = None, cut: str | bool | tuple | None = None) -> list[Flight]:
    """Read flight logs of any supported format into Flights (the format is sniffed from the content).

    Parameters
    ----------
    paths : iterable of str or Path
        Log files: NanoBench CSV, Crazyflie uSD logs, MCAP recordings, ROS bags (ROS 1 .bag, ROS 2 sqlite3
        .db3), or Vicon CSV exports given together
        with as many cfclient CSV logs (paired in name order).
    rate_hz : float
        Rate of the uniform grid every flight is resampled to, Hz.
    pose_topic, imu_topic : str, optional
        The topics to read from every MCAP recording / ROS bag given (see `read_group`); a topic choice with
        a file that has no topics is an IngestError, raised before any file is read.
    cut : str, optional
        The stretch of every flight to keep (see `read_group`; default the flying part).

    Returns
    -------
    list of Flight
        One per flight: single files first, in the order given, then the Vicon/cfclient pairs.  A flight
        that fails the quality checks is still returned, with ``flight.quality["ok"] == False``.  Names that
        collide get a suffix (`ingest.names.unique_names`: the parent folder, else a short sha256).

    Raises
    ------
    IngestError
        Naming the file, if one is missing, empty, unrecognised, unpaired or unreadable.

    Examples
    --------
    >>> import learnest as le
    >>> flights = le.read_flights(["sample_logs/circle_rep1.csv", "sample_logs/circle_rep2.csv"])
    >>> flights[0].p.shape[1]
    3
    """
    from .align import parse_cut

    groups = group_files(paths)
    for adapter, files in groups:
        check_topic_choice(adapter, files, pose_topic, imu_topic)
    parse_cut(cut)   # a malformed cut fails before any file is read
    flights = [read_group(adapter, files, rate_hz, pose_topic=pose_topic, imu_topic=imu_topic, cut=cut)
               for adapter, files in groups]
    from .names import unique_names

    unique_names(flights)   # two eckart06 from two folders: eckart06-runA, eckart06-runB
    return flights


def summary(flight: Flight) -> dict:
    """The per-flight record `learnest ingest --json` prints: sources, adapter, duration (s), rate (Hz),
    samples, clock offset (s), quality, the topics read (recordings with topics, else None), warnings
    (e.g. a pose that is the vehicle's onboard estimate), the stretch kept (``kept``: start_s, stop_s,
    recording_s on the recording's grid, the rule and the cut asked for), the vehicle profile
    (`ingest.profile.flight_profile`: vehicle, sensor rates, attitude source) and how each stream was
    delivered (``timing``: `ingest.align.stream_timing`: rate from the time stamps, share delivered, gaps)."""
    from .profile import flight_profile

    return {"source": [s["path"] for s in flight.meta.get("sources", [])], "adapter": flight.meta.get("adapter"),
            "duration_s": round(flight.duration_s, 3), "rate_hz": round(flight.rate_hz, 3),
            "samples": len(flight.t), "clock_offset_s": flight.meta.get("clock_offset_s"),
            "quality": flight.quality, "topics": flight.meta.get("topics"),
            "warnings": list(flight.meta.get("warnings", [])), "kept": flight.meta.get("flying_window"),
            "profile": flight_profile(flight), "timing": flight.meta.get("timing")}


__all__ = ["Flight", "IngestError", "collect_logs", "detect", "group_files", "read_flights", "read_group", "summary"]
