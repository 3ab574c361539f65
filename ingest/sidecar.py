"""Metadata sidecars (NanoBench ``*_metadata.yaml``, crazyswarm2 ``info*.yaml``): small YAML read safely.

``yaml.safe_load`` builds no objects but still expands aliases, so 352 bytes of nested ``&a [*b, *b, ...]``
become a structure of millions of nodes (the "billion laughs").  A sidecar is a flat record of a flight;
it never needs an alias or megabytes, so both are refused before anything is built.
"""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from .flight import IngestError

MAX_SIDECAR_BYTES = 1 << 20   # a metadata sidecar is a few kB; anything past 1 MiB is not one
MAX_SIDECAR_NODES = 100_000   # scalars + collections, counted on the parse events
MAX_FLOW_DEPTH = 64           # [ and { nesting: PyYAML's scanner is quadratic in it (2000 levels take ~20 s)


class SidecarTooLarge(IngestError):
    """A sidecar past a cap (size, aliases, nodes): the whole upload is refused, not just the sidecar."""


def _flow_depth(text: str) -> int:
    """Deepest nesting of [ and { in the text (quotes not parsed: a bound, checked before PyYAML scans it)."""
    depth = deepest = 0
    for bracket in re.sub(r"[^\[\]{}]", "", text):
        depth = depth + 1 if bracket in "[{" else max(depth - 1, 0)
        deepest = max(deepest, depth)
    return deepest


def read_sidecar(path) -> object:
    """The YAML document in ``path``, refused if it is too big, uses aliases or has too many nodes.

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
        Naming the file and the cap it broke.
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
            raise IngestError(path, f"unreadable YAML (brackets nested {depth} deep, more than {MAX_FLOW_DEPTH})")
        nodes = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent):
                raise SidecarTooLarge(path, "YAML aliases are not accepted in metadata (an alias can expand a few "
                                        "bytes into gigabytes)")
            if isinstance(event, (yaml.ScalarEvent, yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                nodes += 1
                if nodes > MAX_SIDECAR_NODES:
                    raise SidecarTooLarge(path, f"metadata sidecar with more than {MAX_SIDECAR_NODES} YAML nodes")
        return yaml.safe_load(text)
    except SidecarTooLarge:
        raise
    # ValueError: an integer of more than 4300 digits (Python's int-from-text cap); RecursionError: a
    # document nested thousands of levels deep (PyYAML builds it recursively)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError, yaml.YAMLError) as err:
        raise IngestError(path, f"unreadable YAML ({type(err).__name__}: {str(err)[:200]})") from None
