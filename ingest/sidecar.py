"""Metadata sidecars (NanoBench ``*_metadata.yaml``, crazyswarm2 ``info*.yaml``): small YAML read safely.

``yaml.safe_load`` builds no objects but still expands aliases, so 352 bytes of nested ``&a [*b, *b, ...]``
become a structure of millions of nodes (the "billion laughs").  A sidecar is a flat record of a flight;
it never needs an alias or megabytes, so both are refused before anything is built.

Nesting is limited for every YAML shape: flow (``[[[...``, counted on the text before PyYAML scans it, as its
scanner is quadratic in that depth) and block (``- - - ...``, counted on the parse events, as is flow).  A
document nested deeper than a record ever is would be stored and then fail every answer that serializes it;
like the other caps it refuses the upload (`SidecarTooLarge`), where a sidecar that is merely unreadable is
ignored with a warning: a client who sends a hostile sidecar learns so, rather than seeing it vanish.
"""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from .flight import IngestError, json_compatible

MAX_SIDECAR_BYTES = 1 << 20   # a metadata sidecar is a few kB; anything past 1 MiB is not one
MAX_SIDECAR_NODES = 100_000   # scalars + collections, counted on the parse events
MAX_FLOW_DEPTH = 64           # [ and { nesting: PyYAML's scanner is quadratic in it (2000 levels take ~20 s)
MAX_DEPTH = 32                # nesting of sequences and mappings, block or flow (a sidecar record: 2-3)


class SidecarTooLarge(IngestError):
    """A sidecar past a cap (size, aliases, nodes, nesting): the whole upload is refused, not just the sidecar."""


def _flow_depth(text: str) -> int:
    """Deepest nesting of [ and { in the text (quotes not parsed: a bound, checked before PyYAML scans it)."""
    depth = deepest = 0
    for bracket in re.sub(r"[^\[\]{}]", "", text):
        depth = depth + 1 if bracket in "[{" else max(depth - 1, 0)
        deepest = max(deepest, depth)
    return deepest


