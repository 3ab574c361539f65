"""The text of a CSV log as both readers see it: lines of any line ending, stripped cells, a table of
string cells read in one pass, and numbers with the line of any cell that is not one."""
from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pandas as pd

from ...flight import IngestError, existing_file

SNIFF_BYTES = 1 << 16
MAX_COLUMNS = 10_000               # a full-body Nexus export has a few hundred


def read_lines(path: Path) -> tuple[list[str], bool]:
    """The file's lines (CRLF, CR or LF) and whether it ends with a line break."""
    existing_file(path, "CSV log")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IngestError(path, f"cannot read ({err.strerror or err})") from None
    # Names may be in a Windows code page; numbers are ASCII either way, so undecodable bytes just become �.
    text = data.decode("utf-8-sig", errors="replace").replace("\r\n", "\n").replace("\r", "\n")
    ends_with_newline = text.endswith("\n")
    lines = text.split("\n")[:-1] if ends_with_newline else text.split("\n")
    if all(is_blank(line) for line in lines):
        raise IngestError(path, "empty file" + (" (only blank lines)" if data.strip() else ""))
    return lines, ends_with_newline


def split_cells(line: str) -> list[str]:
    """The comma-separated cells of a line, each stripped of spaces and surrounding double quotes.

    No CSV quoting: a comma inside quotes still splits.
    """
    return [cell.strip().strip('"').strip() for cell in line.split(",")]


def is_blank(line: str) -> bool:
    """True for a line of nothing but commas and whitespace."""
    return not line.replace(",", "").strip()


def is_number(text: str) -> bool:
    """Whether float() parses the text (so "nan" and "inf" count as numbers)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def string_table(lines: list[str], usecols: list[int]) -> pd.DataFrame:
    """Cells as stripped strings, one row per line (so row i is lines[i]); short rows padded with ""."""
    n_fields = max(max(line.count(",") for line in lines) + 1, max(usecols) + 1)
    if n_fields > MAX_COLUMNS:
        raise ValueError(f"{n_fields} columns in a row: not a log export")
    try:
        table = pd.read_csv(io.StringIO("\n".join(lines) + "\n"), header=None, names=range(n_fields),
                            usecols=usecols, dtype=str, na_filter=False, quoting=csv.QUOTE_NONE,
                            skip_blank_lines=False, engine="c")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, OverflowError) as err:
        raise ValueError(f"malformed CSV ({(str(err).strip().splitlines() or [type(err).__name__])[-1]})") from None
    if len(table) != len(lines):  # cannot happen with QUOTE_NONE and blank lines kept; guards line numbers
        raise ValueError(f"malformed CSV ({len(table)} rows parsed from {len(lines)} lines)")
    return table.fillna("").apply(lambda column: column.str.strip())


def parse_numbers(path: Path, cells: pd.Series, what: str, first_line: int) -> np.ndarray:
    """Floats from string cells; blank -> NaN; anything else that is not a number -> IngestError."""
    values = pd.to_numeric(cells.replace("", "nan"), errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(np.isnan(values) & (cells != "").to_numpy() & (cells.str.lower() != "nan").to_numpy())
    if bad.size:
        raise IngestError(path, f"line {first_line + bad[0]}: non-numeric value {cells.iloc[bad[0]]!r} in "
                                f"column {what} ({bad.size} such cell(s))")
    return values

