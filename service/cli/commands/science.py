"""The handlers of the subcommands that read flights and run the science: ingest, train, evaluate,
diagnose, thrust-map, reproduce, demo."""
from __future__ import annotations

import json
import shlex
import sys
import time
from pathlib import Path

from learnest.workflows.vocabulary import (
    CRAZYFLIE_TRAINING,
    EVALUATION_METHODS,
    EvaluationSettings,
    InvalidInput,
    parse_methods,
)

from ..arguments import _export_format, _topics, evaluation_settings
from ..formatting import _gap_lines, diagnosis_lead, format_report, format_trained
from .common import _batch_status, _command_started, _home, _read_batch


def _ingest(args) -> int:
    from learnest.workflows.files import summary

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
    """Store the flights and register the next version of NAME in the registry (service.local)."""
    from learnest.workflows.files import format_errors

    from ...local import UnreadableFile, train
    from ..progress import StageProgress

    try:   # the arguments were checked before this import (cli.usage)
        with StageProgress(f"training {args.name}") as bar:
            out = train(args.files, args.name, epochs=args.epochs, include_bad=args.include_bad,
                        progress=bar.progress, system=args.system, on_stage=bar.on_stage, **_topics(args),
                        cut=args.cut, validate=args.validate, strict=args.strict,
                        group_by=args.group_by, noise=args.noise, ensemble=args.ensemble)
    except UnreadableFile as err:   # --strict: the first unreadable file stops the command, nothing trained
        print(f"learnest: {err}; nothing was trained (--strict)", file=sys.stderr)
        return 1
    out["command_seconds"] = time.perf_counter() - _command_started[0]
    for line in format_errors(out["errors"]):
        print(f"learnest: {line}", file=sys.stderr)
    print(json.dumps(out, indent=2) if args.json else format_trained(out))
    return _batch_status(out["errors"])


def _evaluate(args) -> int:
    """Evaluate a registered model on flight files: stored in the registry (flights and evaluation, as the
    web UI's), or with --no-store only computed here."""
    from ...local import load_model
    from ...local.figures import evaluation_summary, save_figure

    if args.new:
        return _evaluate_new(args)
    settings = evaluation_settings(args)   # checked, with the rest, by cli.usage
    model = load_model(args.model)
    if args.system and args.system != model.system.name:
        raise InvalidInput(f"{args.model} was trained with the {model.system.name!r} prior, not {args.system!r}")
    ref = model.meta.get("ref", args.model)  # name:version, whatever form was asked for
    report = (_evaluate_stored if args.store else _evaluate_here)(args, model, ref, settings)
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


def _evaluate_stored(args, model, ref: str, settings: EvaluationSettings) -> dict:
    """Store the flights and the evaluation in the registry (service.local.evaluate)."""
    from learnest.workflows.files import format_errors

    from ...local import evaluate, export
    from ..progress import StageProgress

    with StageProgress("evaluating") as bar:
        report = evaluate(args.files, ref, settings, progress=bar.progress, on_stage=bar.on_stage, **_topics(args),
                          cut=args.cut)
    for line in format_errors(report.get("errors") or []):
        print(f"learnest: {line}", file=sys.stderr)
    if args.export and report["flights_scored"]:
        export(report["evaluation_id"], args.export, _export_format(args.export))
    return report


def _evaluate_here(args, model, ref: str, settings: EvaluationSettings) -> dict:
    """Evaluate in this process and store nothing (--no-store); --export writes the estimates kept on the way."""
    from learnest.workflows.files import write_estimates
    from learnest.workflows.flights import score_flights

    from ..progress import StageProgress

    batch = _read_batch(args.files, args.rate, _topics(args), args.cut)
    flights = batch.flights
    kept: list = []
    with StageProgress("evaluating") as bar:
        done = [0]

        def flight_done(_flight) -> None:
            done[0] += 1
            bar.update(done[0] / len(flights), f"{done[0]}/{len(flights)} flight(s) done")

        report = score_flights(model, flights, settings, progress=flight_done,
                               on_estimates=(lambda _i, e: kept.append(e)) if args.export else None).to_dict()
    report["model"] = ref
    report["errors"] = batch.errors
    if args.export and kept:
        write_estimates(kept, args.export, _export_format(args.export))
    return report


def _evaluate_new(args) -> int:
    """One scheduler round (for cron): evaluate every stored flight without a result for name@alias."""
    from ...local import evaluate_new_once

    rounds = evaluate_new_once(args.alias, evaluation_settings(args))
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


def _diagnose(args) -> int:
    from learnest.workflows.diagnosis import diagnose_flights, diagnose_simulated, format_diagnosis

    from ...local.figures import residual_before_after, save_figure

    methods = parse_methods(args.methods)   # the arguments were checked by cli.usage
    if args.simulate is not None or args.system in ("cartpole", "robot"):
        result = diagnose_simulated(args.system, args.simulate or "", seed=args.seed, methods=methods,
                                    epochs=args.epochs)
    else:
        model = None
        if args.model:
            from ...local import load_model
            model = load_model(args.model)
        from ..progress import StageProgress

        with StageProgress("diagnosing") as bar:
            bar.update(0.0, f"reading {len(args.files)} file(s)")
            batch = _read_batch(args.files, args.rate, _topics(args), args.cut)
            flights = batch.flights
            epochs = args.epochs or CRAZYFLIE_TRAINING.epochs
            result, repaired = diagnose_flights(flights, knode=model, methods=methods, epochs=epochs,
                                                return_model=True, system=args.system, mass_kg=args.mass_kg,
                                                on_stage=_diagnosis_stages(bar))
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


