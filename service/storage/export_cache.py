"""Estimate exports, made once and kept: blobs/.exports holds one file per (evaluation, flight or all of its
flights, format) and the estimates it was made from, within a disk budget.

An export of a long flight is hundreds of MB.  Made anew for every download, as it was, six stalled clients
held six copies; here every download of the same export reads the same file:

- **Once.**  One request makes it (a lock per export, across threads and processes); the others wait and
  read what it made.  It is written to a temp file in blobs/.tmp (swept at start if a crash leaves it),
  fsync'ed and renamed into place: a reader sees a whole export or none.  Its name holds a digest of what it
  was made from (the estimates blobs and flight names), so stored estimates replaced or gone are never
  served from an old file.
- **Within a budget.**  The exports kept and those being written may take ``budget_bytes``.  A write that
  would pass it first removes the least recently served exports; one that still does not fit is refused
  with `ExportBudgetExceeded` (507) and its temp file removed (one larger than the whole budget removes no
  other).  An export removed while a client reads it stays readable to that client until it is done (or
  dropped: the server's send deadline).
- **Gone with what it shows.**  `forget_exports` removes an evaluation's exports; deleting an evaluation, a
  flight it scored or its model version calls it.  A request making an export while its evaluation is
  deleted does not put it in place (`still_wanted`, checked under the folder's shared lock that
  `forget_exports` waits for).
"""
from __future__ import annotations

import fcntl
import io
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, BinaryIO

from learnest.errors import NotFound

from .blobs import CHUNK, BlobStore, StorageUnavailable, _fsync_dir, storage_errors, temp_prefix

log = logging.getLogger("learnest.storage")

FOLDER = ".exports"            # under the blob folder: the same file system, so a temp file is renamed in
PART_SUFFIX = ".export-part"   # temp files of exports being written (in blobs/.tmp), counted in the budget


class ExportBudgetExceeded(StorageUnavailable):
    """An export would take the estimate exports past their disk budget: HTTP 507 Insufficient Storage."""


def export_folder(blobs: BlobStore) -> Path:
    """Where the blob store's exports are kept (made if needed)."""
    folder = blobs.root / FOLDER
    folder.mkdir(exist_ok=True)
    return folder


def export_name(evaluation_id: int, flight_id: int | None, digest: str, suffix: str) -> str:
    """``e<evaluation>-<f<flight>|all>-<digest>.<ext>``: `forget_exports` finds an evaluation's by its prefix."""
    return f"{_prefix(evaluation_id, flight_id)}{digest[:32]}{suffix}"


def _prefix(evaluation_id: int, flight_id: int | None) -> str:
    return f"e{int(evaluation_id)}-{'all' if flight_id is None else f'f{int(flight_id)}'}-"


def forget_exports(blobs: BlobStore, evaluation_ids: Iterable[int]) -> list[str]:
    """Remove the kept exports of these evaluations (their evaluation, or a flight or version they show, is
    gone); -> the names removed.  Waits for the exports being made (they then find their evaluation gone).
    Best effort, like `BlobStore.collect`: a file that cannot be removed is logged and left."""
    # with their lock files: a maker that still holds one only makes a file that `still_wanted` refuses
    prefixes = tuple(f"{dot}e{int(i)}-" for i in evaluation_ids for dot in ("", "."))
    removed: list[str] = []
    if not prefixes:
        return removed
    folder = export_folder(blobs)
    with _flock(folder / ".lock", fcntl.LOCK_EX):
        for path in folder.iterdir():
            if path.name.startswith(prefixes):
                try:
                    path.unlink(missing_ok=True)
                except OSError as err:
                    log.warning("export %s not removed (%s)", path.name, err.strerror)
                    continue
                removed.append(path.name)
    return removed


