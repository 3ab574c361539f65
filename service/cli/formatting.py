"""The text the `learnest` subcommands print: reports, trained and registered models, diagnoses."""
from __future__ import annotations

from learnest.workflows.vocabulary import EVALUATION_METHODS, GAP_START_S, gain_pct, worse_beyond_interval


def format_report(report: dict) -> str:
    """An evaluation report (evaluate_flights' JSON) as a text table: per-flight and median MSE (x 1e-3) per method
    and the share of the flight outside the model's training envelope, then the improvements in %, the thrust-axis
    calibration of each flight (Crazyflie prior), then a warning per flight that differs from the training
    flight (vehicle, sensor rates, attitude source).  The verdict per flight and the recommended estimate come
    first, with the headline (`headline_lines`).
    """
    methods = list(report["median"])
    prior = f" ({report['system']} prior)" if report.get("system") else ""
    # a model that learned nothing says so before anything else: every number below is then its prior's
    note = [f"NOTE {report['model']}: {report['learned_note']}"] if report.get("learned_note") else []
    lines = note + headline_lines(report) + _yardstick_lines(report, prior)
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
    axes = {f["flight"]: f["thrust_axis_offset_deg"] for f in report["flights"] if f.get("thrust_axis_offset_deg")}
    if axes:   # the calibration the prior's attitude input got (models.crazyflie.thrust_axis)
        lines.append("thrust axis vs mocap frame (deg, x/y): "
                     + ", ".join(f"{name} {x:+.1f}/{y:+.1f}" for name, (x, y) in axes.items()))
    gains = {f["flight"]: f["thrust_gain"] for f in report["flights"] if f.get("thrust_gain")}
    if gains:   # the thrust gain the prior got per flight (models.crazyflie.thrust_gain)
        lines.append("thrust gain vs the prior's thrust map (mocap / map): "
                     + ", ".join(f"{name} {gain:.3f}" for name, gain in gains.items()))
    heating = {f["flight"]: f["heating_thrust_loss_pct"] for f in report["flights"]
               if f.get("heating_thrust_loss_pct") is not None}
    if heating:   # the motors' heating the prior's thrust carried (models.crazyflie.motor_heating)
        lines.append("largest thrust loss to motor heating over the flight (%): "
                     + ", ".join(f"{name} {loss:.1f}" for name, loss in heating.items()))
    for f in report["flights"]:   # another vehicle, sensor rate or attitude source than the training flight's
        lines += [f"WARNING {f['flight']}: {warning}" for warning in f.get("warnings") or []]
    return "\n".join(lines)


def headline_lines(report: dict) -> list[str]:
    """The answer first (`learnest.workflows.headline`, as the report page says it): the sentence of each KNODE
    against its prior, what the yardstick measures, and per flight the gain with its 95 % interval; then a
    blank line before the tables and the details."""
    from learnest.workflows.headline import evaluation_headline

    head = evaluation_headline(report)
    lines = [pair["sentence"] for pair in head["pairs"]] or [head["sentence"]]
    lines.append(f"  (yardstick: {head['measures']})")
    for pair in head["pairs"]:
        label = f"{pair['knode'].upper()} gain over {pair['prior'].upper()} (%)"
        lines.append(f"{'flight':<28}{label:>30}  95 % interval")
        for r in pair["rows"]:
            ci = r["interval_pct"]
            beyond = "  WORSE beyond its interval" if worse_beyond_interval(ci) else ""
            lines.append(f"{r['flight']:<28}{r['gain_pct']:>+30.1f}  "
                         + (f"[{ci[0]:+.1f}, {ci[1]:+.1f}]" if ci else "undecided (no interval)") + beyond)
        if pair["undecided_names"]:
            lines.append(f"  undecided on {pair['undecided']} of {pair['scored']} flights scored: "
                         + "; ".join(pair["undecided_names"]))
    return lines + recommended_lines(report) + [""]


