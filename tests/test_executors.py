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
