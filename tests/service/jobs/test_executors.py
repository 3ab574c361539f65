"""The job executors: pool workers must not outlive the server that started them."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

SERVER = """
import time
from learnest.service.jobs.executors import LocalPoolExecutor
pool = LocalPoolExecutor(max_workers=1)
pool.submit(time.sleep, 600)                  # a long job: the worker is busy when the server dies
while not pool._pool._processes:
    time.sleep(0.05)
print(*pool._pool._processes, flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    status = Path(f"/proc/{pid}/status")
    try:
        return "State:\tZ" not in status.read_text()  # a zombie has exited; only its entry is left
    except FileNotFoundError:
        return False


def test_pool_workers_exit_when_the_server_is_killed():
    server = subprocess.Popen([sys.executable, "-c", SERVER], stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(pid) for pid in server.stdout.readline().split()]
        assert workers and all(_alive(pid) for pid in workers)
        os.kill(server.pid, signal.SIGKILL)      # no shutdown, no atexit: what a crash or OOM kill does
        server.wait()
        deadline = time.monotonic() + 120        # the worker first finishes importing torch, then checks
        while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_alive(pid) for pid in workers), f"orphaned workers still running: {workers}"
    finally:
        server.kill()


def test_a_task_that_does_not_stop_is_killed_after_the_grace_period_and_the_pool_recovers():
    from concurrent.futures.process import BrokenProcessPool

    import pytest

    from learnest.service.jobs.executors import LocalPoolExecutor

    pool = LocalPoolExecutor(max_workers=1)
    try:
        stuck = pool.submit(time.sleep, 600)            # a task that never looks at its job's state
        queued = pool.submit(time.sleep, 600)
        while not pool._pool._processes:
            time.sleep(0.05)
        worker = next(iter(pool._pool._processes))
        while not stuck.running():
            time.sleep(0.05)
        started = time.monotonic()
        pool.stop([stuck, queued], grace_s=0.5)
        assert time.monotonic() - started < 10
        assert queued.done()    # cancelled, or (already handed to the worker) failed with the pool
        with pytest.raises(BrokenProcessPool):
            stuck.result(timeout=30)
        deadline = time.monotonic() + 30
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(worker)
        assert pool.submit(sum, [1, 2, 3]).result(timeout=120) == 6   # a new pool serves the next job
    finally:
        pool.shutdown()
