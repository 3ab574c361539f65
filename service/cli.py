"""The `learnest` command line."""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import NoReturn

from learnest.errors import InvalidInput, LearnestError
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    EVALUATION_METHODS,
    GAP_EVERY_S,
    GAP_S,
    METHODS,
    MHE_HORIZON,
    PRODUCTION_ALIAS,
    SG_WINDOW,
    SG_WINDOW_RANGE,
)


# -- argument types: refuse bad values before any import or ingest (one-line error, exit 2) -----------
def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    return _whole_number(text, 1)


def _seconds(text: str) -> float:
    """A non-negative number of seconds (a gap length of 0 turns the gap yardstick off)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a non-negative number of seconds, got {text!r}")
    return value


def _gap_plan(args):
    """The gaps --gap-s and --gap-every-s ask for, checked before any flight is read (InvalidInput when the
    gaps would leave no mocap between them)."""
    from learnest.estimators.yardsticks import GapPlan

    return GapPlan(args.gap_s, args.gap_every_s)


def _add_gap_arguments(parser: argparse.ArgumentParser) -> None:
    """--gap-s and --gap-every-s: where the mocap-gap yardstick hides the mocap (estimators.yardsticks)."""
    parser.add_argument("--gap-s", type=_seconds, default=GAP_S, metavar="S",
                        help=f"mocap-gap yardstick: hide the mocap position from the estimators for S s per gap "
                             f"(default {GAP_S}; 0: no gaps)")
    parser.add_argument("--gap-every-s", type=_positive_float, default=GAP_EVERY_S, metavar="S",
                        help=f"one gap every S s after the first 5 s of the kept flight (default {GAP_EVERY_S})")


def _whole_number(text: str, least: int = 0) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be at least {least}, got {text!r}")
    return value


def _sg_window(text: str) -> int:
    """A Savitzky-Golay window in samples, within `SG_WINDOW_RANGE`."""
    value = _positive_int(text)
    low, high = SG_WINDOW_RANGE
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"must be {low} to {high} samples, got {text!r}")
    return value


def _model_ref(text: str) -> str:
    """A registry reference, checked for its form only (whether it exists needs the registry)."""
    from .references import parse_ref

    try:
        return str(parse_ref(text))
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _name(text: str) -> str:
    """A registered model or alias name (references.NAME), checked before any import of the service."""
    from .references import check_name

    try:
        return check_name(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _topic(text: str) -> str:
    """A ROS topic name, optionally with ":BODY" (one body of a TFMessage / NamedPoseArray topic)."""
    from .references import check_topic

    try:
        return check_topic(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _add_topic_arguments(parser: argparse.ArgumentParser) -> None:
    """--pose-topic / --imu-topic, for the commands that read MCAP recordings and ROS bags."""
    parser.add_argument("--pose-topic", type=_topic, metavar="TOPIC",
                        help="MCAP/ROS bag: the pose topic to read, e.g. /poses:cf1 (one body of a NamedPoseArray "
                             "or /tf topic) or /vicon/cf1/cf1 (default: the motion-capture topic, if only one)")
    parser.add_argument("--imu-topic", "--accel-topic", dest="imu_topic", type=_topic, metavar="TOPIC",
                        help="MCAP/ROS bag: the acceleration topic (sensor_msgs/Imu or LogDataGeneric), "
                             "e.g. /cf1/imu (default: the only one, or the pose's vehicle's)")


def _topics(args) -> dict:
    return {"pose_topic": getattr(args, "pose_topic", None), "imu_topic": getattr(args, "imu_topic", None)}


def _cut(text: str) -> str:
    """The take-off/landing cut, checked for its form before any work (`learnest.ingest.align.parse_cut`)."""
    from learnest.ingest.align import cut_text, parse_cut

    try:
        return cut_text(parse_cut(text))
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _add_cut_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cut", type=_cut, default="auto", metavar="auto|none|START:STOP",
                        help="the stretch of each recording to keep: auto (default: the flying part, take-off and "
                             "landing cut; a log that starts in the air keeps its start), none (everything) or "
                             "START:STOP in seconds from the recording's start, e.g. 2.5:14 (either side may be empty)")


def _new_file(text: str) -> str:
    """An output path whose folder exists: a typo must not cost a whole evaluation."""
    folder = Path(text).expanduser().resolve().parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"folder {folder} does not exist")
    if Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file name")
    return text


def _reproduce(args) -> int:
    from .experiments.table1 import ReproduceSettings, format_table, reproduce

    settings = ReproduceSettings(task=args.task, eval_samples=args.samples, epochs=args.epochs, horizon=args.horizon,
                                 observer_rounds=args.observer_rounds, observer=args.observer)
    from .progress import StageProgress

    with StageProgress(f"Table I {args.task}") as bar:
        done = [0]

        def seed_done(_result) -> None:
            done[0] += 1
            bar.update(done[0] / args.seeds, f"{done[0]}/{args.seeds} seeds done")

        report = reproduce(settings, args.seeds, workers=args.workers, progress=seed_done,
                           first_seed=args.first_seed)
    print(format_table(report))
    print(f"wall time {report['wall_time_s']:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


def _thrust_map(args) -> int:
    from .experiments.thrust_map import bench_thrust_map_report, format_bench_map, format_thrust_map, thrust_map_report

    if args.bench:
        if args.fit or args.score:
            raise InvalidInput("thrust-map: give --bench CSV, or --fit and --score flights, not both")
        report = bench_thrust_map_report(args.bench, args.mass_kg)
        print(json.dumps(report, indent=2) if args.json else format_bench_map(report))
        return 0
    if not args.fit or not args.score:
        raise InvalidInput("thrust-map needs --fit and --score flight logs (or --bench CSV, a bench calibration)")

    sets, errors = {}, []
    for role, given in (("fit", args.fit), ("score", args.score)):
        try:
            batch = _read_batch(given, args.rate)
        except InvalidInput as err:
            raise InvalidInput(f"{err} (--{role})") from None
        sets[role], errors = batch.flights, errors + batch.errors
    from .progress import StageProgress

    with StageProgress("thrust map") as bar:
        def stage(name: str, done: int, total: int) -> None:
            bar.update(done / total if total else None, name)

        report = thrust_map_report(sets["fit"], sets["score"], progress=stage)
    if args.json:
        report["errors"] = errors
    print(json.dumps(report, indent=2) if args.json else format_thrust_map(report))
    return _batch_status(errors)


def _read(paths, rate_hz, topics: dict | None = None, cut: str | None = None):
    from learnest.ingest import read_flights

    return read_flights(paths, rate_hz=rate_hz, **(topics or {}), cut=cut)


def _read_batch(paths, rate_hz, topics: dict | None = None, cut: str | None = None, *, need: int = 1):
    """Read every flight of ``paths`` past the files that cannot be read (`learnest.ingest.batch.read_batch`):
    each of those is named on stderr with its reason, and the batch goes on (the command then exits with
    status 1, `_batch_status`).  InvalidInput (status 2) when fewer than ``need`` flights were read: nothing
    to go on with."""
    from learnest.ingest.batch import format_errors, read_batch

    batch = read_batch(paths, rate_hz=rate_hz, **(topics or {}), cut=cut)
    for note in batch.notes:
        print(note, file=sys.stderr)
    for line in format_errors(batch.errors):
        print(f"learnest: {line}", file=sys.stderr)
    if len(batch.flights) < need:
        failed = f" ({len(batch.errors)} file(s) could not be read)" if batch.errors else ""
        raise InvalidInput(f"no flight logs read from {', '.join(map(str, paths))}{failed}")
    return batch


def _gap_lines(timing: dict | None, delivered_below: float = 0.95) -> list[str]:
    """One line for the mocap and the accelerometer each, when it lost more than 5 % of its samples
    (`learnest.ingest.align.stream_timing`): a stream with gaps, at its own rate."""
    return [f"  {name}: {t['rate_hz']:.1f} Hz with gaps: {100 * t['delivered']:.0f} % of its samples delivered "
            f"({t['gaps']} gaps, longest {t['longest_gap_s']:.2f} s)"
            for name, t in (timing or {}).items()
            if name in ("mocap", "acc") and t and t["delivered"] < delivered_below]


def _batch_status(errors: list) -> int:
    """Exit status of a command that read several files: 1 when any could not be read."""
    if errors:
        print(f"learnest: {len(errors)} file(s) could not be read (listed above); the others were used",
              file=sys.stderr)
    return 1 if errors else 0


def _ingest(args) -> int:
    from learnest.ingest import summary

    # a folder stands for its logs; sidecars are read with their logs; an unreadable file is named, not fatal
    batch = _read_batch(args.files, args.rate, _topics(args), args.cut)
    flights = batch.flights
    if args.json:
        print(json.dumps({"flights": [{"name": f.name, **summary(f)} for f in flights], "errors": batch.errors},
                         indent=2))
    else:
        for f in flights:
            s = summary(f)
            state = "ok" if s["quality"]["ok"] else "BAD: " + "; ".join(s["quality"]["issues"])
            offset = "" if s["clock_offset_s"] is None else f", clock offset {s['clock_offset_s']:+.3f} s"
            print(f"{f.name}: {s['adapter']}, {s['duration_s']:.1f} s at {s['rate_hz']:.0f} Hz "
                  f"({s['samples']} samples{offset}) — {state}")
            if s["kept"]:
                k = s["kept"]
                print(f"  kept {k['start_s']:.2f}-{k['stop_s']:.2f} s of the {k['recording_s']:.2f}-s recording: "
                      f"{k['rule']} (--cut to change)")
            if s["topics"]:
                t = s["topics"]
                print(f"  pose from {t['pose']} ({t['pose_type']}, {t['pose_source']}); "
                      f"acceleration from {t['accel']} ({t['accel_type']})")
            for warning in s["warnings"]:
                print(f"  WARNING: {warning}")
            print(*_gap_lines(s.get("timing")), sep="\n", end="\n" if _gap_lines(s.get("timing")) else "")
    failed = [f.name for f in flights if not f.quality["ok"]]
    if args.strict and failed:
        print(f"learnest: {len(failed)} of {len(flights)} flight(s) failed the quality checks: {', '.join(failed)}",
              file=sys.stderr)
        return 1
    return _batch_status(batch.errors)


def _train(args) -> int:
    """Store the flight and register the next version of NAME in the registry (service.local_registry)."""
    from learnest.ingest.batch import format_errors

    from .local_registry import UnreadableFile, train
    from .progress import StageProgress

    _registry_grid(args.rate)
    try:
        with StageProgress(f"training {args.name}") as bar:
            out = train(args.files, args.name, epochs=args.epochs, include_bad=args.include_bad,
                        progress=bar.progress, system=args.system, on_stage=bar.on_stage, **_topics(args),
                        cut=args.cut, validate=args.validate, strict=args.strict)
    except UnreadableFile as err:   # --strict: the first unreadable file stops the command, nothing trained
        print(f"learnest: {err}; nothing was trained (--strict)", file=sys.stderr)
        return 1
    out["command_seconds"] = time.perf_counter() - _command_started[0]
    for line in format_errors(out["errors"]):
        print(f"learnest: {line}", file=sys.stderr)
    print(json.dumps(out, indent=2) if args.json else format_trained(out))
    return _batch_status(out["errors"])


def format_trained(out: dict) -> str:
    """`learnest train`'s text: what was registered, on which flights, and whether the residual learned
    anything that held-out data confirm."""
    from learnest.models.training import NOT_LEARNED

    if len(out["training_flights"]) == 1 and not out["validation_flights"]:
        on = f"trained on {out['training_flight']} (flight {out['flight_id']})"
    else:
        count = len(out["training_flights"])
        on = (f"trained on {count} flight{'s' if count != 1 else ''} ({', '.join(out['training_flights'])}), "
              f"validated on {len(out['validation_flights'])} held-out flight(s) "
              f"({', '.join(out['validation_flights']) or 'none'})")
    lines = [f"registered {out['ref']} ({out['system']} prior): {on}: {out['epochs']} epochs in "
             f"{out['seconds']:.1f} s, kept epoch {out['best_epoch']}; {out['command_seconds']:.1f} s in all (this "
             "command: imports, storing the flights, starting a worker, the pre-training observer, the epochs, storing "
             f"the model); registry in {out['home']}"]
    if out.get("skipped_flights"):
        lines.append("left out (failed the quality checks; --include-bad keeps them): "
                     + "; ".join(out["skipped_flights"]))
    if not out["learned"]:
        lines.append(f"NOT LEARNED: {out.get('learned_note') or NOT_LEARNED}")
    elif out.get("prior_validation_loss") and out.get("best_validation_loss") is not None:
        gain = 100 * (1 - out["best_validation_loss"] / out["prior_validation_loss"])
        lines.append(f"learned: the held-out one-step loss is {gain:.1f} % below the prior's")
    elif out.get("learned_note"):
        lines.append(out["learned_note"])
    return "\n".join(lines)


_command_started = [time.perf_counter()]   # reset by main(): the command's whole time, imports included


def _registry_grid(rate: float, hint: str = "") -> None:
    if rate != 100.0:
        raise InvalidInput("--rate: flights in the model registry are on the service's 100 Hz grid"
                           + (f"; {hint}" if hint else ""))


def _evaluate(args) -> int:
    """Evaluate a registered model on flight files: stored in the registry (flights and evaluation, as the
    web UI's), or with --no-store only computed here."""
    from learnest.models.presets import parse_methods

    from .local_registry import load_model
    from .web.figures import evaluation_summary, save_figure

    if args.new:
        return _evaluate_new(args)
    if not args.model or not args.files:
        raise InvalidInput("evaluate needs --model REF and FILE..., or --new [--alias ALIAS]")
    methods = parse_methods(args.methods, EVALUATION_METHODS)
    _gap_plan(args)
    if args.store:
        _registry_grid(args.rate, "pass --no-store to evaluate on another grid without storing")
    model = load_model(args.model)
    if args.system and args.system != model.system.name:
        raise InvalidInput(f"{args.model} was trained with the {model.system.name!r} prior, not {args.system!r}")
    ref = model.meta.get("ref", args.model)  # name:version, whatever form was asked for
    report = (_evaluate_stored if args.store else _evaluate_here)(args, model, ref, methods)
    if args.plot:
        save_figure(evaluation_summary(report), args.plot, dpi=120)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(format_report(report))
        for stored in report.get("stored") or []:
            print(f"  {stored['file']}: {stored['stored']} flight {stored['flight_id']} ({stored['name']})")
        if "evaluation_id" in report:
            print(f"stored as evaluation {report['evaluation_id']} in {_home()} (web page "
                  f"/evaluations/{report['evaluation_id']}/report.html under `learnest serve`)")
        if args.export and report["flights_scored"]:
            print(f"estimates written to {args.export}")
    if args.export and not report["flights_scored"]:
        print(f"learnest: no flight was scored: {args.export} not written", file=sys.stderr)
    return _batch_status(report.get("errors") or [])


def _evaluate_stored(args, model, ref: str, methods: list[str]) -> dict:
    """Store the flights and the evaluation in the registry (service.local_registry.evaluate)."""
    from learnest.ingest.batch import format_errors

    from .jobs.result_cache import EstimatorSettings
    from .local_registry import evaluate, export

    settings = EstimatorSettings(tuple(methods), args.horizon, args.include_bad, args.sg_window, args.gap_s,
                                 args.gap_every_s)
    from .progress import StageProgress

    with StageProgress("evaluating") as bar:
        report = evaluate(args.files, ref, settings, progress=bar.progress, on_stage=bar.on_stage, **_topics(args),
                          cut=args.cut)
    for line in format_errors(report.get("errors") or []):
        print(f"learnest: {line}", file=sys.stderr)
    if args.export and report["flights_scored"]:
        export(report["evaluation_id"], args.export, _export_format(args.export))
    return report


def _evaluate_here(args, model, ref: str, methods: list[str]) -> dict:
    """Evaluate in this process and store nothing (--no-store); --export writes the estimates kept on the way."""
    from learnest.estimators.export import write_estimates

    from .experiments.flights import evaluate_flights
    from .progress import StageProgress

    batch = _read_batch(args.files, args.rate, _topics(args), args.cut)
    flights = batch.flights
    kept: list = []
    with StageProgress("evaluating") as bar:
        done = [0]

        def flight_done(_flight) -> None:
            done[0] += 1
            bar.update(done[0] / len(flights), f"{done[0]}/{len(flights)} flight(s) done")

        report = evaluate_flights(model, flights, methods, include_bad=args.include_bad, horizon=args.horizon,
                                  sg_window=args.sg_window, progress=flight_done,
                                  gap_s=args.gap_s, gap_every_s=args.gap_every_s,
                                  on_estimates=(lambda _i, e: kept.append(e)) if args.export else None)
    report["model"] = ref
    report["errors"] = batch.errors
    if args.export and kept:
        write_estimates(kept, args.export, _export_format(args.export))
    return report


def _export(args) -> int:
    """Write a stored evaluation's state estimates (service.exports) as CSV, Parquet or MCAP."""
    from .local_registry import export

    fmt = args.format or _export_format(args.output)
    flights = export(args.evaluation_id, args.output, fmt, args.flight)
    methods = sorted({m for f in flights for m in f.methods})
    print(f"wrote {args.output} ({fmt}): {len(flights)} flight(s) "
          f"({', '.join(f.flight for f in flights)}), methods {', '.join(methods)}")
    return 0


def _export_format(path: str) -> str:
    from learnest.estimators.export import format_of

    return format_of(path)


def _export_path(text: str) -> str:
    """An output file whose folder exists and whose suffix names an export format (.csv, .parquet, .mcap)."""
    from learnest.estimators.export import format_of

    try:
        format_of(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return _new_file(text)


def _home() -> str:
    from .config import Settings

    return str(Settings().home)


def _evaluate_new(args) -> int:
    """One scheduler round (for cron): evaluate every stored flight without a result for name@alias."""
    from learnest.models.presets import parse_methods

    from .jobs.result_cache import EstimatorSettings
    from .jobs.scheduler import evaluate_new_once

    _gap_plan(args)
    settings = EstimatorSettings(tuple(parse_methods(args.methods, EVALUATION_METHODS)), args.horizon,
                                 args.include_bad, gap_s=args.gap_s, gap_every_s=args.gap_every_s)
    rounds = evaluate_new_once(args.alias, settings)
    if args.json:
        print(json.dumps({"alias": args.alias, "busy": rounds is None, "evaluations": rounds or []}, indent=2))
    elif rounds is None:
        print("another process (the server's scheduler) holds the scheduler lease: nothing done")
    elif not rounds:
        print(f"nothing new to evaluate for models with alias {args.alias!r}")
    for r in [] if args.json else rounds or []:
        print(f"{r['model']}: evaluation {r['evaluation_id']} ({r['state']}) of {len(r['flights'])} new flight(s)"
              + (f" ({r['failed']} failed)" if r.get("failed") else ""))
    return 0


def _flights_list(args) -> int:
    """The stored flights (service.local_registry.list_flights)."""
    from .local_registry import list_flights

    out = list_flights(args.q)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{out['total']} flight(s)" + (f" whose name contains {args.q!r}" if args.q else ""))
    if out["items"]:
        print(f"{'id':>5}  {'name':<32}{'format':<16}{'duration':>9}  {'quality':<8}uploaded (UTC)")
    for f in out["items"]:
        quality = "ok" if f["quality"].get("ok") else "BAD"
        print(f"{f['id']:>5}  {f['name']:<32}{f['adapter']:<16}{f['duration_s']:>7.1f} s  {quality:<8}"
              f"{f['created_at'][:19].replace('T', ' ')}")
    return 0


def _models_list(args) -> int:
    """The registered models (service.local_registry.list_models)."""
    from .local_registry import list_models

    out = list_models(args.q)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{out['total']} model(s)" + (f" whose name contains {args.q!r}" if args.q else ""))
    if out["items"]:
        print(f"{'name':<24}{'versions':>9}{'latest ready':>14}  aliases")
    for m in out["items"]:
        aliases = ", ".join(f"@{a} -> {v}" for a, v in m["aliases"].items()) or "-"
        latest = "-" if m["latest_version"] is None else str(m["latest_version"])
        print(f"{m['name']:<24}{m['versions']:>9}{latest:>14}  {aliases}")
    return 0


def _models_show(args) -> int:
    """A model's versions, or one version with its lineage and evaluations."""
    from .local_registry import show_model

    out = show_model(args.ref)
    print(json.dumps(out, indent=2, default=str) if args.json else format_model(out))
    return 0


def format_model(out: dict) -> str:
    """`learnest models show`'s text: a model's versions table, or one version's details."""
    if "versions" in out:
        aliases = ", ".join(f"@{a} -> {v}" for a, v in out["aliases"].items()) or "none"
        lines = [f"model {out['name']}: latest ready version {out['latest_version']}; aliases {aliases}",
                 f"{'version':>7}  {'status':<9}{'training flight':<28}{'epochs':>7}{'final loss':>12}"
                 f"{'train s':>9}  parent"]
        for v in out["versions"]:
            loss, seconds = (v["metrics"] or {}).get("final_loss"), v["training_seconds"]
            loss_text = "-" if loss is None else f"{loss:.4g}"
            seconds_text = "-" if seconds is None else f"{seconds:.1f}"
            flights = v.get("training_flights") or [v["training_flight"]]
            trained_on = str(flights[0]["name"]) + (f" +{len(flights) - 1}" if len(flights) > 1 else "")
            lines.append(f"{v['version']:>7}  {v['status']:<9}{trained_on:<28}"
                         f"{str((v['hyperparameters'] or {}).get('epochs')):>7}{loss_text:>12}{seconds_text:>9}"
                         f"  {v['parent'] or '-'}" + (f"  @{', @'.join(v['aliases'])}" if v["aliases"] else ""))
        return "\n".join(lines)
    lineage, hp, metrics = out["lineage"], out["hyperparameters"] or {}, out["metrics"] or {}
    flight = lineage["training_flight"]
    made = lineage["diagnosis"]
    lines = [f"{out['ref']}: {out['status']}" + (f" ({out['error']})" if out["error"] else "")
             + (f", aliases @{', @'.join(out['aliases'])}" if out["aliases"] else ""),
             f"  prior {hp.get('system', 'quadrotor')}; "
             + ", ".join(f"{k} {v}" for k, v in hp.items() if k != "system"),
             "  metrics: " + (", ".join(f"{k} {v:.4g}" for k, v in metrics.items()
                                        if isinstance(v, (int, float)) and not isinstance(v, bool)) or "none"),
             f"  training time {out['training_seconds']:.1f} s (the epochs)" if out["training_seconds"] else
             "  training time -",
             *_trained_on_lines(lineage, flight, metrics),
             f"  parent {lineage['parent']['ref'] if lineage['parent'] else 'none'}"
             + ("" if not lineage["parent"] or lineage["parent"]["exists"] else " (deleted)"),
             f"  children {', '.join(c['ref'] for c in lineage['children']) or 'none'}"]
    if made:
        lines.append(f"  made by {'diagnosis ' + str(made['id']) if made['id'] else 'a diagnosis'}, adding "
                     f"{', '.join(made['effects_added']) or 'no effect'}")
    lines.append(f"  evaluations: {len(lineage['evaluations'])}")
    for e in lineage["evaluations"]:
        mse = ", ".join(f"{m} {x * 1e3:.3f}" for m, x in e["median_mse"].items())
        better = ", ".join(f"{k.replace('_vs_', ' vs ')} {x:+.1f} %" for k, x in e["improvement_pct"].items())
        lines.append(f"    {e['id']}: {e['state']} on flights {', '.join(map(str, e['flight_ids']))}"
                     + (f"; median MSE x 1e-3: {mse}" if mse else "") + (f"; {better}" if better else ""))
    return "\n".join(lines)


def _trained_on_lines(lineage: dict, flight: dict, metrics: dict) -> list[str]:
    """`models show`'s lines on a version's training and validation flights (with their sha256) and on
    whether its residual learned anything held-out data confirm."""
    trained, held = lineage.get("training_flights") or [], lineage.get("validation_flights") or []

    def listed(flights: list[dict]) -> str:
        return ", ".join(f"{f['id']} ({f['name']}, sha256 {str(f.get('sha256') or '-')[:12]})"
                         + ("" if f["exists"] else ", deleted since") for f in flights)

    if len(trained) <= 1 and not held:
        lines = [f"  trained on flight {flight['id']} ({flight['name']})"
                 + ("" if flight["exists"] else ", deleted since")]
    else:
        lines = [f"  trained on {len(trained)} flights: {listed(trained)}",
                 f"  validated on {len(held)} held-out flight(s): {listed(held) or 'none'}"]
    if lineage.get("learned") is False:
        lines.append(f"  NOT LEARNED: {lineage.get('learned_note')}")
    elif metrics.get("prior_validation_loss") and metrics.get("best_validation_loss") is not None:
        gain = 100 * (1 - metrics["best_validation_loss"] / metrics["prior_validation_loss"])
        lines.append(f"  learned: held-out one-step loss {gain:.1f} % below the prior's")
    elif lineage.get("learned_note"):
        lines.append(f"  {lineage['learned_note']}")
    return lines


def _alias_set(args) -> int:
    """Point NAME@ALIAS at VERSION (service.local_registry.set_alias)."""
    from .local_registry import set_alias

    out = set_alias(args.name, args.version, args.alias)
    before = out["previous_version"]
    print(json.dumps(out, indent=2) if args.json else
          f"{out['name']}@{out['alias']} -> version {out['version']}"
          + ("" if before is None else f" (was {before})" if before != out["version"] else " (unchanged)"))
    return 0


def _serve(args) -> int:
    """The HTTP service (FastAPI app factory service.api.app:create_app under uvicorn); docs at /docs."""
    import os

    import uvicorn

    from .api.server import uvicorn_options
    from .config import Settings

    if args.dask:  # the app reads its settings from the environment, in every worker process
        os.environ["LEARNEST_DASK"] = args.dask
    for option in SERVE_LIMITS:  # likewise the connection limits given on the command line
        value = getattr(args, option)
        if value is not None:
            os.environ[f"LEARNEST_{option.upper()}"] = str(value)
    if args.host not in ("0.0.0.0", "::"):  # the name it is reached by is served (LEARNEST_ALLOWED_HOSTS)
        served = os.environ.get("LEARNEST_ALLOWED_HOSTS", Settings.model_fields["allowed_hosts"].default)
        os.environ["LEARNEST_ALLOWED_HOSTS"] = f"{served},{args.host}"
    else:
        print("learnest: serving every interface: set LEARNEST_ALLOWED_HOSTS to the names clients use "
              "(requests for other host names get 400)", file=sys.stderr)
    settings = Settings()  # validated here: a bad value stops the start with its name
    uvicorn.run("learnest.service.api.app:create_app", factory=True, host=args.host, port=args.port,
                workers=args.workers, **uvicorn_options(settings))
    return 0


# `learnest serve --NAME` options that override LEARNEST_NAME (service.config): timeouts and limits
SERVE_LIMITS = {"header_timeout_s": (float, "a request's headers must arrive within this many seconds (10)"),
                "body_timeout_s": (float, "a request body gets this many seconds (30) ..."),
                "body_min_rate": (float, "... plus one per this many bytes received (10000); else 408"),
                "keep_alive_s": (float, "close an idle keep-alive connection after this many seconds (5)"),
                "limit_concurrency": (int, "connections + requests in progress beyond which the answer is 503 "
                                           "(200; 0 = no limit)"),
                "decode_workers": (int, "uploads decoded at once (2)"),
                "decode_timeout_s": (float, "one upload's decode time limit, seconds (60)")}


def _demo(args) -> int:
    """ingest -> train on one flight -> evaluate on every other flight of a folder."""
    from learnest.ingest import IngestError, detect
    from learnest.models.presets import parse_methods

    from .experiments.flights import evaluate_flights
    from .local_registry import load_model, train
    from .progress import StageProgress
    from .web.figures import evaluation_summary, save_figure

    _registry_grid(args.rate)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise InvalidInput(f"{folder}: not a folder")
    logs = []
    documents = {".md", ".txt", ".yaml", ".yml"}  # READMEs and sidecar metadata, not logs
    for path in sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() not in documents):
        try:
            detect(path)
            logs.append(path)
        except IngestError as err:
            print(f"skipped {err}", file=sys.stderr)
    batch = _read_batch(logs, args.rate, need=0)
    flights = batch.flights
    print(f"ingested {len(flights)} flights from {len(logs)} files in {folder}")
    clean = [f for f in flights if f.quality["ok"]]
    if len(clean) < 2:
        raise InvalidInput(f"{folder}: need at least two flights that pass the quality checks, found {len(clean)}")
    from learnest.models.inputs import missing_inputs

    # the Crazyflie prior (motors and battery) where the flights carry its inputs: it knows the vehicle's
    # thrust, which the kinematic prior leaves to the network
    driven = [f for f in clean if not missing_inputs(f, "crazyflie")]
    pool = driven if args.system == "crazyflie" or (args.system is None and len(driven) >= 2) else clean
    system = "crazyflie" if pool is driven else "quadrotor"
    if len(pool) < 2:
        raise InvalidInput(f"{folder}: the {system} prior needs at least two clean flights with motor PWM and "
                           f"battery voltage, found {len(pool)}")
    chosen = [f for f in pool if f.name == args.train] if args.train else pool[:1]
    if not chosen:
        raise InvalidInput(f"no clean flight named {args.train!r} in {folder}"
                           + (" with motor PWM and battery voltage" if system == "crazyflie" else ""))
    kept = {id(f) for f in pool}   # by identity: a Flight's == compares arrays
    left_out = [f.name for f in flights if id(f) not in kept]
    print(f"prior: {system}" + (" (the flights carry motor PWM and battery voltage)" if system == "crazyflie" else "")
          + (f"; scored on the {len(pool) - 1} other flight(s) with the same inputs, left out: "
             f"{', '.join(left_out)}" if left_out else ""))
    with StageProgress(f"training on {chosen[0].name}") as bar:
        trained = train([source["path"] for source in chosen[0].meta["sources"]], args.name, progress=bar.progress,
                        on_stage=bar.on_stage, system=system)
    print(f"registered {trained['ref']} in {trained['home']}")
    with StageProgress("evaluating") as bar:
        done = [0]

        def flight_done(_flight) -> None:
            done[0] += 1
            bar.update(done[0] / len(pool), f"{done[0]}/{len(pool)} flight(s) done")

        report = evaluate_flights(load_model(trained["ref"]), pool, parse_methods(args.methods, EVALUATION_METHODS),
                                  horizon=args.horizon, progress=flight_done)
    report["model"] = trained["ref"]
    print(format_report(report))
    if args.plot:
        save_figure(evaluation_summary(report), args.plot, dpi=120)
        print(f"gain per flight and MSE per flight (prior vs KNODE): {args.plot}")
    print(f"\nnext: `learnest serve`, then open http://127.0.0.1:8000/ui/models/{args.name} to see the model, "
          f"evaluate it on other flights and diagnose it from the browser")
    return _batch_status(batch.errors)


def _diagnose(args) -> int:
    from learnest.models.presets import parse_methods

    from .experiments.diagnosis import diagnose_flights, diagnose_simulated, format_diagnosis
    from .web.figures import residual_before_after, save_figure

    methods = parse_methods(args.methods)
    if args.simulate is not None or args.system in ("cartpole", "robot"):
        if args.files:
            raise InvalidInput("give flight files or --simulate, not both")
        if args.register:
            raise InvalidInput("--register registers a repaired Crazyflie model: give flight files, not --simulate")
        result = diagnose_simulated(args.system, args.simulate or "", seed=args.seed, methods=methods,
                                    epochs=args.epochs)
    else:
        if not args.files:
            raise InvalidInput("diagnose needs flight files (or --system cartpole|robot --simulate ...)")
        model = None
        if args.model:
            from .local_registry import load_model
            model = load_model(args.model)
        if args.register:
            from .references import check_name
            _registry_grid(args.rate)
            check_name(args.register)  # before the work
        from .progress import StageProgress

        with StageProgress("diagnosing") as bar:
            bar.update(0.0, f"reading {len(args.files)} file(s)")
            batch = _read_batch(args.files, args.rate, _topics(args), args.cut)
            flights = batch.flights
            epochs = args.epochs or CRAZYFLIE_TRAINING.epochs
            bar.update(0.05, f"fitting effects and training the KNODEs ({epochs} epochs each), then scoring "
                             f"before and after on {max(1, len(flights) - 1)} flight(s)")
            result, repaired = diagnose_flights(flights, knode=model, methods=methods, epochs=epochs,
                                                return_model=True, system=args.system, mass_kg=args.mass_kg)
        if args.register:
            _register_diagnosed(args, result, repaired, flights, model)
        result["errors"] = batch.errors
    if args.plot:
        save_figure(residual_before_after(result), args.plot, dpi=110)
    print(json.dumps(result, indent=2, default=float) if args.json else
          "\n".join(diagnosis_lead(result)) + format_diagnosis(result))
    if result.get("registered") and not args.json:
        r = result["registered"]
        print(f"registered {r['name']}:{r['version']} (parent {r['parent'] or 'none'})"
              + (f"; warning stored with it: {r['warning']}" if r.get("warning") else ""))
    elif result.get("not_registered") and not args.json:
        print(f"nothing registered: {result['not_registered']}", file=sys.stderr)
    return _batch_status(result.get("errors") or [])


def _register_diagnosed(args, result: dict, repaired, flights, model) -> None:
    """Register the repaired model only when the diagnosis says it improves the held-out flights (its
    ``repair`` verdict, the evaluation's interval rule); ``--force`` registers anyway, with a warning
    stored in the version.  Sets ``result["registered"]`` or ``result["not_registered"]`` (why)."""
    from .local_registry import register_repaired

    verdict = result.get("repair") or {"improves": True, "reason": ""}
    warning = None
    if not verdict["improves"]:
        if not args.force:
            result["not_registered"] = (f"the repair does not improve the held-out flights ({verdict['reason']}); "
                                        "--force registers it anyway")
            return
        warning = f"registered with --force although the repair does not improve held-out flights: {verdict['reason']}"
    result["registered"] = register_repaired(args.register, repaired, flights, result,
                                             epochs=args.epochs or CRAZYFLIE_TRAINING.epochs,
                                             parent=model.meta.get("ref") if model else None, warning=warning)
    if warning:
        result["registered"]["warning"] = warning


def diagnosis_lead(result: dict) -> list[str]:
    """The diagnosis' answer and split first, as its page says them (service.web.headline)."""
    from .web.headline import diagnosis_headline, diagnosis_split

    split = diagnosis_split(result)
    lines = [diagnosis_headline(result)]
    if split["fitting"] or split["scored"]:
        lines.append(f"split: fitted on {', '.join(split['fitting']) or '-'}; "
                     f"scored on {', '.join(split['scored']) or '-'}"
                     + (f" ({split['text']})" if split["text"] else ""))
    elif split["text"]:
        lines.append(f"split: {split['text']}")
    return lines + [""]


def format_report(report: dict) -> str:
    """An evaluation report (evaluate_flights' JSON) as a text table: per-flight and median MSE (x 1e-3) per method
    and the share of the flight outside the model's training envelope, then the improvements in %, the prediction
    check of each flight (KNODE vs prior one-step innovations), the thrust-axis calibration of each flight
    (Crazyflie prior), then a warning per flight that differs from the training
    flight (vehicle, sensor rates, attitude source).
    """
    methods = list(report["median"])
    prior = f" ({report['system']} prior)" if report.get("system") else ""
    lines = headline_lines(report) + _yardstick_lines(report, prior)
    lines += [f"The paper's score (paper_sg), model {report['model']}{prior}: MSE over [p, v, a] vs "
              "Savitzky-Golay references (x 1e-3)",
             f"{'flight':<28}" + "".join(f"{m:>12}" for m in methods) + "  outside envelope"]
    for f in report["flights"]:
        if f["excluded"]:
            lines.append(f"{f['flight']:<28}  excluded: {f['reason']}")
        else:
            lines.append(f"{f['flight']:<28}" + "".join(f"{f['mse'][m] * 1e3:>12.3f}" for m in methods)
                         + f"  {_envelope_text(f.get('envelope'))}")
    lines.append(f"{'median':<28}" + "".join(f"{report['median'][m] * 1e3:>12.3f}" for m in methods))
    for key, value in report["improvement_pct"].items():
        lines.append(f"improvement {key}: {value:+.1f} % (median MSE)")
    outside = report.get("outside_training_envelope")
    if outside:
        lines.append(f"outside what this model saw in training: {', '.join(outside)}")
    checks = {f["flight"]: f["prediction_check"] for f in report["flights"] if f.get("prediction_check")}
    if checks:   # estimators.evaluate.prediction_check: no ground truth, only the flight's own measurements
        lines.append("one-step position innovations, KNODE / prior (above 1: the KNODE predicts the flight worse): "
                     + ", ".join(f"{name} {c['innovation_ratio']:.2f}" for name, c in checks.items()))
    worse = report.get("knode_predicts_worse")
    if worse:
        lines.append(f"do not trust the KNODE on: {', '.join(worse)} (it predicts these flights worse than its prior)")
    for base, names in (report.get("knode_clearly_worse") or {}).items():
        # estimators.evaluate.gain_interval: the gain's 95 % block-bootstrap interval lies below 0
        lines.append(f"KNODE-{base.upper()} worse than {base.upper()} beyond the flight's own variability (95 % "
                     f"interval of the gain below 0) on: {', '.join(names) or 'no flight'}")
    recommended = report.get("recommended")
    if recommended:   # estimators.evaluate.recommended_model per flight, scored as one estimator
        scores = ", ".join(f"{base.upper()} {value * 1e3:.3f} ({recommended['improvement_pct'][base]:+.1f} % vs prior)"
                           for base, value in recommended["median"].items())
        prior_on = ", ".join(recommended["prior_on"]) or "none"
        lines.append(f"recommended estimate (the KNODE's; the prior's where the check flags the flight): median "
                     f"{scores}; prior's used on: {prior_on}")
    axes = {f["flight"]: f["thrust_axis_offset_deg"] for f in report["flights"] if f.get("thrust_axis_offset_deg")}
    if axes:   # the calibration the prior's attitude input got (models.thrust_axis)
        lines.append("thrust axis vs mocap frame (deg, x/y): "
                     + ", ".join(f"{name} {x:+.1f}/{y:+.1f}" for name, (x, y) in axes.items()))
    gains = {f["flight"]: f["thrust_gain"] for f in report["flights"] if f.get("thrust_gain")}
    if gains:   # the thrust gain the prior got per flight (models.thrust_gain)
        lines.append("thrust gain vs the prior's thrust map (mocap / map): "
                     + ", ".join(f"{name} {gain:.3f}" for name, gain in gains.items()))
    heating = {f["flight"]: f["heating_thrust_loss_pct"] for f in report["flights"]
               if f.get("heating_thrust_loss_pct") is not None}
    if heating:   # the motors' heating the prior's thrust carried (models.motor_heating)
        lines.append("largest thrust loss to motor heating over the flight (%): "
                     + ", ".join(f"{name} {loss:.1f}" for name, loss in heating.items()))
    for f in report["flights"]:   # another vehicle, sensor rate or attitude source than the training flight's
        lines += [f"WARNING {f['flight']}: {warning}" for warning in f.get("warnings") or []]
    return "\n".join(lines)


def _yardstick_lines(report: dict, prior: str) -> list[str]:
    """The report's opening lines: whether the model learned anything, the mocap-gap score (per flight, the
    median and the KNODE's gain with its interval), then the fast reference with the onboard estimate; each
    yardstick says what it measures.  Rows are indented so a flight's first line stays its paper_sg row."""
    import statistics

    lines = []
    if report.get("learned_note"):
        lines.append(f"NOTE {report['model']}: {report['learned_note']}")
    definitions = report.get("yardstick_definitions") or {}
    scored = [f for f in report["flights"] if not f.get("excluded") and f.get("yardsticks")]
    if not scored:
        return lines
    head = report.get("headline") or {}
    gapped = [f for f in scored if not f["yardsticks"]["mocap_gaps"].get("skipped")]
    plan = scored[0]["yardsticks"]["mocap_gaps"]
    lines.append(f"Mocap gaps (headline), model {report['model']}{prior}: mocap hidden {plan['gap_s']:g} s every "
                 f"{plan['every_s']:g} s after the first {plan['start_s']:g} s; position RMSE in the gaps (m)")
    if definitions.get("mocap_gaps"):
        lines.append(f"  measures {_the(definitions['mocap_gaps'])}")
    methods = sorted({m for f in gapped for m in f["yardsticks"]["mocap_gaps"]["rmse_m"]}, key=_method_order)
    keys = sorted({k for f in gapped for k in f["yardsticks"]["mocap_gaps"]["gain_pct"]},
                  key=lambda k: _method_order(k.split("_vs_")[0]))
    if gapped:
        lines.append(f"  {'flight':<26}" + "".join(f"{m:>11}" for m in methods) + "".join(
            f"  {k.replace('_vs_', ' vs '):>28}" for k in keys))
    for f in scored:
        gaps = f["yardsticks"]["mocap_gaps"]
        if gaps.get("skipped"):
            lines.append(f"  {f['flight']:<26}  no gap score: {gaps['skipped']}")
            continue
        row = "".join(f"{gaps['rmse_m'][m]:>11.4f}" if m in gaps["rmse_m"] else f"{'-':>11}" for m in methods)
        for key in keys:
            gain, interval = gaps["gain_pct"].get(key), (gaps.get("gain_interval_pct") or {}).get(key)
            text = "-" if gain is None else f"{gain:+.1f} %" + (
                f" [{interval[0]:+.1f}, {interval[1]:+.1f}]" if interval else " [too few gaps]")
            row += f"  {text:>28}"
        lines.append(f"  {f['flight']:<26}" + row + f"  ({gaps['gaps']} gaps)")
    if gapped:
        lines.append(f"  {'median':<26}" + "".join(f"{head.get('median_rmse_m', {}).get(m, float('nan')):>11.4f}"
                                                  for m in methods))
    for key in keys:
        worse = (head.get("flights_worse_names") or {}).get(key) or []
        median = head["median_gain_pct"].get(key)
        lines.append(f"  {key.replace('_vs_', ' vs ')}: median gain "
                     f"{'-' if median is None else format(median, '+.1f')} % (mean "
                     f"squared gap error), better on {head['flights_better'][key]} of {head['flights_with_gaps']} "
                     f"flights, worse beyond the 95 % interval on {len(worse)}"
                     + (f": {', '.join(worse)}" if worse else ""))
    fast = scored[0]["yardsticks"]["fast_reference"]
    lines.append(f"Fast reference: velocity RMSE (m/s) vs a {fast['window_s']:g}-s derivative of the raw mocap, "
                 "outside the gaps")
    if definitions.get("fast_reference"):
        lines.append(f"  measures {_the(definitions['fast_reference'])}")
    methods = sorted({m for f in scored for m in f["yardsticks"]["fast_reference"]["velocity_rmse_m_s"]},
                     key=_method_order)
    lines.append(f"  {'flight':<26}" + "".join(f"{m:>11}" for m in methods))
    for f in scored:
        velocity = f["yardsticks"]["fast_reference"]["velocity_rmse_m_s"]
        lines.append(f"  {f['flight']:<26}" + "".join(f"{velocity[m]:>11.4f}" if m in velocity else f"{'-':>11}"
                                                      for m in methods))
    medians = {m: float(statistics.median([f["yardsticks"]["fast_reference"]["velocity_rmse_m_s"][m] for f in scored
                                   if m in f["yardsticks"]["fast_reference"]["velocity_rmse_m_s"]])) for m in methods}
    lines.append(f"  {'median':<26}" + "".join(f"{medians[m]:>11.4f}" for m in methods))
    if definitions.get("paper_sg"):
        lines.append(f"The paper's score measures {_the(definitions['paper_sg'])}")
    return lines


def _the(sentence: str) -> str:
    """A yardstick's definition as the object of "measures": with its article."""
    return sentence if sentence.startswith("the ") else f"the {sentence}"


def _method_order(method: str) -> int:
    """Methods in the order of EVALUATION_METHODS (unknown ones last)."""
    return EVALUATION_METHODS.index(method) if method in EVALUATION_METHODS else len(EVALUATION_METHODS)


def headline_lines(report: dict) -> list[str]:
    """The answer first (service.web.headline, as the report page says it): the sentence of each KNODE
    against its prior, what the yardstick measures, and per flight the gain with its 95 % interval; then a
    blank line before the tables and the details."""
    from .web.headline import evaluation_headline

    head = evaluation_headline(report)
    lines = [pair["sentence"] for pair in head["pairs"]] or [head["sentence"]]
    lines.append(f"  (yardstick: {head['measures']})")
    for pair in head["pairs"]:
        label = f"{pair['knode'].upper()} gain over {pair['prior'].upper()} (%)"
        lines.append(f"{'flight':<28}{label:>30}  95 % interval")
        for r in pair["rows"]:
            ci = r["interval_pct"]
            beyond = "  WORSE beyond its interval" if ci and ci[1] < 0 else ""
            lines.append(f"{r['flight']:<28}{r['gain_pct']:>+30.1f}  "
                         + (f"[{ci[0]:+.1f}, {ci[1]:+.1f}]" if ci else "-") + beyond)
    return lines + [""]


def _envelope_text(envelope: dict | None) -> str:
    """'12 % (vx, az) OUTSIDE', '40 % (vbat), residual unaffected', '0 %', or '-' for a model stored
    without an envelope."""
    if not envelope:
        return "-"
    states = ", ".join(envelope["states_outside"])
    if envelope["outside_training_envelope"]:
        return f"{100 * envelope['fraction_outside']:.0f} % ({states}) OUTSIDE"
    if states and envelope.get("residual_checked"):   # outside the box where the residual does not care
        return f"{100 * envelope['fraction_outside']:.0f} % ({states}), residual unaffected"
    return f"{100 * envelope['fraction_outside']:.0f} %"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors, like every other learnest error (the usage is one --help away)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every `learnest` subcommand; each sets `func`, the function that runs it."""
    parser = _Parser(prog="learnest", description="Learning-enhanced state estimation "
                                     "for Crazyflie flight logs (LEARNEST).")
    sub = parser.add_subparsers(dest="command", required=True)

    rep = sub.add_parser("reproduce", help="reproduce Table I of the paper on simulated systems")
    rep.add_argument("--task", choices=["cartpole", "robot"], required=True)
    rep.add_argument("--seeds", type=_positive_int, default=15)
    rep.add_argument("--first-seed", type=_whole_number, default=0, metavar="S",
                     help="draw seeds S, S+1, ... instead of Table I's 0, 1, ... (a check on fresh seeds)")
    rep.add_argument("--json", metavar="FILE", type=_new_file, help="also write the results as JSON")
    rep.add_argument("--samples", type=_positive_int, default=None,
                     help="evaluation trajectory length in samples (default: the paper's)")
    rep.add_argument("--epochs", type=_positive_int, default=None, help="training epochs (default: the paper's)")
    rep.add_argument("--horizon", type=_positive_int, default=MHE_HORIZON,
                     help=f"MHE horizon N (default {MHE_HORIZON})")
    rep.add_argument("--workers", type=_positive_int, default=1, help="processes to spread the seeds over")
    rep.add_argument("--observer-rounds", type=int, choices=range(0, 11), default=None, metavar="K",
                     help="observer -> train rounds of the KNODE rows, 0-10 (default: the task's, "
                          "models/presets.py PAPER_OBSERVER; 0 is the paper's Algorithm 1)")
    rep.add_argument("--observer", choices=("filter", "smoother", "joint"), default=None,
                     help="pre-training observer of the KNODE rows (default: the task's, PAPER_OBSERVER); 'joint' "
                          "fits the record's states and the residual together (estimators/joint_training.py)")
    rep.set_defaults(func=_reproduce)

    ing = sub.add_parser("ingest", help="read flight logs, normalise them and check their quality")
    ing.add_argument("files", nargs="+", help="log files or folders (a folder's logs are read; NanoBench "
                                              "*_metadata.yaml and crazyswarm2 infoNNN.yaml are read with their logs)")
    ing.add_argument("--json", action="store_true")
    ing.add_argument("--rate", type=_positive_float, default=100.0, help="grid rate in Hz (default 100)")
    ing.add_argument("--strict", action="store_true", help="exit with status 1 if any flight fails the quality checks")
    _add_topic_arguments(ing)
    _add_cut_argument(ing)
    ing.set_defaults(func=_ingest)

    tr = sub.add_parser("train", help="train a KNODE on one flight (Algorithm 1) or on several flights of one "
                                      "vehicle (one pooled loss, whole flights held out) and register it as the next "
                                      "version of NAME (the flights are stored too, as by an upload)")
    tr.add_argument("files", nargs="+", metavar="FILE|FOLDER",
                    help="the log file(s) of one flight, or of several flights, or folders of them")
    tr.add_argument("--validate", nargs="+", metavar="FILE", default=None,
                    help="log files of flights held out whole to choose the kept epoch (default with several flights: "
                         "one in five; one flight alone is validated on time blocks of it)")
    tr.add_argument("--name", required=True, help="registered model name")
    tr.add_argument("--epochs", type=_positive_int, default=None,
                    help=f"default {CRAZYFLIE_TRAINING.epochs} (Sec. V-C)")
    tr.add_argument("--json", action="store_true")
    tr.add_argument("--rate", type=_positive_float, default=100.0, help="grid rate in Hz (the registry keeps 100)")
    tr.add_argument("--include-bad", action="store_true",
                    help="train even on flights that fail the quality checks (of several, they are left out otherwise)")
    tr.add_argument("--strict", action="store_true",
                    help="stop with status 1 at the first file that cannot be read, training nothing (without it, such "
                         "files are named and the model is trained on the others)")
    tr.add_argument("--system", default="quadrotor", choices=["quadrotor", "crazyflie"],
                    help="the prior: the paper's kinematic chain (default) or the Crazyflie driven by its motors "
                         "and battery (needs motor PWM and battery voltage in the log)")
    _add_topic_arguments(tr)
    _add_cut_argument(tr)
    tr.set_defaults(func=_train)

    ev = sub.add_parser("evaluate", help="run UKF/MHE/KNODE-UKF/KNODE-MHE on flights and score them")
    ev.add_argument("files", nargs="*")
    ev.add_argument("--model", metavar="REF", type=_model_ref,
                    help="a registered model: NAME (its latest ready version), NAME:VERSION or NAME@ALIAS "
                         "(required unless --new)")
    ev.add_argument("--methods", default=",".join(EVALUATION_METHODS),
                    help=f"any of {', '.join(EVALUATION_METHODS)} (default: all; onboard is the vehicle's own "
                         "estimate, scored where the log carries it)")
    ev.add_argument("--json", action="store_true")
    ev.add_argument("--plot", metavar="PNG", type=_new_file,
                    help="write the per-flight MSE figure (prior vs KNODE, one line per flight; box plots from "
                         "10 flights on)")
    ev.add_argument("--horizon", type=_positive_int, default=MHE_HORIZON, help="MHE horizon N")
    ev.add_argument("--sg-window", type=_sg_window, default=SG_WINDOW, metavar="SAMPLES",
                    help=f"Savitzky-Golay window of the reference states, samples (default {SG_WINDOW}, the "
                         "paper's, about 1.5 s at 100 Hz; it clips the velocity peaks of fast manoeuvres: "
                         "shorter follows them)")
    ev.add_argument("--rate", type=_positive_float, default=100.0)
    ev.add_argument("--include-bad", action="store_true", help="also score flights that fail quality checks")
    ev.add_argument("--system", default=None, choices=["quadrotor", "crazyflie"],
                    help="check that the model's prior is this one (a model always runs with its own prior)")
    ev.add_argument("--new", action="store_true", help="evaluate every stored flight that has no result yet "
                    "for the registry model holding --alias (one scheduler round, for cron)")
    ev.add_argument("--alias", default=PRODUCTION_ALIAS,
                    help=f"with --new: the alias to evaluate (default {PRODUCTION_ALIAS})")
    ev.add_argument("--no-store", dest="store", action="store_false",
                    help="only compute: do not store the flights and the evaluation in the registry (by default "
                         "they are, so the evaluation shows in the web UI and `learnest export` can write it)")
    ev.add_argument("--export", metavar="PATH", type=_export_path,
                    help="also write the state estimates; the format follows the suffix: .csv, .parquet, .mcap")
    _add_gap_arguments(ev)
    _add_topic_arguments(ev)
    _add_cut_argument(ev)
    ev.set_defaults(func=_evaluate)

    exp = sub.add_parser("export", help="write a stored evaluation's state estimates (every method and flight, "
                                        "with the reference) as CSV, Parquet or MCAP (Foxglove)")
    exp.add_argument("evaluation_id", type=_positive_int, metavar="EVALUATION_ID")
    exp.add_argument("-o", "--output", required=True, type=_new_file, metavar="PATH")
    exp.add_argument("--format", choices=["csv", "parquet", "mcap"], default=None,
                     help="default: from the suffix of PATH (.csv, .parquet, .mcap)")
    exp.add_argument("--flight", type=_positive_int, default=None, metavar="ID",
                     help="only this flight (default: every scored flight)")
    exp.set_defaults(func=_export)

    fl = sub.add_parser("flights", help="the flights stored in the registry (LEARNEST_HOME)")
    fl_sub = fl.add_subparsers(dest="action", required=True)
    fl_list = fl_sub.add_parser("list", help="stored flights by id")
    fl_list.add_argument("--q", "--search", dest="q", metavar="TEXT", help="only names containing TEXT")
    fl_list.add_argument("--json", action="store_true")
    fl_list.set_defaults(func=_flights_list)

    mo = sub.add_parser("models", help="the registered models (LEARNEST_HOME)")
    mo_sub = mo.add_subparsers(dest="action", required=True)
    mo_list = mo_sub.add_parser("list", help="registered models with versions and aliases")
    mo_list.add_argument("--q", "--search", dest="q", metavar="TEXT", help="only names containing TEXT")
    mo_list.add_argument("--json", action="store_true")
    mo_list.set_defaults(func=_models_list)
    mo_show = mo_sub.add_parser("show", help="NAME: its versions; NAME:N or NAME@ALIAS: that version with its "
                                             "metrics, lineage and evaluations")
    mo_show.add_argument("ref", type=_model_ref, metavar="REF")
    mo_show.add_argument("--json", action="store_true")
    mo_show.set_defaults(func=_models_show)

    al = sub.add_parser("alias", help="move a model's aliases")
    al_sub = al.add_subparsers(dest="action", required=True)
    al_set = al_sub.add_parser("set", help="point NAME@ALIAS at VERSION (creating or moving the alias)")
    al_set.add_argument("name", type=_name, metavar="NAME")
    al_set.add_argument("version", type=_positive_int, metavar="VERSION")
    al_set.add_argument("alias", type=_name, metavar="ALIAS")
    al_set.add_argument("--json", action="store_true")
    al_set.set_defaults(func=_alias_set)

    srv = sub.add_parser("serve", help="run the HTTP service (uvicorn; OpenAPI docs at /docs)")
    srv.add_argument("--host", default="127.0.0.1")
    srv.add_argument("--port", type=int, default=8000)
    srv.add_argument("--workers", type=_positive_int, default=1, help="uvicorn worker processes")
    srv.add_argument("--dask", metavar="URL", help="run jobs on a Dask scheduler (tcp://host:port, or 'local' "
                     "for a LocalCluster) instead of the local process pool")
    for option, (kind, text) in SERVE_LIMITS.items():
        srv.add_argument("--" + option.replace("_", "-"), type=kind, default=None,
                         help=f"{text}; env LEARNEST_{option.upper()}")
    srv.set_defaults(func=_serve)

    dia = sub.add_parser("diagnose", help="trace the residual to named physical effects, add them, "
                                          "report the error before and after")
    dia.add_argument("files", nargs="*",
                     help="flight log files (Crazyflie), in order: " + DIAGNOSIS_SPLIT_RULE.replace("%", "%%"))
    dia.add_argument("--system", default=None, choices=["quadrotor", "crazyflie", "cartpole", "robot"],
                     help="the prior diagnosed (default: --model's prior, else quadrotor)")
    dia.add_argument("--mass-kg", type=_positive_float, default=None,
                     help="the vehicle's declared mass, kg (crazyflie; default: the log's own, e.g. a crazyswarm2 "
                          "info*.yaml): a payload is then reported as a mass, not a thrust gain")
    dia.add_argument("--force", action="store_true",
                     help="with --register: register even when the repair does not improve held-out flights "
                          "(a warning is stored in the version)")
    dia.add_argument("--simulate", metavar="NAME=VALUE,...", default=None,
                     help="simulated systems: the true system's parameters/effects (hidden from the diagnosis)")
    dia.add_argument("--seed", type=int, default=0)
    dia.add_argument("--model", metavar="REF", type=_model_ref,
                     help="a registered KNODE to analyse: NAME, NAME:VERSION or NAME@ALIAS (default: train one "
                          "on the fitting flight)")
    dia.add_argument("--register", metavar="NAME", help="register the repaired model (flight files only) as the "
                     "next version of NAME, with --model's version as its parent")
    dia.add_argument("--methods", default="ukf,knode-ukf", help="estimators scored before and after")
    dia.add_argument("--epochs", type=_positive_int, default=None)
    dia.add_argument("--json", action="store_true")
    dia.add_argument("--plot", metavar="PNG", type=_new_file,
                     help="residual over time and held-out error before/after (linear axes)")
    dia.add_argument("--rate", type=_positive_float, default=100.0)
    _add_topic_arguments(dia)
    _add_cut_argument(dia)
    dia.set_defaults(func=_diagnose)

    thr = sub.add_parser("thrust-map", help="identify the Crazyflie thrust map (body-z specific force from motor PWM, "
                                            "battery and attitude) on some flights and score it on others")
    thr.add_argument("--fit", nargs="+", metavar="FILE", help="flight logs (or folders) to fit on")
    thr.add_argument("--score", nargs="+", metavar="FILE",
                     help="flight logs (or folders) to score on, held out whole")
    thr.add_argument("--bench", metavar="CSV", help="a bench calibration of one motor instead of flights: columns "
                     "thrust_n (N) or thrust_g, and pwm, rpm or omega_rad_s, optionally vbat (V)")
    thr.add_argument("--mass-kg", type=_positive_float, default=None,
                     help="with --bench: the vehicle's mass, kg, for the prior's effective mass")
    thr.add_argument("--json", action="store_true")
    thr.add_argument("--rate", type=_positive_float, default=100.0, help="grid rate in Hz (default 100)")
    thr.set_defaults(func=_thrust_map)

    demo = sub.add_parser("demo", help="ingest, train on one flight and evaluate the others, for a folder")
    demo.add_argument("folder")
    demo.add_argument("--train", help="name of the training flight (default: the first clean one)")
    demo.add_argument("--name", default="demo", help="registered model name (each run adds a version)")
    demo.add_argument("--methods", default=",".join(EVALUATION_METHODS))
    demo.add_argument("--plot", metavar="PNG", type=_new_file, default=None)
    demo.add_argument("--horizon", type=_positive_int, default=MHE_HORIZON)
    demo.add_argument("--rate", type=_positive_float, default=100.0)
    demo.add_argument("--system", default=None, choices=["quadrotor", "crazyflie"],
                      help="the prior to train (default: crazyflie when at least two clean flights carry motor PWM "
                           "and battery voltage, else the kinematic quadrotor)")
    demo.set_defaults(func=_demo)
    _fill_help(parser)
    return parser


# Help of the arguments defined above without one (kept here, in one block, so the definitions stay short);
# tests/test_cli_help.py walks the parser and fails on any argument still without help.
JSON_HELP = "print the result as JSON instead of text"
HELP = {
    ("reproduce", "--task"): "the simulated system of Table I: cartpole or robot",
    ("reproduce", "--seeds"): "how many seeds (random systems and noise) to average over (default 15, the paper's)",
    ("evaluate", "files"): "flight log files or folders to score the model on (not with --new)",
    ("evaluate", "--methods"): f"comma-separated estimators to run (default {','.join(METHODS)})",
    ("evaluate", "--rate"): "grid rate in Hz (default 100; the registry keeps 100, other rates need --no-store)",
    ("export", "evaluation_id"): "the stored evaluation (its id, as `learnest evaluate` prints it)",
    ("export", "--output"): "the file to write; its suffix picks the format unless --format is given",
    ("models show", "ref"): "NAME, NAME:VERSION or NAME@ALIAS",
    ("alias set", "name"): "the registered model",
    ("alias set", "version"): "the version the alias points to (must be ready)",
    ("alias set", "alias"): "the alias to create or move, e.g. production",
    ("serve", "--host"): "address to listen on (default 127.0.0.1: this machine only)",
    ("serve", "--port"): "TCP port (default 8000)",
    ("diagnose", "--system"): "the prior diagnosed: quadrotor (kinematic, default), crazyflie (motors and battery: "
                              "the log needs motor PWM and battery voltage), or the simulated cartpole / robot",
    ("diagnose", "--seed"): "random seed of a simulated diagnosis (--simulate)",
    ("diagnose", "--epochs"): "KNODE training epochs before and after the effects "
                              f"(default {CRAZYFLIE_TRAINING.epochs})",
    ("diagnose", "--rate"): "grid rate in Hz (default 100; --register needs 100)",
    ("demo", "folder"): "a folder of flight logs (e.g. sample_logs)",
    ("demo", "--methods"): f"comma-separated estimators to run (default {','.join(METHODS)})",
    ("demo", "--plot"): "also write the per-flight MSE figure (prior vs KNODE) to this PNG",
    ("demo", "--horizon"): f"MHE horizon N (default {MHE_HORIZON})",
    ("demo", "--rate"): "grid rate in Hz (the registry keeps 100)",
}


def subcommands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(path, parser) of ``parser`` and of every subcommand under it, depth first ("models show")."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from subcommands(child, (*path, name))


def _fill_help(parser: argparse.ArgumentParser) -> None:
    """Give the arguments defined without help their text from `HELP` (a --json flag: `JSON_HELP`)."""
    for path, sub in subcommands(parser):
        for action in sub._actions:
            if action.help:
                continue
            name = action.option_strings[-1] if action.option_strings else action.dest
            if name == "--json" and action.nargs == 0:
                action.help = JSON_HELP
            else:
                action.help = HELP.get((" ".join(path), name), action.help)


# commands that only read or move registry rows: no torch, no worker set-up
REGISTRY_COMMANDS = (_flights_list, _models_list, _models_show, _alias_set)


def _given_paths(args) -> list[str]:
    """The input files and folders a command was given (FILE..., --fit, --score, demo's FOLDER)."""
    paths = [*(getattr(args, "files", None) or []), *(getattr(args, "fit", None) or []),
             *(getattr(args, "score", None) or [])]
    return paths + ([args.folder] if getattr(args, "folder", None) else [])


def main(argv=None) -> int:
    """Run the `learnest` command line on `argv` (default: sys.argv[1:]) and return the exit status.

    0 on success or --help; 2 for a bad argument or a LearnestError (printed on one line, no traceback);
    otherwise the subcommand's status (e.g. `ingest --strict` returns 1 when a flight fails the quality checks).
    """
    _command_started[0] = time.perf_counter()
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # a bad argument (argparse printed usage and why) or --help
        return int(stop.code or 0)
    if args.func is _export and not args.format:  # the format is checked before any work, like the other arguments
        from learnest.estimators.export import format_of

        try:
            format_of(args.output)
        except InvalidInput as err:
            print(f"learnest export: error: {err} (or give --format)", file=sys.stderr)
            return 2
    given = _given_paths(args)
    missing = [p for p in given if not Path(p).expanduser().exists()]
    # nothing there at all: said before any import, progress bar or stored row (a typo costs nothing); some
    # there: the batch reads them and names each missing one with the other unreadable files
    if missing and (len(missing) == len(given) or getattr(args, "strict", False)):
        print(f"learnest {args.command}: error: no such file or folder: {', '.join(missing)}", file=sys.stderr)
        return 2
    if args.func not in (_ingest, _serve, _export) + REGISTRY_COMMANDS:  # the rest run the networks here
        from .jobs.executors import init_worker

        init_worker()  # the networks are tiny: extra threads only add contention
    try:
        return args.func(args)
    except LearnestError as err:  # bad input, unknown model, failed training: one clear line, no traceback
        print(f"learnest: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: the command cleaned up on the way out (train: nothing registered)
        print("learnest: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
