"""Uploads are decoded in worker processes of their own, bounded in number, waiting room and
time.

Decoding a log is CPU work in pure Python and NumPy; in the request threads it holds the GIL, and a burst of
concurrent uploads (small decompression bombs) stalls every page and ``/health`` for seconds (the results page
`docs/results/service.md`).  Here:

- at most ``LEARNEST_DECODE_WORKERS`` uploads decode at once, each in its own spawned process (the
  server's threads keep the GIL: pages and /health answer while uploads are decoded);
- at most ``LEARNEST_DECODE_QUEUE`` more wait for a worker; an upload beyond that is refused at once
  (503, `DecodeBusy`) instead of holding a request thread;
- a decode that takes longer than ``LEARNEST_DECODE_TIMEOUT_S`` is refused (422 naming the limit) and its
  worker process is killed and replaced.  Nothing of a refused upload is stored: the flight row and its
  blobs are written only after the decode succeeded.

The upload still answers when the flight is stored (synchronous): the client learns in one request
whether its file was read, which id it got, or why it was refused.
"""
from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool

from learnest.errors import InvalidInput, LearnestError
from learnest.ingest.flight import Flight as CanonicalFlight

from .executors import EXIT_GRACE_S, watch_parent
from .reading import StagedFile, read_uploaded_flight


def init_decoder(parent_pid: int, warm: bool = True) -> None:
    """A decoder process: ends with the server (`watch_parent`), and (``warm``) imports the readers and what
    they use (pandas, SciPy: seconds) now, while it is idle, rather than on its first upload."""
    watch_parent(parent_pid)
    if warm:
        from learnest.ingest import detect  # noqa: F401  - the formats' readers
        from learnest.ingest.baseline import sg_references  # noqa: F401  - SciPy's filters


STARTUP_LIMIT_S = 120.0   # a decoder process that has not started by then is a broken server, not a bad file


def _ready() -> bool:
    return True


class DecodeBusy(LearnestError):
    """Every decode worker is busy and the waiting room is full: HTTP 503, retry later."""

    status = 503
    headers = {"Retry-After": "5"}


class DecodePool:
    """Decode uploads in ``workers`` spawned processes (one single-worker process pool per slot, so one
    overrunning decode can be killed without touching the others).

    Parameters
    ----------
    workers : int
        Uploads decoded at once.
    waiting : int
        Uploads that may wait for a free worker; more are refused with `DecodeBusy`.
    timeout_s : float
        Seconds one upload's decode may take (from when a worker starts on it), s.
    read : callable
        What runs in the worker: ``read(staged, pose_topic, imu_topic[, cut=...])`` -> flight, a module-level function
        (default `read_uploaded_flight`; tests pass slow ones).
    """

    def __init__(self, workers: int, waiting: int, timeout_s: float,
                 read: Callable[..., CanonicalFlight] = read_uploaded_flight) -> None:
        self.workers, self.waiting, self.timeout_s, self.read = workers, waiting, timeout_s, read
        self._admitted = threading.BoundedSemaphore(workers + waiting)
        self._slots: queue.Queue[concurrent.futures.ProcessPoolExecutor | None] = queue.Queue()
        for _ in range(workers):
            self._slots.put(None)   # a slot's process is started by `start` or on first use
        self._all: set[concurrent.futures.ProcessPoolExecutor] = set()
        self._started: dict[concurrent.futures.ProcessPoolExecutor, concurrent.futures.Future] = {}
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start every worker process now (in the background: this returns at once), so the first uploads
        do not wait for a process to start and import the readers."""
        for _ in range(self.workers):
            try:
                pool = self._slots.get_nowait()
            except queue.Empty:   # the other slots are decoding: started already
                return
            self._slots.put(pool or self._new_pool())

    def wait_started(self) -> None:
        """Block until every worker process has started (after `start`)."""
        for future in list(self._started.values()):
            future.result(timeout=STARTUP_LIMIT_S)

    def decode(self, staged: list[StagedFile], pose_topic: str | None = None,
               imu_topic: str | None = None, cut: str | None = None) -> CanonicalFlight:
        """`read_uploaded_flight` in a worker process.

        Raises
        ------
        DecodeBusy
            (503) ``workers + waiting`` uploads are being decoded or waiting already.
        InvalidInput
            (422) The file cannot be read (the worker's message), or its decode passed ``timeout_s``.
        """
        if not self._admitted.acquire(blocking=False):
            raise DecodeBusy(f"the server is decoding {self.workers} uploads and {self.waiting} more are waiting "
                             "(LEARNEST_DECODE_WORKERS, LEARNEST_DECODE_QUEUE): retry in a few seconds")
        try:
            pool = self._slots.get()
            try:
                pool = pool or self._new_pool()
                self._started[pool].result(timeout=STARTUP_LIMIT_S)
                chosen = {"cut": cut} if cut not in (None, "auto") else {}   # a read without a cut keeps working
                future = pool.submit(self.read, staged, pose_topic, imu_topic, **chosen)
                try:
                    return future.result(timeout=self.timeout_s)
                except concurrent.futures.TimeoutError:
                    self._kill(pool)
                    pool = self._new_pool()   # the next upload finds a warm process
                    names = ", ".join(f.original_name for f in staged)
                    raise InvalidInput(f"{names}: decoding took longer than the {self.timeout_s:g} s limit "
                                       "(LEARNEST_DECODE_TIMEOUT_S); nothing was stored") from None
                except BrokenProcessPool:   # the worker died: out of memory, or killed
                    self._kill(pool)
                    pool = self._new_pool()
                    names = ", ".join(f.original_name for f in staged)
                    raise InvalidInput(f"{names}: the decoder's worker process died (out of memory?); nothing "
                                       "was stored") from None
            finally:
                self._slots.put(pool)
        finally:
            self._admitted.release()

    def _new_pool(self) -> concurrent.futures.ProcessPoolExecutor:
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                      initializer=init_decoder,
                                                      initargs=(os.getpid(), self.read is read_uploaded_flight))
        # starts the process now (a pool starts its processes on the first task); a decode waits for it first, so
        # its time limit does not count the start of a replacement process
        self._started[pool] = pool.submit(_ready)
        with self._lock:
            self._all.add(pool)
        return pool

    def _kill(self, pool: concurrent.futures.ProcessPoolExecutor, grace_s: float = 0.0) -> None:
        with self._lock:
            self._all.discard(pool)
        self._started.pop(pool, None)
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)   # an idle worker gets its "exit" message
        deadline = time.monotonic() + grace_s
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()

    def shutdown(self) -> None:
        """Let idle worker processes exit by themselves (`EXIT_GRACE_S`: a killed one leaves its semaphores to
        the resource tracker, which warns at the server's exit), kill the rest (a decode in progress is
        abandoned: its request gets an error)."""
        with self._lock:
            pools = list(self._all)
        for pool in pools:
            self._kill(pool, grace_s=EXIT_GRACE_S)