def recommended_lines(report: dict) -> list[str]:
    """The estimate learnest recommends (`estimators.evaluate.recommended_model`), by the verdicts just printed:
    per base estimator, on how many flights the KNODE's, and where the prior's, with the median gap RMSE."""
    recommended = report.get("recommended")
    if not recommended:
        return []
    lines = [f"Recommended estimate: {recommended['rule']}."]
    for base, knode_on in recommended["knode_on"].items():
        prior_on = recommended["prior_on"].get(base) or []
        flights = len(knode_on) + len(prior_on)
        text = (f"  {base.upper()}: the KNODE's on {len(knode_on)} of {flights} flight{'s' if flights != 1 else ''}"
                + (f", the prior's on {', '.join(prior_on)}" if prior_on else ""))
        rmse, prior_rmse = recommended["median_gap_rmse_m"].get(base), recommended["prior_median_gap_rmse_m"].get(base)
        if rmse is not None and prior_rmse is not None:
            text += f"; median gap RMSE {rmse * 1e3:.1f} mm (the prior alone: {prior_rmse * 1e3:.1f} mm)"
        lines.append(text)
    return lines


def _yardstick_lines(report: dict, prior: str) -> list[str]:
    """The report's opening lines: whether the model learned anything, the mocap-gap score (per flight, the
    median and the KNODE's gain with its interval), then the fast reference with the onboard estimate; each
    yardstick says what it measures.  Rows are indented so a flight's first line stays its paper_sg row."""
    import statistics

    lines: list[str] = []
    definitions = report.get("yardstick_definitions") or {}
    scored = [f for f in report["flights"] if not f.get("excluded") and f.get("yardsticks")]
    if not scored:
        return lines
    head = report.get("headline") or {}
    gapped = [f for f in scored if not f["yardsticks"]["mocap_gaps"].get("skipped")]
    plan = scored[0]["yardsticks"]["mocap_gaps"]
    lines.append(f"Mocap gaps (headline), model {report['model']}{prior}: mocap hidden {plan['gap_s']:g} s every "
                 f"{plan['every_s']:g} s after the first {plan.get('start_s', GAP_START_S):g} s; position RMSE in the "
                 "gaps (m)")
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
                f" [{interval[0]:+.1f}, {interval[1]:+.1f}]" if interval else " [no interval]")
            row += f"  {text:>28}"
        lines.append(f"  {f['flight']:<26}" + row + f"  ({gaps['gaps']} gaps)")
    if gapped:
        lines.append(f"  {'median':<26}" + "".join(f"{head.get('median_rmse_m', {}).get(m, float('nan')):>11.4f}"
                                                  for m in methods))
    for key in keys:
        worse = (head.get("flights_worse_names") or {}).get(key) or []
        median = head["median_gain_pct"].get(key)
        counts = {name: (head.get(f"flights_{name}") or {}).get(key)
                  for name in ("better_beyond_interval", "within_interval", "undecided")}
        tally = ""
        if all(isinstance(v, int) for v in counts.values()):   # a report stored before these counts has none
            tally = (f"; better beyond it on {counts['better_beyond_interval']}, within it on "
                     f"{counts['within_interval']}, undecided (no interval) on {counts['undecided']} of "
                     f"{head.get('flights_scored', len(scored))} flights scored")
        lines.append(f"  {key.replace('_vs_', ' vs ')}: median gain "
                     f"{'-' if median is None else format(median, '+.1f')} % (mean "
                     f"squared gap error), better on {head['flights_better'][key]} of "
                     f"{head.get('flights_with_gaps', len(gapped))} "
                     f"flights, worse beyond the 95 % interval on {len(worse)}"
                     + (f": {', '.join(worse)}" if worse else "") + tally)
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


def format_trained(out: dict) -> str:
    """`learnest train`'s text: what was registered, on which flights, and whether the residual learned
    anything that held-out data confirm."""
    from learnest.workflows.learning import NOT_LEARNED

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
    if out.get("residual_scale_note"):
        lines.append(residual_scale_line(out))
    if out.get("skipped_flights"):
        lines.append("left out (failed the quality checks; --include-bad keeps them): "
                     + "; ".join(out["skipped_flights"]))
    if not out["learned"]:
        lines.append(f"NOT LEARNED: {out.get('learned_note') or NOT_LEARNED}")
    elif out.get("prior_validation_loss") and out.get("best_validation_loss") is not None:
        gain = gain_pct(out["prior_validation_loss"], out["best_validation_loss"])
        lines.append(f"learned: the held-out one-step loss is {gain:.1f} % below the prior's")
    elif out.get("learned_note"):
        lines.append(out["learned_note"])
    return "\n".join(lines)