class ExportCache:
    """The kept exports of one blob store (module docstring).

    Parameters
    ----------
    blobs : BlobStore
        Exports live in its ``.exports`` folder; temp files in its ``.tmp``.
    budget_bytes : int
        Disk the exports kept and being written may take together.
    """

    def __init__(self, blobs: BlobStore, budget_bytes: int) -> None:
        self.blobs, self.budget_bytes = blobs, int(budget_bytes)
        self.folder = export_folder(blobs)
        self._lock_path = self.folder / ".lock"

    def open(self, evaluation_id: int, flight_id: int | None, digest: str, suffix: str,
             write: Callable[[IO[bytes]], object], still_wanted: Callable[[], bool]) -> BinaryIO:
        """The export, opened for reading: the kept file, else made once by ``write`` (module docstring).

        Parameters
        ----------
        evaluation_id, flight_id
            Whose export (``flight_id`` None: all the evaluation's flights).
        digest
            Hex digest of what the export is made from: another digest is another file.
        suffix
            The format's file suffix (".csv", ...).
        write
            ``write(handle)`` writes the export to a binary file handle.
        still_wanted
            Whether the evaluation still exists, asked before a made export is put in place.

        Raises
        ------
        ExportBudgetExceeded
            The export does not fit in the budget, even with every other export removed that can be.
        NotFound
            The evaluation went while its export was made (``still_wanted`` said no).
        StorageUnavailable
            The blob folder cannot be written.
        """
        final = self.folder / export_name(evaluation_id, flight_id, digest, suffix)
        served = self._open_kept(final)
        if served is not None:
            return served
        with _flock(self.folder / f".{final.name}.lock", fcntl.LOCK_EX):   # one maker per export
            with _flock(self._lock_path, fcntl.LOCK_SH):                   # `forget_exports` waits for it
                served = self._open_kept(final)   # made by the request this one waited for
                if served is not None:
                    return served
                self._make(final, write, still_wanted)
                for old in self.folder.glob(f"{_prefix(evaluation_id, flight_id)}*{suffix}"):
                    if old != final:   # made from estimates since replaced
                        old.unlink(missing_ok=True)
                return open(final, "rb")

    def usage(self) -> int:
        """Bytes the exports take now: those kept and those being written."""
        kept = [p for p in self.folder.iterdir() if not p.name.startswith(".")]
        parts = [p for p in self.blobs.tmp.iterdir() if p.name.endswith(PART_SUFFIX)]
        return sum(_size(p) for p in kept + parts)

    # -- making one ---------------------------------------------------------------------------------------
    def _open_kept(self, final: Path) -> BinaryIO | None:
        try:
            handle = open(final, "rb")
        except FileNotFoundError:
            return None
        try:
            os.utime(final)   # served now: the last to go when room is made
        except OSError:
            pass
        return handle

    def _make(self, final: Path, write: Callable[[IO[bytes]], object], still_wanted: Callable[[], bool]) -> None:
        with storage_errors("write the export"):
            fd, name = tempfile.mkstemp(dir=self.blobs.tmp, prefix=temp_prefix(), suffix=PART_SUFFIX)
        part = Path(name)
        try:
            with os.fdopen(fd, "wb") as handle:
                budgeted = io.BufferedWriter(_BudgetedFile(handle, lambda size: self._room_for(size, part, final)),
                                             CHUNK)
                write(budgeted)
                if not budgeted.closed:
                    budgeted.flush()
                with storage_errors("write the export"):
                    handle.flush()
                    os.fsync(handle.fileno())
            if not still_wanted():
                raise NotFound("the evaluation was deleted while its export was made")
            with storage_errors("write the export"):
                os.replace(part, final)
                _fsync_dir(final.parent)
        finally:
            part.unlink(missing_ok=True)

    def _room_for(self, size: int, part: Path, final: Path) -> None:
        """Make room for ``size`` bytes of the export being written to ``part`` (removing the least recently
        served others), or refuse it."""
        def fits() -> bool:
            return self.usage() - _size(part) + size <= self.budget_bytes

        if fits():
            return
        kept = sorted((p for p in self.folder.iterdir() if not p.name.startswith(".")), key=_mtime)
        # larger than the whole budget: refused as it is, without removing exports it could never make room with
        for path in [] if size > self.budget_bytes else kept:
            path.unlink(missing_ok=True)
            log.info("export %s removed to make room for %s (LEARNEST_EXPORT_BUDGET_MB)", path.name, final.name)
            if fits():
                return
        mb = self.budget_bytes / 1024 / 1024
        raise ExportBudgetExceeded(f"this export does not fit in the disk budget of estimate exports ({mb:g} MB, "
                                   "LEARNEST_EXPORT_BUDGET_MB, with the exports being written now): try again "
                                   "later, choose one flight, or ask the server's operator to raise it")



@contextmanager
def _flock(path: Path, mode: int) -> Iterator[None]:
    with storage_errors("keep the export"):
        handle = open(path, "ab")
    with handle:
        fcntl.flock(handle, mode)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


class _BudgetedFile(io.RawIOBase):
    """A binary file that asks for room (``room(bytes written with this write)``) as it grows.  Closing it leaves the
    underlying handle open (its owner fsyncs it): writers that close what they were given may."""

    def __init__(self, handle: IO[bytes], room: Callable[[int], None]) -> None:
        super().__init__()
        self._handle, self._room, self._written = handle, room, 0
        self._checked = 0   # bytes the budget was last checked for: checked again every CHUNK

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        size = len(memoryview(data).cast("B"))
        if self._written + size > self._checked:
            self._room(self._written + size)
            self._checked = self._written + size + CHUNK
        with storage_errors("write the export"):
            self._handle.write(data)
        self._written += size
        return size

    def tell(self) -> int:
        return self._written


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return time.time()