def _diagnosis_stages(bar):
    """``on_stage(name, fraction)`` for `diagnose_flights` drawing on ``bar`` (a `StageProgress`): a bar shows
    every tick ("... (epoch 3/20)"); a plain log one line per kind of stage (`diagnosis_stages.stage_kind`).
    Reading the files took the first 5 %."""
    from learnest.workflows.diagnosis_stages import stage_kind

    def on_stage(name: str, fraction: float | None) -> None:
        bar.update(None if fraction is None else 0.05 + 0.95 * fraction,
                   name if bar.draws_bar else stage_kind(name))

    return on_stage


def _register_diagnosed(args, result: dict, repaired, flights, model) -> None:
    """Register the repaired model only when the diagnosis says it improves the held-out flights (its
    ``repair`` verdict, the evaluation's interval rule); ``--force`` registers anyway, with a warning
    stored in the version.  Sets ``result["registered"]`` or ``result["not_registered"]`` (why)."""
    from ...local import register_repaired

    verdict = result.get("repair") or {"improves": False, "reason": "the diagnosis gave no verdict on them"}
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


def _thrust_map(args) -> int:
    from learnest.workflows.thrust_map import (
        bench_thrust_map_report,
        format_bench_map,
        format_thrust_map,
        thrust_map_report,
    )

    if args.bench:   # --bench or --fit and --score: checked by cli.usage
        report = bench_thrust_map_report(args.bench, args.mass_kg)
        print(json.dumps(report, indent=2) if args.json else format_bench_map(report))
        return 0
    sets: dict[str, list] = {}
    errors: list[dict] = []
    for role, given in (("fit", args.fit), ("score", args.score)):
        try:
            batch = _read_batch(given, args.rate)
        except InvalidInput as err:
            raise InvalidInput(f"{err} (--{role})") from None
        sets[role], errors = batch.flights, errors + batch.errors
    from ..progress import StageProgress

    with StageProgress("thrust map") as bar:
        def stage(name: str, done: int, total: int) -> None:
            bar.update(done / total if total else None, name)

        report = thrust_map_report(sets["fit"], sets["score"], progress=stage)
    if args.json:
        report["errors"] = errors
    print(json.dumps(report, indent=2) if args.json else format_thrust_map(report))
    return _batch_status(errors)


def _reproduce(args) -> int:
    from learnest.workflows.table1 import ReproduceSettings, format_table, reproduce

    settings = ReproduceSettings(task=args.task, eval_samples=args.samples, epochs=args.epochs, horizon=args.horizon,
                                 observer_rounds=args.observer_rounds, observer=args.observer, noise=args.noise,
                                 arrival_update=args.arrival_update)
    from ..progress import StageProgress

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


def _this_command() -> str:
    """`learnest` as the user can type it again: the path they ran (`.venv/bin/learnest`) when a bare
    `learnest` would not find this one (the venv not activated)."""
    import shutil

    ran = Path(sys.argv[0])
    if ran.name != "learnest" or not ran.is_file():
        return "learnest"
    found = shutil.which("learnest")
    return "learnest" if found and Path(found).resolve() == ran.resolve() else shlex.quote(sys.argv[0])


def _demo(args) -> int:
    """ingest -> train on one flight -> evaluate on every other flight of a folder."""
    from learnest.workflows.files import IngestError, detect
    from learnest.workflows.flights import evaluate_flights

    from ...local import load_model, train
    from ...local.figures import evaluation_summary, save_figure
    from ..progress import StageProgress

    folder = Path(args.folder)   # a folder, on the registry's grid, with known methods: checked by cli.usage
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
    from learnest.workflows.learning import driven_flights, prior_for_flights

    # the Crazyflie prior (motors and battery) where two flights or more carry its inputs, as le.KNODE() picks it
    system = args.system or prior_for_flights(clean, least=2)
    pool = driven_flights(clean) if system == "crazyflie" else clean
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
    home = Path(trained["home"]).resolve()
    earlier = trained["version"] - 1
    print(f"registered {trained['ref']} in {home}" + (
        f": another version of {args.name} ({earlier} from earlier runs kept; `learnest models show {args.name}` "
        "lists them, --name picks another model)" if earlier else ""))
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
    # the home spelled out: a server started from another folder, or with another LEARNEST_HOME, finds the model
    print(f"\nnext: LEARNEST_HOME={shlex.quote(str(home))} {_this_command()} serve, then open "
          f"http://127.0.0.1:8000/ui/models/{args.name} (the model, its evaluations, more from the browser)")
    return _batch_status(batch.errors)
