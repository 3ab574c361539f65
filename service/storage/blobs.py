"""Content-addressed blob folder: root/ab/cdef... named by the sha256 of the bytes.

Writes go to a temp file in root/.tmp (same file system), are fsync'ed, then atomically renamed into place
and the directory is fsync'ed: a blob is either complete or absent.  Callers write blobs *before* they
commit the row that names them, so a crash can leave an unreferenced blob (harmless; `collect` removes it)
but never a row pointing to a missing one.

Deleting is the only way to break that order (a blob could be unlinked between an uploader finding it
already present and its row commit), so writers hold a shared lock (`writing()`) from their first blob to
their commit and `collect` takes the exclusive lock.  The lock is fcntl.flock on root/.lock: it works
across threads and processes (several uvicorn workers) of one machine.

A blob folder that cannot be written (full, read-only) is a `StorageUnavailable` (HTTP 507) that names the
problem but not the server's folders; whatever the failed write had put in place is removed again.

Temp entries are named "<host>-<pid>-..." after the process writing them: when the store is opened, those of
processes of this host that no longer run (a crashed upload) are removed, and any entry older than an hour.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import logging
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from learnest.errors import LearnestError
from learnest.ingest.flight import sha256_file

log = logging.getLogger("learnest.storage")

SHA256 = re.compile(r"^[0-9a-f]{64}$")
CHUNK = 1 << 20
STALE_TEMP_S = 3600.0   # temp entries this old go whoever wrote them


class StorageUnavailable(LearnestError):
    """The blob folder cannot be written (no space left, read-only, ...): HTTP 507 Insufficient Storage."""

    status = 507


@contextmanager
def storage_errors(what: str = "store the files") -> Iterator[None]:
    """Turn an OSError while writing to the blob folder into `StorageUnavailable`: the reason, not the path."""
    try:
        yield
    except OSError as err:
        reason = err.strerror or errno.errorcode.get(err.errno or 0) or type(err).__name__
        log.error("blob folder write failed: %s", err)
        raise StorageUnavailable(f"the server cannot {what} right now: its storage says {reason!r}; "
                                 "nothing was stored (tell the server's operator)") from None


def temp_prefix() -> str:
    """"<host>-<pid>-": names this process as the writer of a temp entry."""
    return f"{socket.gethostname()}-{os.getpid()}-"


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 digest of ``data``."""
    return hashlib.sha256(data).hexdigest()