def read_sidecar(path) -> object:
    """The YAML document in ``path``, refused if it is too big, uses aliases, has too many nodes or is nested
    too deep.

    Parameters
    ----------
    path : str or Path
        A small YAML file.

    Returns
    -------
    object
        What ``yaml.safe_load`` gives (a dict for a metadata sidecar).

    Raises
    ------
    SidecarTooLarge
        Naming the file and the cap it broke (size, aliases, nodes, nesting).
    IngestError
        Unreadable or malformed YAML.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_SIDECAR_BYTES:
            raise SidecarTooLarge(path, f"metadata sidecar of {size} bytes: the cap is {MAX_SIDECAR_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
        depth = _flow_depth(text)
        if depth > MAX_FLOW_DEPTH:
            raise SidecarTooLarge(path, f"unreadable YAML (brackets nested {depth} deep, more than {MAX_FLOW_DEPTH})")
        nodes = depth = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise SidecarTooLarge(path, f"unreadable YAML (sequences and mappings nested more than "
                                                f"{MAX_DEPTH} deep)")
            elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
            if isinstance(event, yaml.AliasEvent):
                raise SidecarTooLarge(path, "YAML aliases are not accepted in metadata (an alias can expand a few "
                                        "bytes into gigabytes)")
            if isinstance(event, (yaml.ScalarEvent, yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                nodes += 1
                if nodes > MAX_SIDECAR_NODES:
                    raise SidecarTooLarge(path, f"metadata sidecar with more than {MAX_SIDECAR_NODES} YAML nodes")
        return yaml.safe_load(text)
    except IngestError:   # SidecarTooLarge, or a nesting limit: already says what (an IngestError is a ValueError)
        raise
    # ValueError: an integer of more than 4300 digits (Python's int-from-text cap); RecursionError: a
    # document nested thousands of levels deep (PyYAML builds it recursively)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError, yaml.YAMLError) as err:
        raise IngestError(path, f"unreadable YAML ({type(err).__name__}: {str(err)[:200]})") from None


# -- which files are sidecars, and whose ----------------------------------------------------------------------
# NanoBench: <stem>_metadata.yaml next to <stem>.csv; crazyswarm2-tools: infoNNN.yaml next to the uSD log logNNN
# (an upload stages it as <log>_info.yaml next to the staged log).
NANOBENCH_SIDECAR = re.compile(r"^(?P<stem>.+)_metadata\.ya?ml$", re.IGNORECASE)
INFO_SIDECAR = re.compile(r"^(?:info(?P<number>\d+)|(?P<stem>.+)_info)\.ya?ml$", re.IGNORECASE)
# crazyswarm2's configuration (its firmware_logging names the values of the LogDataGeneric topics) beside an MCAP
# recording or a ROS 2 bag's .db3: <stem>_crazyflies.yaml for that recording, crazyflies.yaml for the folder's.
CRAZYSWARM_CONFIG = re.compile(r"^(?:(?P<stem>.+)_)?crazyflies\.ya?ml$", re.IGNORECASE)
RECORDING_SUFFIXES = (".mcap", ".db3")


def sidecar_log_names(name: str) -> list[str] | None:
    """The file names of the log a sidecar belongs to (any one of them), or None if ``name`` is no sidecar.

    >>> sidecar_log_names("B2_circle_rep1_metadata.yaml")
    ['B2_circle_rep1.csv', 'B2_circle_rep1']
    >>> sidecar_log_names("info182.yaml")
    ['log182']
    >>> sidecar_log_names("crazyflies.yaml")    # crazyswarm2's configuration: every recording of its folder
    ['*.mcap', '*.db3']
    """
    nanobench = NANOBENCH_SIDECAR.match(name)
    if nanobench:
        return [f"{nanobench['stem']}.csv", nanobench["stem"]]
    info = INFO_SIDECAR.match(name)
    if info:
        return [f"log{info['number']}"] if info["number"] else [info["stem"]]
    crazyswarm = CRAZYSWARM_CONFIG.match(name)
    if crazyswarm:
        return [f"{crazyswarm['stem'] or '*'}{suffix}" for suffix in RECORDING_SUFFIXES]
    return None


def info_sidecar(log_path: str | Path) -> Path | None:
    """The crazyswarm2 info sidecar of a uSD log, if there is one: ``infoNNN.yaml`` next to ``logNNN``, or
    ``<log>_info.yaml`` next to the log."""
    log_path = Path(log_path)
    number = re.fullmatch(r"log(\d+)", log_path.name)
    names = [f"info{number[1]}.yaml", f"info{number[1]}.yml"] if number else []
    names += [f"{log_path.name}_info.yaml", f"{log_path.name}_info.yml"]
    return next((log_path.with_name(n) for n in names if log_path.with_name(n).is_file()), None)


def vehicle_info(path: Path, log_variables: set[str], warnings: list[str]) -> dict:
    """What a crazyswarm2 ``info*.yaml`` says about the vehicle: ``mass_kg``, ``controller`` and the whole
    record (``info``).  A sidecar that cannot be read is a warning, not a failure (the log is still a flight);
    a sidecar past a cap (`SidecarTooLarge`) is refused with the log.

    The controller is the sidecar's ``controller`` entry, else "lee" when the log carries the Lee
    controller's variables (``ctrlLee.*``; crazyswarm2-tools' info files list its gains Kpos/KR/Kw).
    """
    try:
        record = read_sidecar(path)
    except SidecarTooLarge:
        raise
    except IngestError as err:
        warnings.append(f"{path.name}: {err.problem}; sidecar ignored")
        return {}
    if not isinstance(record, dict):
        warnings.append(f"{path.name}: not a YAML mapping; sidecar ignored")
        return {}
    mass = record.get("mass")
    if not (isinstance(mass, (int, float)) and not isinstance(mass, bool) and 0.0 < mass < 10.0):
        if mass is not None:
            warnings.append(f"{path.name}: mass = {str(mass)[:40]!r} is not a mass in kg: ignored")
        mass = None
    controller = record.get("controller")
    if not isinstance(controller, str):
        controller = "lee" if any(name.startswith("ctrlLee.") for name in log_variables) else None
    return {"mass_kg": None if mass is None else float(mass), "controller": controller,
            "info": json_compatible(record), "path": str(path)}
