"""How fast a newcomer gets a first answer: a usage error, the server's /health and /, the first /manual page,
the demo's first line and the test suite's first line.

Each is timed from the moment the command starts (wall clock, this machine as it is: the load average is
recorded with the numbers). Targets: /health and / under 2 s after `learnest serve` starts, the usage error
under 1 s, the first /manual answer under 2 s, the suite's first line within 10 s, the demo's within 1 s.

    python benchmarks/first_answers.py [--runs 5] [--out benchmarks/results/first_answers]

Writes ``OUT.json`` and ``OUT.md``. Every server, demo and test run gets a fresh LEARNEST_HOME in a temporary
folder, so the manual is built from nothing, as on a first start.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from served import free_port  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
LEARNEST = str(BIN / "learnest")


def usage_error_s() -> float:
    """`learnest evaluate` (no --model): its usage error, s."""
    start = time.perf_counter()
    run = subprocess.run([LEARNEST, "evaluate"], capture_output=True, text=True, cwd=REPO)
    elapsed = time.perf_counter() - start
    assert run.returncode == 2 and "needs --model" in run.stderr, run.stderr
    return elapsed


def _get(client: httpx.Client, path: str) -> httpx.Response | None:
    try:
        return client.get(path)
    except httpx.TransportError:
        return None


def serve_times(home: Path, manual_wait_s: float = 300.0) -> dict:
    """Start `learnest serve` on a fresh home and time its first answers, s from the start of the command."""
    port = free_port()
    log = open(home.parent / "serve.log", "wb")   # noqa: SIM115 - closed below
    env = {**os.environ, "LEARNEST_HOME": str(home)}
    start = time.perf_counter()
    server = subprocess.Popen([LEARNEST, "serve", "--port", str(port)], cwd=REPO, env=env, stdout=log,
                              stderr=subprocess.STDOUT, start_new_session=True)
    out: dict = {}
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as client:
            while (health := _get(client, "/health")) is None:
                assert server.poll() is None, "learnest serve exited"
                time.sleep(0.02)
            out["health_first_s"] = time.perf_counter() - start
            out["health_first_status"] = health.status_code
            home_page = client.get("/")
            out["home_first_s"] = time.perf_counter() - start
            out["home_first_status"] = home_page.status_code
            asked = time.perf_counter()
            manual = client.get("/manual/index.html")   # waits for the service, not for the manual's build
            out["manual_first_s"] = time.perf_counter() - start
            out["manual_first_request_s"] = time.perf_counter() - asked
            out["manual_first_text"] = manual.text[manual.text.find("<h1>") + 4:manual.text.find("</h1>")]
            out["manual_first_status"] = manual.status_code
            while client.get("/health").status_code != 200:
                time.sleep(0.05)
            out["health_ok_s"] = time.perf_counter() - start
            deadline = time.perf_counter() + manual_wait_s
            while manual.status_code != 200 and time.perf_counter() < deadline:
                time.sleep(0.5)
                manual = client.get("/manual/index.html")
            out["manual_ok_s"] = time.perf_counter() - start if manual.status_code == 200 else None
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(60)
        log.close()
    return out


def first_line_s(command: list[str], env: dict) -> tuple[float, str]:
    """Run ``command`` until it prints its first line; the time to that line, s, and the line."""
    start = time.perf_counter()
    process = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               text=True, start_new_session=True)
    try:
        line = process.stdout.readline()
        return time.perf_counter() - start, line.rstrip("\n")
    finally:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="usage-error runs (the median is reported)")
    parser.add_argument("--out", default="benchmarks/results/first_answers", help="results path without suffix")
    args = parser.parse_args()
    result: dict = {"load_before": os.getloadavg(), "cores": os.cpu_count()}
    usage = [usage_error_s() for _ in range(args.runs)]
    result["usage_error_s"] = {"median": statistics.median(usage), "max": max(usage), "runs": usage}
    with tempfile.TemporaryDirectory() as scratch:
        result["serve"] = serve_times(Path(scratch) / "home")
    with tempfile.TemporaryDirectory() as scratch:
        env = {**os.environ, "LEARNEST_HOME": str(Path(scratch) / "home")}
        result["demo_first_line_s"], result["demo_first_line"] = first_line_s([LEARNEST, "demo", "sample_logs"], env)
        result["suite_first_line_s"], result["suite_first_line"] = first_line_s(
            [str(BIN / "pytest"), "-q", "-p", "no:cacheprovider"], env)
    result["load_after"] = os.getloadavg()
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(report(result))
    print(report(result))


def report(r: dict) -> str:
    s = r["serve"]
    manual_ok = "not within the wait" if s["manual_ok_s"] is None else f"{s['manual_ok_s']:.1f} s"
    rows = [
        ("`learnest evaluate` (no --model): the usage error", f"{r['usage_error_s']['median']:.2f} s "
         f"(median of {len(r['usage_error_s']['runs'])}, max {r['usage_error_s']['max']:.2f})", "< 1 s"),
        ("`learnest serve`: first /health answer", f"{s['health_first_s']:.2f} s ({s['health_first_status']})",
         "< 2 s"),
        ("`learnest serve`: first / answer", f"{s['home_first_s']:.2f} s ({s['home_first_status']})", "< 2 s"),
        ("`learnest serve`: /health 200 (the service up)", f"{s['health_ok_s']:.1f} s", "-"),
        ("`learnest serve`: first /manual/index.html answer, asked right after the first /health",
         f"{s['manual_first_s']:.1f} s ({s['manual_first_status']}: {s['manual_first_text']})", "< 2 s"),
        ("`learnest serve`: the manual built and served (200)", manual_ok, "-"),
        ("`learnest demo sample_logs`: first line", f"{r['demo_first_line_s']:.2f} s", "< 1 s"),
        ("`pytest -q`: first line", f"{r['suite_first_line_s']:.1f} s", "< 10 s"),
    ]
    lines = ["# First answers", "",
             f"`python benchmarks/first_answers.py`, {r['cores']} cores, load average "
             f"{r['load_before'][0]:.1f} before and {r['load_after'][0]:.1f} after (other work shared the cores). "
             "Times from the start of each command, fresh LEARNEST_HOME.", "",
             "| what | measured | target |", "|---|---|---|"]
    lines += [f"| {what} | {measured} | {target} |" for what, measured, target in rows]
    lines += ["", f"The demo's first line: `{r['demo_first_line']}`", "",
              f"The suite's first line: `{r['suite_first_line']}`", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
