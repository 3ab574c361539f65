"""The uSD log's binary layout: magic byte, versions, value types and one event type's record dtype
(shared by the decoder and the writer)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAGIC = 0xBC
FIXED_FREQUENCY = "fixedFrequency"
FIXED_FREQUENCY_ID = 0xFFFF
TIMESTAMP_FORMATS = {1: ("<u4", 1e-3), 2: ("<u8", 1e-6)}   # version -> (record dtype, seconds per tick)
VALUE_TYPES = {"B": "u1", "b": "i1", "H": "<u2", "h": "<i2", "I": "<u4", "i": "<i4", "f": "<f4", "e": "<f2"}


@dataclass(frozen=True)
class EventType:
    """One event type declared in the header: its id and its variables, which fix the layout of its records.

    Attributes
    ----------
    id : int
        The uint16 id that starts each record of this event.
    name : str
        Event name.
    var_names : tuple of str
        Variable names ("group.name"), in record order.
    var_types : tuple of str
        Struct codes (keys of VALUE_TYPES), one per variable.
    """
    id: int
    name: str
    var_names: tuple[str, ...]
    var_types: tuple[str, ...]      # struct codes, one per variable

    def record_dtype(self, version: int) -> np.dtype:
        """One record as a packed numpy dtype; positional field names cannot clash with variable names."""
        fields = [("id", "<u2"), ("time", TIMESTAMP_FORMATS[version][0])]
        fields += [(f"v{i}", VALUE_TYPES[code]) for i, code in enumerate(self.var_types)]
        return np.dtype(fields)