def residual_scale_line(out: dict) -> str:
    """The residual's scale and how it was chosen (or why none was), in one line."""
    return f"residual scale {float(out.get('residual_scale', 1.0)):g}: {out['residual_scale_note']}"


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


def residual_line(residual: dict) -> str:
    """`models show`'s line on what the residual reads and how many members its ensemble has."""
    frame = {"body": "body frame (height, body velocity, collective thrust, battery; its force turns with the "
                     "vehicle)", "state": "state frame ([x, u], the paper's)"}.get(residual["frame"], residual["frame"])
    members = residual.get("members", 1)
    return f"residual: {frame}" + (f"; mean of an ensemble of {members}, whose spread joins its process noise"
                                   if members > 1 else "")


def noise_lines(noise: dict) -> list[str]:
    """`models show`'s lines on the noise each of the version's filters runs with
    (`service.jobs.tasks.noise_summary`)."""
    lines = []
    for who, label in (("model", "the model"), ("prior", "its prior")):
        entry = noise.get(who)
        if not entry:
            lines.append(f"  noise of {label}: the system's fixed noise (paper)")
            continue
        blocks = ", ".join(f"{k} {v}" for k, v in {**{f"Q {k}": v for k, v in entry["process_per_step"].items()},
                                                   **{f"R {k}": v for k, v in entry["measurement"].items()}}.items())
        steps = (entry.get("detail") or {}).get("log_likelihood_per_step") or {}
        how = (f" (log-likelihood per step {steps['start']:.2f} -> {steps['identified']:.2f})"
               if {"start", "identified"} <= set(steps) else "")
        lines.append(f"  noise of {label}: {entry['source']}{how}: {blocks}")
    return lines


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
    if metrics.get("residual_scale_note"):
        lines.append("  " + residual_scale_line(metrics))
    if metrics.get("residual"):
        lines.append("  " + residual_line(metrics["residual"]))
    lines += noise_lines(metrics.get("noise") or {})
    if lineage.get("learned") is False:
        lines.append(f"  NOT LEARNED: {lineage.get('learned_note')}")
    elif metrics.get("prior_validation_loss") and metrics.get("best_validation_loss") is not None:
        gain = gain_pct(metrics["prior_validation_loss"], metrics["best_validation_loss"])
        lines.append(f"  learned: held-out one-step loss {gain:.1f} % below the prior's")
    elif lineage.get("learned_note"):
        lines.append(f"  {lineage['learned_note']}")
    return lines


def diagnosis_lead(result: dict) -> list[str]:
    """The diagnosis' answer and split first, as its page says them (`learnest.workflows.headline`)."""
    from learnest.workflows.headline import diagnosis_headline, diagnosis_split

    split = diagnosis_split(result)
    lines = [diagnosis_headline(result)]
    if split["fitting"] or split["scored"]:
        lines.append(f"split: fitted on {', '.join(split['fitting']) or '-'}; "
                     f"scored on {', '.join(split['scored']) or '-'}"
                     + (f" ({split['text']})" if split["text"] else ""))
    elif split["text"]:
        lines.append(f"split: {split['text']}")
    return lines + [""]


def _gap_lines(timing: dict | None, delivered_below: float = 0.95) -> list[str]:
    """One line for the mocap and the accelerometer each, when it lost more than 5 % of its samples
    (`learnest.ingest.align.stream_timing`): a stream with gaps, at its own rate."""
    return [f"  {name}: {t['rate_hz']:.1f} Hz with gaps: {100 * t['delivered']:.0f} % of its samples delivered "
            f"({t['gaps']} gaps, longest {t['longest_gap_s']:.2f} s)"
            for name, t in (timing or {}).items()
            if name in ("mocap", "acc") and t and t["delivered"] < delivered_below]
