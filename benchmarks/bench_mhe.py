"""MHE speed: the Gauss–Newton solver (default) against today's warm-started IPOPT, side by side.

One process, one core (BLAS and torch limited to one thread), each case run alternately GN / IPOPT
`--repeats` times; medians and their ratio.  Equality: max |GN - IPOPT| over every state and step.
Cases (N = 20, arrival "ekf"):
- quadrotor prior MHE and KNODE-MHE on a real NanoBench flight (KNODE trained on another flight with the
  Crazyflie settings of benchmarks/bench_ingest.py);
- cartpole and robot MHE (prior models, Table I's "MHE" rows) on simulated runs;
- the real-time iteration (one Gauss–Newton step per window) of the KNODE-MHE: speed and its error
  against the converged estimate;
- the compiled UKF (prior and KNODE) per step on the same steps, medians of `--repeats` runs;
- end to end on the 40-s flight: load the CSV, references, UKF, KNODE-UKF, MHE, KNODE-MHE (compiled
  functions cached, as after the first evaluation of a model); the first use of a model is reported
  apart, (a) compiling into an empty cache and (b) into a cache that holds another model of the same
  architecture (trained on B2_circle_slow_rep2), with the number of libraries each leaves in the cache.

Run:  .venv/bin/python benchmarks/bench_mhe.py [--baseline old.json]   (writes benchmarks/results/mhe_speed.{json,md});
``--baseline`` puts the per-step numbers of an earlier run's json (another checkout) side by side.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core: before numpy loads its BLAS
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from bench_core import timed_side_by_side  # noqa: E402  (the script folder is on sys.path)

import learnest.estimators.native.codegen as codegen  # noqa: E402
from learnest.estimators.mhe import MHE  # noqa: E402
from learnest.estimators.prepared import initial_state, model_params, system_for  # noqa: E402
from learnest.estimators.ukf import run_ukf  # noqa: E402
from learnest.ingest import read_flights  # noqa: E402
from learnest.models.knode import HybridModel  # noqa: E402
from learnest.models.systems import make_system  # noqa: E402
from learnest.models.training import TrainingConfig  # noqa: E402
from learnest.workflows.flights import evaluate_flight, train_on_flight  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nanobench"
OUT = Path(__file__).parent / "results"


def compare(label, params, y, u, repeats):
    build = time.perf_counter()
    gn = MHE(params, horizon=20)
    build_gn = time.perf_counter() - build
    build = time.perf_counter()
    ipopt = MHE(params, horizon=20, solver="ipopt").prepare()
    build_ipopt = time.perf_counter() - build
    T = len(y)
    gn_s, ip_s, ours, ref = timed_side_by_side(lambda: gn.run(y, u).means, lambda: ipopt.run(y, u).means, repeats)
    runs = gn.stats["solves"] / T
    row = {"case": label, "steps": T, "gn_ms_per_step": 1e3 * gn_s / T, "ipopt_ms_per_step": 1e3 * ip_s / T,
           "speedup": ip_s / gn_s, "max_abs_difference": float(np.abs(ours - ref).max()),
           "gn_iterations_per_window": gn.stats["iterations"] / gn.stats["solves"],
           "gn_relinearisations_per_window": gn.stats["relinearisations"] / gn.stats["solves"],
           "gn_ipopt_fallbacks": gn.stats["ipopt_fallbacks"] / runs, "gn_backend": gn._gn.backend,
           "gn_build_s": build_gn, "ipopt_build_s": build_ipopt}
    print(row, flush=True)
    return row, ours


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=800, help="steps of the real flight for the MHE table")
    parser.add_argument("--baseline", type=Path, help="an earlier run's mhe_speed.json: per-step numbers side by side")
    args = parser.parse_args()
    torch.set_num_threads(1)
    train_flight, flight, other_flight = read_flights([DATA / "B2_circle_medium_rep2.csv",
                                                       DATA / "B2_circle_fast_rep2.csv",
                                                       DATA / "B2_circle_slow_rep2.csv"])
    config = TrainingConfig(hidden=16, epochs=50, lr=1e-3)
    knode = train_on_flight(train_flight, config).model
    other = train_on_flight(other_flight, config).model   # same architecture, other weights
    system = system_for(flight)
    knode = HybridModel(replace(knode.system, dt=flight.dt), knode.kind, knode.residual, knode.meta)
    prior = HybridModel(system, "prior")
    T = min(args.steps, len(flight.t))
    y, u, x0 = flight.measurements()[:T], np.zeros((T, 0)), initial_state(flight)
    # both models with the flight system's fixed noise, as the kinematic prior's defaults
    prior_params = model_params(prior, x0, flight.dt)
    knode_params = replace(prior_params, model=knode)
    rows = [compare("quadrotor prior MHE (real flight)", prior_params, y, u, args.repeats)[0]]
    knode_row, converged = compare("quadrotor KNODE-MHE (real flight, 16 hidden)", knode_params, y, u, args.repeats)
    rows.append(knode_row)
    for name, seed in (("cartpole", 3), ("robot", 3)):
        sim = make_system(name)
        run = sim.simulate(seed, n_samples=500)
        rows.append(compare(f"{name} MHE (prior model, simulated)", model_params(HybridModel(sim, "prior"),
                            run.x_noisy[0]), run.y, run.u, args.repeats)[0])

    rti = MHE(knode_params, horizon=20, max_iter=1)
    rti_s = statistics.median(_time(lambda: rti.run(y, u), args.repeats))
    rti_est = rti.run(y, u).means
    rti_row = {"steps": T, "ms_per_step": 1e3 * rti_s / T,
               "max_abs_error_vs_converged": float(np.abs(rti_est - converged).max()),
               "rms_error_vs_converged_by_group": {g: float(np.sqrt(np.mean((rti_est - converged)[:, s] ** 2)))
                                                   for g, s in (("p", slice(0, 3)), ("v", slice(3, 6)),
                                                                ("a", slice(6, 9)))}}
    print(rti_row, flush=True)

    ukf_cases = (("quadrotor prior UKF (compiled)", prior), ("quadrotor KNODE-UKF (compiled)", knode))
    ukf_rows = [_ukf_speed(label, replace(prior_params, model=model), y, u, args.repeats) for label, model in ukf_cases]
    end_to_end = _end_to_end(knode, other, args.repeats)
    report = {"machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                          "cpus": os.cpu_count(), "load_average_at_end": os.getloadavg()},
              "flight": flight.name, "mhe": rows, "ukf": ukf_rows, "knode_mhe_real_time_iteration": rti_row,
              "end_to_end": end_to_end}
    OUT.mkdir(exist_ok=True)
    (OUT / "mhe_speed.json").write_text(json.dumps(report, indent=2))
    md = ["# MHE speed: Gauss–Newton vs IPOPT (benchmarks/bench_mhe.py)", "",
          f"Machine: {report['machine']}", "",
          f"N = 20, arrival 'ekf', one core, medians of {args.repeats} alternating runs; IPOPT is today's "
          "warm-started build (hessian='cost'), built before timing.", "",
          "| case | steps | Gauss–Newton ms/step | IPOPT ms/step | speedup | max abs diff | GN iterations / window |",
          "|---|---|---|---|---|---|---|"]
    md += [f"| {r['case']} | {r['steps']} | {r['gn_ms_per_step']:.3f} | {r['ipopt_ms_per_step']:.3f} | "
           f"{r['speedup']:.1f}x | {r['max_abs_difference']:.1e} | {r['gn_iterations_per_window']:.2f} "
           f"(+{r['gn_relinearisations_per_window']:.2f} full Jacobians) |" for r in rows]
    md += ["", f"Real-time iteration (max_iter=1) of the KNODE-MHE: {rti_row['ms_per_step']:.3f} ms/step; "
           f"max |error| vs the converged estimate {rti_row['max_abs_error_vs_converged']:.2e} (RMS p, v, a: "
           + ", ".join(f"{v:.1e}" for v in rti_row["rms_error_vs_converged_by_group"].values()) + ").", "",
           f"End to end, {end_to_end['flight']} ({end_to_end['steps']} steps, {end_to_end['seconds_of_flight']:.1f} s "
           "of flight), load + references + UKF + KNODE-UKF + MHE + KNODE-MHE, compiled functions cached: "
           f"**{end_to_end['median_s']:.2f} s** (median of {args.repeats}; per method ms/step: "
           + ", ".join(f"{m} {v:.3f}" for m, v in end_to_end["ms_per_step"].items())
           + ")."]
    md += ["", "First use of a model, the same evaluation timed once (UKF, KNODE-UKF, MHE, KNODE-MHE; every compiled "
           "function of both models goes through the cache):", "",
           "| cache before the run | seconds | libraries in the cache before -> after |", "|---|---|---|",
           f"| (a) empty | {end_to_end['cold_s']:.2f} | 0 -> {end_to_end['cold_libraries']} |",
           f"| (b) holding another model of the same architecture | {end_to_end['same_architecture_s']:.2f} | "
           f"{end_to_end['same_architecture_libraries'][0]} -> {end_to_end['same_architecture_libraries'][1]} |",
           f"| filled by this model (the median above) | {end_to_end['median_s']:.2f} | - |"]
    md += ["", "Per step (ms), compiled, medians of alternating runs:", "",
           "| case | ms/step |" + (" baseline ms/step |" if args.baseline else ""),
           "|---|---|" + ("---|" if args.baseline else "")]
    baseline = _per_step(json.loads(args.baseline.read_text())) if args.baseline else {}
    for case, value in _per_step(report).items():
        md.append(f"| {case} | {value:.3f} |" + (f" {baseline[case]:.3f} |" if case in baseline else
                                                 (" - |" if args.baseline else "")))
    if args.baseline:
        md += ["", f"Baseline: {args.baseline.name}, machine load at its end "
               f"{json.loads(args.baseline.read_text())['machine']['load_average_at_end']}."]
    (OUT / "mhe_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def _time(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def _ukf_speed(label, params, y, u, repeats):
    """Compiled UKF ms/step (median of `repeats` runs, after one run that compiles or loads the functions)."""
    def run():
        return run_ukf(params, y, u, compiled=True)

    run()
    row = {"case": label, "steps": len(y), "ms_per_step": 1e3 * statistics.median(_time(run, repeats)) / len(y)}
    print(row, flush=True)
    return row


def _per_step(report):
    """{case: ms/step} of a report (this script's json) for the side-by-side table."""
    out = {f"{r['case']}, Gauss-Newton": r["gn_ms_per_step"] for r in report["mhe"]}
    out.update({r["case"]: r["ms_per_step"] for r in report.get("ukf", [])})
    out.update({f"end to end, {m}": v for m, v in report["end_to_end"]["ms_per_step"].items()})
    return out


def _end_to_end(knode, other, repeats):
    """Wall time of one flight's evaluation from its CSV, four methods, as `learnest evaluate` runs it;
    ``other`` is a model of the same architecture as ``knode`` (for the first use into a filled cache)."""
    path = DATA / "B2_circle_fast_rep2.csv"
    methods = ["ukf", "knode-ukf", "mhe", "knode-mhe"]

    def once(model, cache_dir=None):
        saved = codegen.DEFAULT_CACHE   # every compiled function (MHE and UKF) goes through this cache
        if cache_dir is not None:
            codegen.DEFAULT_CACHE = Path(cache_dir)
        try:
            start = time.perf_counter()
            flight = read_flights([path])[0]
            result = evaluate_flight(model, flight, methods)
            return time.perf_counter() - start, flight, result
        finally:
            codegen.DEFAULT_CACHE = saved

    def libraries(folder):
        return len(list(Path(folder).glob("*.so")))

    once(knode)  # fills the cache for these models
    times, flight, result = [], None, None
    for _ in range(repeats):
        seconds, flight, result = once(knode)
        times.append(seconds)
    with tempfile.TemporaryDirectory() as tmp:   # (a) a cold start: compile into an empty cache
        cold, _, _ = once(knode, tmp)
        cold_libraries = libraries(tmp)
    with tempfile.TemporaryDirectory() as tmp:   # (b) the cache already holds a model of this architecture
        once(other, tmp)
        before = libraries(tmp)
        same_architecture, _, _ = once(knode, tmp)
        same_libraries = (before, libraries(tmp))
    row = {"flight": flight.name, "steps": len(flight.t), "seconds_of_flight": float(flight.t[-1] - flight.t[0]),
           "median_s": statistics.median(times), "runs_s": times, "cold_s": cold, "cold_libraries": cold_libraries,
           "same_architecture_s": same_architecture, "same_architecture_libraries": same_libraries,
           "ms_per_step": {m: r["ms_per_step"] for m, r in result["results"].items()},
           "mse": {m: r["mse"] for m, r in result["results"].items()}}
    print(row, flush=True)
    return row


if __name__ == "__main__":
    main()