class BlobStore:
    """A content-addressed blob folder (module docstring): blobs named by the sha256 of their bytes.

    Creating one makes ``root/.tmp`` and ``root/.lock`` if needed and removes the temp entries of processes
    that no longer run and those older than an hour (module docstring).

    Parameters
    ----------
    root : Path
        The folder (LEARNEST_HOME/blobs in the service).
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.tmp = self.root / ".tmp"
        self.tmp.mkdir(parents=True, exist_ok=True)
        self._lock_path = self.root / ".lock"
        self._lock_path.touch(exist_ok=True)
        self._remove_stale_temp_files()

    def _remove_stale_temp_files(self, older_than_s: float = STALE_TEMP_S) -> list[str]:
        """Left by a crash mid-upload: those of dead writers of this host, and old ones (another process may
        be uploading right now).  Returns the names removed."""
        cutoff, removed = time.time() - older_than_s, []
        for path in self.tmp.iterdir():
            try:
                if _writer_is_gone(path.name) or path.lstat().st_mtime < cutoff:
                    shutil.rmtree(path) if path.is_dir() else path.unlink()
                    removed.append(path.name)
            except OSError:
                pass
        if removed:
            log.warning("removed %d temp entr(ies) left in %s by interrupted uploads", len(removed), self.tmp.name)
        return removed

    # -- addressing -------------------------------------------------------------------------------------
    def path(self, sha: str) -> Path:
        """Where blob ``sha`` lives (root/ab/cdef...); ValueError if ``sha`` is not 64 lower-case hex digits."""
        if not SHA256.fullmatch(sha or ""):  # never let anything else become a path
            raise ValueError(f"not a sha256: {sha!r}")
        return self.root / sha[:2] / sha[2:]

    def exists(self, sha: str) -> bool:
        """Whether blob ``sha`` is stored."""
        return self.path(sha).is_file()

    def read_bytes(self, sha: str) -> bytes:
        """The bytes of blob ``sha`` (FileNotFoundError if absent)."""
        return self.path(sha).read_bytes()

    # -- writing ----------------------------------------------------------------------------------------
    @contextmanager
    def temp_dir(self) -> Iterator[Path]:
        """A private scratch folder on the blob file system (so `put_file` can rename or link, not copy), named
        after this process; `StorageUnavailable` if it cannot be made."""
        with storage_errors("accept uploads"):
            scratch = tempfile.TemporaryDirectory(dir=self.tmp, prefix=temp_prefix(), ignore_cleanup_errors=True)
        with scratch as directory:
            yield Path(directory)

    def put_bytes(self, data: bytes) -> str:
        """Store ``data`` atomically; returns its sha256 (an existing blob with that content is kept).
        `StorageUnavailable` when the folder cannot take it (the temp file is removed)."""
        with storage_errors():
            fd, name = tempfile.mkstemp(dir=self.tmp, prefix=temp_prefix())
            try:
                with os.fdopen(fd, "wb") as handle:
                    handle.write(data)
            except OSError:
                Path(name).unlink(missing_ok=True)
                raise
        return self.put_file(Path(name), sha256_bytes(data))

    def put_file(self, source: Path, sha: str | None = None, *, keep: bool = False) -> str:
        """Move `source` (on this file system) into the store; returns its sha256.

        ``sha`` is trusted when given (computed from the file otherwise).  ``source`` is consumed: renamed into
        place, or deleted when that content is already stored (or when storing fails: `StorageUnavailable`).
        With ``keep``, ``source`` stays where it is and the blob is a hard link to it (a copy where the file
        system cannot link): a caller that may have to store it again - an upload retried under another name
        after its first attempt's blobs were collected - still holds the file.
        """
        with storage_errors():
            try:
                sha = sha or sha256_file(source)
                with open(source, "rb") as handle:
                    os.fsync(handle.fileno())
                target = self.path(sha)
                target.parent.mkdir(exist_ok=True)
                if target.exists():  # same content already stored: keep the existing file
                    if not keep:
                        source.unlink()
                elif keep:
                    self._link_into_place(source, target)
                else:
                    os.replace(source, target)
                    _fsync_dir(target.parent)
            except OSError:
                if not keep:
                    source.unlink(missing_ok=True)
                raise
        return sha

    def _link_into_place(self, source: Path, target: Path) -> None:
        """``target`` becomes ``source``'s content atomically, ``source`` stays: a hard link, else a copy."""
        try:
            os.link(source, target)
        except FileExistsError:   # the same content, stored meanwhile by another writer
            return
        except OSError as err:
            if err.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP):
                raise
            fd, name = tempfile.mkstemp(dir=self.tmp, prefix=temp_prefix())
            os.close(fd)
            try:
                shutil.copyfile(source, name)
                with open(name, "rb") as handle:
                    os.fsync(handle.fileno())
                os.replace(name, target)
            finally:
                Path(name).unlink(missing_ok=True)
        _fsync_dir(target.parent)

    @contextmanager
    def writing(self) -> Iterator[None]:
        """Shared lock: held from the first blob written until the row naming it is committed."""
        with self._flock(fcntl.LOCK_SH):
            yield

    # -- deleting ---------------------------------------------------------------------------------------
    def collect(self, candidates: Iterable[str], is_referenced: Callable[[str], bool]) -> list[str]:
        """Delete the candidate blobs no row references (checked under the exclusive lock).  A blob that
        cannot be deleted (read-only folder) is logged and left: an orphan is harmless, and the next
        collect (the server's start-up sweep) removes it."""
        removed = []
        with self._flock(fcntl.LOCK_EX):
            for sha in set(candidates):
                path = self.path(sha)
                if path.exists() and not is_referenced(sha):
                    try:
                        path.unlink()
                    except OSError as err:
                        log.warning("blob %s not removed (%s); the next sweep retries", sha[:12], err.strerror)
                        continue
                    removed.append(sha)
        return removed

    def all_blobs(self) -> Iterator[str]:
        """Every stored sha; `collect(all_blobs(), is_referenced)` removes the orphans a crash between a
        blob write and its row commit can leave (safe while the server runs: see `writing`)."""
        for path in self.root.glob("??/*"):
            if path.is_file() and SHA256.fullmatch(path.parent.name + path.name):
                yield path.parent.name + path.name

    @contextmanager
    def _flock(self, mode: int):
        with open(self._lock_path, "rb") as handle:
            fcntl.flock(handle, mode)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)


def _writer_is_gone(name: str) -> bool:
    """A temp entry named by `temp_prefix` whose process, on this host, no longer runs."""
    host, pid, rest = (["", "", ""] + name.rsplit("-", 2))[-3:]  # the host name may hold "-"; the rest cannot
    if host != socket.gethostname() or not pid.isdigit() or not rest:
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, someone else's
        return False
    return False


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
