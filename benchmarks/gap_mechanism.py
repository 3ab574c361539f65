"""Where a pooled Crazyflie KNODE loses in the mocap gaps of a held-out family: in the gaps, or before them?

Train the pooled KNODE on the other three families (full residual, as `benchmarks/family_holdout.py --scale full`),
then run the UKF with the mocap hidden in the gaps (`estimators.yardsticks`) on every flight of the held-out family
in variants that each change one thing, scored by the gap gain over the prior UKF with the default tuning
(100 (1 − Σ|e|² / Σ|e_prior|²) over the gap samples, %, with its 95 % block-bootstrap interval):

- ``knode``: the KNODE-UKF as evaluated;
- ``knode, accelerometer hidden too``: the accelerometer's rows masked in the gaps as well (and the prior's);
  the gain over the prior run the same way;
- ``knode only inside gaps`` / ``knode only outside gaps``: the filter steps with the prior where the mocap is
  present (absent) and with the KNODE where it is absent (present) (numpy UKF, same algorithm);
- ``Q_v x10`` / ``Q_v x30``: both filters with the velocity rows of Q scaled (prior and KNODE alike; the gain is
  over the default prior UKF, and the prior with the same Q is listed too);
- ``residual scale s``: the residual multiplied by s (`models.residual_scale`).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/gap_mechanism.py [--family helix] [--out benchmarks/results/gap_diagnosis]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from family_holdout import DATA, family_of  # noqa: E402

from learnest.estimators.evaluate import gain_interval  # noqa: E402
from learnest.estimators.mocap_gaps import PositionGapModel, gap_mask, masked_measurements  # noqa: E402
from learnest.estimators.params import EstimatorParams  # noqa: E402
from learnest.estimators.prepared import initial_state, model_system  # noqa: E402
from learnest.estimators.ukf import compiled_sigma_functions, run_ukf  # noqa: E402
from learnest.estimators.yardsticks import GapPlan  # noqa: E402
from learnest.ingest import read_flights  # noqa: E402
from learnest.models.inputs import system_inputs  # noqa: E402
from learnest.models.knode import HybridModel  # noqa: E402
from learnest.models.residual_scale import scaled_model  # noqa: E402
from learnest.workflows.flights import train_on_flights  # noqa: E402

ALL_ROWS = (0, 1, 2, 3, 4, 5)


class Switched:
    """A gap-masked model (`PositionGapModel`'s inputs: the model's, then the mask) stepping with ``present``
    where the mocap is present and with ``absent`` inside the gaps (numpy only)."""

    def __init__(self, present: HybridModel, absent: HybridModel):
        self.present, self.absent = present, absent
        self.n, self.n_inputs, self.n_meas = present.n, present.n_inputs + 1, present.n_meas

    def step(self, x, u, dt):
        u = np.asarray(u)
        mask = float(np.atleast_1d(u[..., -1]).ravel()[0])
        return (self.present if mask > 0.5 else self.absent).step(x, u[..., :-1], dt)

    def h(self, x, u=None):
        u = np.asarray(u)
        y = np.array(self.present.h(x, u[..., :-1]), dtype=float, copy=True)
        y[..., :3] *= np.asarray(u[..., -1])[..., None]
        return y


def flight_variants(knode: HybridModel, flight, cache: dict) -> tuple[dict, list]:
    """{variant: (prior's squared gap errors (K,), the variant's (K,)) in m²} of one flight, and its gap windows."""
    system = model_system(knode, flight)
    u = system_inputs(flight, system, thrust_gain=True)
    y, x0 = flight.measurements(), initial_state(flight)
    windows = GapPlan().windows(len(flight.t), flight.dt)
    inside = gap_mask(len(flight.t), windows)
    prior = HybridModel(system, "prior")
    full = HybridModel(system, "knode", knode.residual, knode.meta)

    def q(v_factor):
        d = np.diag(system.Q).copy()
        d[3:6] *= v_factor ** 2
        return np.diag(d)

    def gap_error(model, rows=(0, 1, 2), Q=None, compiled=True):
        yg, ug = masked_measurements(y, u, inside, rows)
        gapped = PositionGapModel(model, rows) if isinstance(model, HybridModel) else model
        functions = None
        if compiled:
            key = (id(model.residual), rows)
            if key not in cache:   # the model is kept with its functions: a freed model's id could be reused
                cache[key] = (model, compiled_sigma_functions(gapped, flight.dt))
            functions = cache[key][1]
        params = EstimatorParams(gapped, flight.dt, system.Q if Q is None else Q, system.R, system.P0, x0)
        est = run_ukf(params, yg, ug, sigma_functions=functions).means
        return np.sum((est[inside][:, :3] - flight.p[inside]) ** 2, axis=1)

    base = gap_error(prior)
    variants = {
        "knode": (base, gap_error(full)),
        "knode, accelerometer hidden too": (gap_error(prior, ALL_ROWS), gap_error(full, ALL_ROWS)),
        "knode only inside gaps": (base, gap_error(Switched(prior, full), compiled=False)),
        "knode only outside gaps": (base, gap_error(Switched(full, prior), compiled=False)),
        "prior, Q_v x10": (base, gap_error(prior, Q=q(10))),
        "knode, Q_v x10": (base, gap_error(full, Q=q(10))),
        "prior, Q_v x30": (base, gap_error(prior, Q=q(30))),
        "knode, Q_v x30": (base, gap_error(full, Q=q(30))),
    }
    for s in (0.5, 0.25):
        variants[f"knode, residual scale {s}"] = (base, gap_error(scaled_model(full, s)))
    return variants, windows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="helix")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/gap_diagnosis"))
    args = parser.parse_args(argv)
    started = time.perf_counter()
    paths = sorted(p for folder in DATA for p in folder.glob("B*.csv"))
    flights = [f for f in read_flights(paths) if family_of(f.name)]
    train = [f for f in flights if f.quality["ok"] and family_of(f.name) != args.family]
    knode = train_on_flights(train, system="crazyflie", group_by="none").model
    cache: dict = {}
    gains: dict[str, list] = {}
    for flight in (f for f in flights if family_of(f.name) == args.family and f.quality["ok"]):
        variants, windows = flight_variants(knode, flight, cache)
        per_gap = windows[0][1] - windows[0][0]
        for name, (ref, err) in variants.items():
            interval = gain_interval(ref, err, per_gap)
            gains.setdefault(name, []).append({"flight": flight.name, "gain_pct": 100 * (1 - err.sum() / ref.sum()),
                                               "interval_pct": interval})
        print(flight.name, {k: round(v[-1]["gain_pct"], 1) for k, v in gains.items()}, file=sys.stderr, flush=True)
    summary = {name: {"median_gain_pct": float(np.median([r["gain_pct"] for r in rows])),
                      "better": sum(r["gain_pct"] > 0 for r in rows), "flights": len(rows),
                      "worse_beyond": sum(1 for r in rows if r["interval_pct"] and r["interval_pct"][1] < 0)}
               for name, rows in gains.items()}
    command = "python benchmarks/gap_mechanism.py " + " ".join(argv if argv is not None else sys.argv[1:])
    result = {"command": command.strip(), "family": args.family, "summary": summary, "flights": gains,
              "seconds": time.perf_counter() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"gap_mechanism_{args.family}.json").write_text(json.dumps(result, indent=1, default=float))
    lines = [f"# Where the pooled Crazyflie KNODE loses in the gaps: {args.family} held out", "",
             f"Command: `{result['command']}` ({result['seconds']:.0f} s)", "",
             "| variant | median gap gain over the default prior UKF | better | worse beyond interval |",
             "|---|---|---|---|"]
    lines += [f"| {k} | {v['median_gain_pct']:+.1f} % | {v['better']}/{v['flights']} | {v['worse_beyond']} |"
              for k, v in summary.items()]
    (args.out / f"gap_mechanism_{args.family}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
