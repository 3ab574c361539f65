"""Where the heavy work (training, per-flight evaluation) runs: one small interface, three back ends.

- `LocalPoolExecutor`: a concurrent.futures ProcessPoolExecutor (spawned processes: forking a server
  with running threads and torch/CasADi state is unsafe).  The default.
- `DaskExecutor`: a dask.distributed Client, to a scheduler at tcp://host:port or to an in-process
  LocalCluster (tests, laptops).
- `InlineExecutor`: in the calling process, one task at a time (the CLI's evaluations).

Tasks are plain module-level functions taking and returning bytes/JSON-able values (flight and model
bytes travel with the task), so remote Dask workers need no access to the blob folder.

Stopping a cancelled job's tasks (`Executor.stop`): pending tasks are cancelled; running ones get a grace
period to stop themselves (training checks its job's state between epochs), then the local pool kills its
worker processes and starts new ones (a ProcessPoolExecutor cannot kill one task: the tasks of other jobs
running in the pool at that moment fail with BrokenProcessPool), and Dask cancels them with force=True.
"""
from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures.process import BrokenProcessPool
from typing import Any

PARENT_CHECK_S = 0.5  # how often a pool worker checks that the server that started it is alive
EXIT_GRACE_S = 5.0    # at shutdown, how long idle pool workers get to exit by themselves before being killed


def init_worker(parent_pid: int | None = None) -> None:
    """Set up a worker process (or the CLI's own process, with no parent to watch).

    The networks are tiny: one torch thread per worker avoids oversubscribing the cores.  With
    ``parent_pid``, a daemon thread ends the worker as soon as that process is gone: a server killed with
    ``kill -9`` cannot shut its pool down, and its workers would otherwise keep computing, then block
    forever on their pipe holding memory and the database's files.  (Linux's PR_SET_PDEATHSIG is not used:
    it fires when the parent *thread* that spawned the worker ends, which for a pool is any request thread.)
    """
    import torch

    torch.set_num_threads(1)
    if parent_pid is not None:
        watch_parent(parent_pid)


def watch_parent(parent_pid: int) -> None:
    """In a worker process: ignore Ctrl-C, and end as soon as process ``parent_pid`` is gone (see
    `init_worker`).  The upload decoders' initializer (they need no torch)."""
    # Ctrl-C reaches the whole process group: the server (or CLI) decides which work ends, and stops its
    # workers itself; a worker interrupted mid-task would only hand its job a KeyboardInterrupt
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), name="parent-watch", daemon=True).start()


def _exit_with_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_CHECK_S)
    os._exit(1)  # re-parented: the server is gone; nothing of this process's work can be delivered


class Executor(ABC):
    """Where jobs' heavy tasks run: submit module-level functions, collect their futures."""

    name = "executor"

    @abstractmethod
    def submit(self, fn: Callable, *args: Any) -> Any:
        """Schedule fn(*args); returns a future with .result()."""

    @abstractmethod
    def as_completed(self, futures: Iterable) -> Iterator:
        """Yield the futures as they finish."""

    @abstractmethod
    def shutdown(self) -> None:
        """Stop the back end (running tasks are abandoned)."""

    @abstractmethod
    def stop(self, futures: Iterable, grace_s: float) -> None:
        """Stop these tasks (a cancelled job's): pending ones never start, running ones get ``grace_s``
        seconds to end by themselves and are then killed."""

    def describe(self) -> dict:
        """What the status page shows about this executor."""
        return {"name": self.name}


class _DeferredFuture(concurrent.futures.Future):
    """A future whose function runs, in the asking thread, when it is first asked whether it is done."""

    def __init__(self, fn: Callable, args: tuple) -> None:
        super().__init__()
        self._call: tuple[Callable, tuple] | None = (fn, args)

    def _run_once(self) -> None:
        if self._call is None or not self.set_running_or_notify_cancel():
            return
        fn, args = self._call
        self._call = None
        try:
            self.set_result(fn(*args))
        except Exception as err:  # kept for .result(), as a pool's future does
            self.set_exception(err)

    def done(self) -> bool:
        self._run_once()
        return super().done()

    def result(self, timeout: float | None = None) -> Any:
        self._run_once()
        return super().result(timeout)


class InlineExecutor(Executor):
    """Runs each task in the calling process, one at a time, when its result is first waited for: what the
    CLI uses (its user waits anyway, torch is already loaded, and a spawned worker would cost seconds of
    imports).  A job's progress still advances task by task."""

    name = "inline"

    def submit(self, fn: Callable, *args: Any) -> concurrent.futures.Future:
        """A future that runs fn(*args) when first asked whether it is done (or for its result)."""
        return _DeferredFuture(fn, args)

    def as_completed(self, futures: Iterable) -> Iterator:
        """Run the tasks in order, yielding each when done."""
        for future in list(futures):
            future.done()
            yield future

    def shutdown(self) -> None:
        """Nothing runs in the background."""

    def stop(self, futures: Iterable, grace_s: float) -> None:
        """Tasks not yet started never start (one running is this thread: it has already returned)."""
        for future in futures:
            future.cancel()


class LocalPoolExecutor(Executor):
    """A ProcessPoolExecutor of ``max_workers`` spawned processes, one torch thread each; replaced by a
    new pool when a worker dies."""

    name = "local-pool"

    def __init__(self, max_workers: int = 2) -> None:
        self.max_workers = max_workers
        self._lock = threading.Lock()
        self._pool = self._new_pool()

    def _new_pool(self):
        return concurrent.futures.ProcessPoolExecutor(
            max_workers=self.max_workers, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker,
            initargs=(os.getpid(),))

    def submit(self, fn: Callable, *args: Any) -> concurrent.futures.Future:
        """Schedule fn(*args) on the pool (a broken pool is replaced first)."""
        with self._lock:
            try:
                return self._pool.submit(fn, *args)
            except BrokenProcessPool:  # a worker died (killed, out of memory): the jobs after it get a new pool
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = self._new_pool()
                return self._pool.submit(fn, *args)

    def as_completed(self, futures: Iterable) -> Iterator:
        """concurrent.futures.as_completed over ``futures``."""
        return concurrent.futures.as_completed(list(futures))

    def shutdown(self) -> None:
        """Cancel pending tasks, let idle workers exit by themselves (`EXIT_GRACE_S`), terminate the rest."""
        # the jobs still running are already marked failed: their processes are not waited for; an idle
        # worker that exits by itself releases its semaphores (a terminated one leaves them to the resource
        # tracker, which warns about "leaked semaphore objects" at the server's exit)
        self._terminate(self._pool, grace_s=EXIT_GRACE_S)

    def stop(self, futures: Iterable, grace_s: float) -> None:
        """Cancel the pending futures; if one still runs after ``grace_s`` s, kill the pool's workers and
        start a new pool (the module docstring says what that costs other jobs)."""
        running = [f for f in futures if not f.cancel()]
        deadline = time.monotonic() + grace_s
        while any(not f.done() for f in running) and time.monotonic() < deadline:
            time.sleep(0.05)
        if any(not f.done() for f in running):
            with self._lock:
                old, self._pool = self._pool, self._new_pool()
            self._terminate(old)

    @staticmethod
    def _terminate(pool, grace_s: float = 0.0) -> None:
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)   # idle workers get their "exit" message
        deadline = time.monotonic() + grace_s
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.terminate()

    def describe(self) -> dict:
        """``name`` and ``workers``."""
        return {"name": self.name, "workers": self.max_workers}


class DaskExecutor(Executor):
    """A dask.distributed Client: to the scheduler at ``address``, or without one to a LocalCluster
    (default: one in-process worker thread; ``cluster_options`` override LocalCluster's arguments)."""

    name = "dask"

    def __init__(self, address: str | None = None, **cluster_options: Any) -> None:
        from dask.distributed import Client, LocalCluster

        self.address = address
        self._cluster = None
        if address:
            self._client = Client(address)
        else:
            options = {"n_workers": 1, "threads_per_worker": 1, "processes": False,
                       "dashboard_address": None, **cluster_options}
            self._cluster = LocalCluster(**options)
            self._client = Client(self._cluster)

    def submit(self, fn: Callable, *args: Any) -> Any:
        """Client.submit with pure=False (two runs of a job are never merged); returns a Dask future."""
        return self._client.submit(fn, *args, pure=False)  # pure=False: never merge two runs of a job

    def as_completed(self, futures: Iterable) -> Iterator:
        """dask.distributed.as_completed over ``futures``."""
        from dask.distributed import as_completed

        return iter(as_completed(list(futures)))

    def shutdown(self) -> None:
        """Close the client, and the LocalCluster if this executor started one."""
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()

    def stop(self, futures: Iterable, grace_s: float) -> None:
        """Give running tasks ``grace_s`` s to end, then Client.cancel(force=True) (a worker thread cannot
        be killed: Dask drops its result; tasks that check their job's state end by themselves)."""
        futures = list(futures)
        deadline = time.monotonic() + grace_s
        while any(not f.done() for f in futures) and time.monotonic() < deadline:
            time.sleep(0.05)
        self._client.cancel([f for f in futures if not f.done()], force=True)

    def describe(self) -> dict:
        """``name`` and the ``scheduler`` address."""
        return {"name": self.name, "scheduler": self._client.scheduler.address}


def make_executor(dask_address: str | None, pool_workers: int) -> Executor:
    """`dask_address`: None -> local process pool; "local" -> a Dask LocalCluster of worker processes on
    this machine; anything else -> the Dask scheduler at that address (tcp://host:port)."""
    if not dask_address:
        return LocalPoolExecutor(pool_workers)
    if dask_address == "local":
        return DaskExecutor(None, processes=True, n_workers=pool_workers)
    return DaskExecutor(dask_address)
