"""The `learnest` argument parser: one function per subcommand group, the help of every argument."""
from __future__ import annotations

import argparse
from typing import NoReturn

from learnest.workflows.vocabulary import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    EVALUATION_METHODS,
    METHODS,
    MHE_HORIZON,
    PAPER_OBSERVER,
    PRODUCTION_ALIAS,
    SG_WINDOW,
    __version__,
)

from .arguments import (
    SERVE_LIMITS,
    _add_cut_argument,
    _add_gap_arguments,
    _add_topic_arguments,
    _export_path,
    _model_ref,
    _name,
    _new_file,
    _positive_float,
    _positive_int,
    _sg_window,
    _whole_number,
)
from .commands import (
    _alias_set,
    _audit,
    _demo,
    _diagnose,
    _evaluate,
    _export,
    _flights_list,
    _ingest,
    _models_list,
    _models_show,
    _reproduce,
    _serve,
    _thrust_map,
    _tokens_create,
    _tokens_list,
    _tokens_revoke,
    _train,
)


class _Formatter(argparse.HelpFormatter):
    """Help that states every default: an option's text gets "(default: X)" unless it already names X (flags,
    whose default is only "not given", and options without a default get nothing)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if default_text(action) is None or text == argparse.SUPPRESS or states_default(action):
            return action.help
        return text + (" " if text else "") + "(default: %(default)s)"


def default_text(action: argparse.Action) -> str | None:
    """How the help names ``action``'s default, or None when it has none to state (no default, a flag)."""
    default = action.default
    if default is None or default is False or default == argparse.SUPPRESS or action.nargs == 0:
        return None
    if isinstance(default, float):
        return f"{default:g}"
    return str(default)


def states_default(action: argparse.Action) -> bool:
    """Whether ``action``'s own help text already names its default (`default_text`)."""
    text, default = (action.help or "").replace("%%", "%"), default_text(action)
    return "%(default)" in text or (default is not None and default in text) or str(action.default) in text


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors, like every other learnest error (the usage is one --help away), and help
    that states every default (`_Formatter`)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every `learnest` subcommand; each sets `func`, the function that runs it."""
    parser = _Parser(prog="learnest", description="Learning-enhanced state estimation "
                                     "for Crazyflie flight logs (LEARNEST).",
                     epilog="`learnest COMMAND --help` says what each command does and takes.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the installed learnest's version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_reproduce(sub)
    _add_ingest(sub)
    _add_train(sub)
    _add_evaluate(sub)
    _add_export(sub)
    _add_registry(sub)
    _add_access(sub)
    _add_serve(sub)
    _add_diagnose(sub)
    _add_thrust_map(sub)
    _add_demo(sub)
    _fill_help(parser)
    return parser


def _add_reproduce(sub: argparse._SubParsersAction) -> None:
    """reproduce: Table I of the paper on the simulated systems."""
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
    rep.add_argument("--workers", type=_positive_int, default=1, help="processes to spread the seeds over "
                     "(more than one per core does not help)")
    rep.add_argument("--observer-rounds", type=int, choices=range(0, 11), default=None, metavar="K",
                     help="rounds of re-estimating the KNODE rows' training states with the learned model and "
                          "training again, 0-10 (default: the task's, "
                          f"{_observers(lambda kind, rounds: str(rounds))}; 0 is the paper's Algorithm 1)")
    rep.add_argument("--observer", choices=("filter", "smoother", "joint"), default=None,
                     help="how the KNODE rows estimate the unmeasured states they train on: filter (the prior's "
                          "UKF), smoother (the UKF, then a backward smoothing pass) or joint (the states and the "
                          f"residual fitted together) (default: the task's, {_observers(lambda kind, rounds: kind)})")
    rep.add_argument("--noise", choices=("paper", "identified"), default="paper",
                     help="every filter with the system's fixed noise (paper: Table I) or each model's process noise "
                          "identified on its training run (identified) (default paper)")
    rep.add_argument("--arrival-update", choices=("smoothing", "filtering"), default="smoothing",
                     help="the MHE rows' arrival mean: smoothing, the last window's estimate (the paper's eq. 2: "
                          "Table I), or filtering, the prediction its arrival covariance describes (as learnest "
                          "evaluates flights)")
    rep.set_defaults(func=_reproduce)


def _add_ingest(sub: argparse._SubParsersAction) -> None:
    """ingest: read, normalise and check flight logs."""
    ing = sub.add_parser("ingest", help="read flight logs, normalise them and check their quality")
    ing.add_argument("files", nargs="+", help="log files or folders (a folder's logs are read; NanoBench "
                                              "*_metadata.yaml and crazyswarm2 infoNNN.yaml are read with their logs)")
    ing.add_argument("--json", action="store_true")
    ing.add_argument("--rate", type=_positive_float, default=100.0, help="grid rate in Hz (default 100)")
    ing.add_argument("--strict", action="store_true", help="exit with status 1 if any flight fails the quality checks")
    _add_topic_arguments(ing)
    _add_cut_argument(ing)
    ing.set_defaults(func=_ingest)


def _add_train(sub: argparse._SubParsersAction) -> None:
    """train: a KNODE on one flight or several, registered."""
    tr = sub.add_parser("train", help="train a KNODE on one flight (Algorithm 1) or on several flights of one "
                                      "vehicle (one pooled loss, whole flights held out) and register it as the next "
                                      "version of NAME (the flights are stored too, as by an upload)")
    tr.add_argument("files", nargs="+", metavar="FILE|FOLDER",
                    help="the log file(s) of one flight, or of several flights, or folders of them")
    tr.add_argument("--validate", nargs="+", metavar="FILE", default=None,
                    help="log files of flights held out whole to choose the kept epoch (default with several flights: "
                         "one in five; one flight alone is validated on time blocks of it)")
    tr.add_argument("--group-by", default=None, metavar="RULE",
                    help="groups of several flights, each held out in turn to choose how much of the residual to keep "
                         "(its scale): 'family' (the trajectory family the logs declare; the default), "
                         "'name:REGEX' (the regex's one capture group in each flight's name) or 'none' (the whole "
                         "residual); fewer than two groups keep the whole residual")
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
    tr.add_argument("--noise", default="identified", choices=["identified", "paper"],
                    help="identified (default): identify the model's and its prior's process noise on the training "
                         "flights by the UKF's likelihood (innovations and hidden mocap) and store it with the "
                         "version (every evaluation then runs each model with its own); paper: the system's fixed "
                         "noise")
    tr.add_argument("--ensemble", type=_positive_int, default=1, metavar="K",
                    help="several flights: train K residuals from different seeds; their mean is the model and their "
                         "disagreement on a flight joins its process noise (default 1)")
    _add_topic_arguments(tr)
    _add_cut_argument(tr)
    tr.set_defaults(func=_train)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    """evaluate: score a registered model's estimators on flights."""
    ev = sub.add_parser("evaluate", help="run UKF/MHE/KNODE-UKF/KNODE-MHE on flights and score them")
    ev.add_argument("files", nargs="*")
    ev.add_argument("--model", metavar="REF", type=_model_ref,
                    help="a registered model: NAME (its latest ready version), NAME:VERSION or NAME@ALIAS "
                         "(required unless --new)")
    ev.add_argument("--methods", default=",".join(EVALUATION_METHODS),
                    help=f"comma-separated estimators to run, any of {', '.join(EVALUATION_METHODS)} (onboard is "
                         "the vehicle's own estimate, scored where the log carries it)")
    ev.add_argument("--json", action="store_true")
    ev.add_argument("--plot", metavar="PNG", type=_new_file,
                    help="write the per-flight MSE figure (prior vs KNODE, one line per flight; box plots from "
                         "10 flights on)")
    ev.add_argument("--horizon", type=_positive_int, default=MHE_HORIZON, help="MHE horizon N, samples")
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
    ev.add_argument("--noise", default="identified", choices=["identified", "paper"],
                    help="identified (default): the KNODE and its prior each with its own noise identified on the "
                         "training flights (the system's fixed noise for a model trained without it); paper: both "
                         "with the system's fixed noise")
    _add_gap_arguments(ev)
    _add_topic_arguments(ev)
    _add_cut_argument(ev)
    ev.set_defaults(func=_evaluate)


def _add_export(sub: argparse._SubParsersAction) -> None:
    """export: a stored evaluation's state estimates."""
    exp = sub.add_parser("export", help="write a stored evaluation's state estimates (every method and flight, "
                                        "with the reference) as CSV, Parquet or MCAP (Foxglove)")
    exp.add_argument("evaluation_id", type=_positive_int, metavar="EVALUATION_ID")
    exp.add_argument("-o", "--output", required=True, type=_new_file, metavar="PATH")
    exp.add_argument("--format", choices=["csv", "parquet", "mcap"], default=None,
                     help="default: from the suffix of PATH (.csv, .parquet, .mcap)")
    exp.add_argument("--flight", type=_positive_int, default=None, metavar="ID",
                     help="only this flight (default: every scored flight)")
    exp.set_defaults(func=_export)


def _add_registry(sub: argparse._SubParsersAction) -> None:
    """flights list, models list/show, alias set: the registry's rows."""
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


def _add_access(sub: argparse._SubParsersAction) -> None:
    """tokens create/list/revoke, audit: who may use the server, and what they deleted."""
    tok = sub.add_parser("tokens", help="API tokens of people and machines, with scopes (read, write, admin)")
    tok_sub = tok.add_subparsers(dest="action", required=True)
    create = tok_sub.add_parser("create", help="make a token NAME and print it, this once (only its hash is kept)")
    create.add_argument("name", metavar="NAME", help="who holds it, e.g. alice or ci-runner")
    create.add_argument("--scope", required=True, choices=["read", "write", "admin"],
                        help="read: every GET; write: also uploads, training, evaluation, diagnosis, aliases, "
                             "cancelling; admin: also deletes, tokens and the audit log")
    create.add_argument("--json", action="store_true")
    create.set_defaults(func=_tokens_create)
    listing = tok_sub.add_parser("list", help="every token made, revoked ones too (never the tokens themselves)")
    listing.add_argument("--json", action="store_true")
    listing.set_defaults(func=_tokens_list)
    revoke = tok_sub.add_parser("revoke", help="revoke a token: it fails at once on every server worker")
    revoke.add_argument("token", metavar="NAME|ID", help="the token's id, or the name of a token not revoked")
    revoke.add_argument("--json", action="store_true")
    revoke.set_defaults(func=_tokens_revoke)
    aud = sub.add_parser("audit", help="the audit log: deletions, alias moves and token changes, who and when")
    aud.add_argument("--limit", type=_positive_int, default=50, help="the newest this many entries")
    aud.add_argument("--json", action="store_true")
    aud.set_defaults(func=_audit)


def _add_serve(sub: argparse._SubParsersAction) -> None:
    """serve: the HTTP service and its connection limits."""
    srv = sub.add_parser("serve", help="run the HTTP service (uvicorn; OpenAPI docs at /docs)")
    srv.add_argument("--host", default="127.0.0.1")
    srv.add_argument("--port", type=int, default=8000)
    srv.add_argument("--workers", type=_positive_int, default=1, help="uvicorn worker processes")
    srv.add_argument("--dask", metavar="URL", help="run jobs on a Dask scheduler (tcp://host:port, or 'local' "
                     "for a LocalCluster) instead of the local process pool")
    srv.add_argument("--insecure", action="store_true",
                     help="serve an address other than this machine's loopback although the server has no token and "
                          "no LEARNEST_API_KEY (anyone who reaches it may read, upload and delete everything)")
    for option, (kind, text) in SERVE_LIMITS.items():
        srv.add_argument("--" + option.replace("_", "-"), type=kind, default=None,
                         help=f"{text}; env LEARNEST_{option.upper()}")
    srv.set_defaults(func=_serve)


def _add_diagnose(sub: argparse._SubParsersAction) -> None:
    """diagnose: trace the residual to named effects, repair, score before/after."""
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
    dia.add_argument("--methods", default="ukf,knode-ukf",
                     help=f"comma-separated estimators scored before and after, any of {', '.join(METHODS)}")
    dia.add_argument("--epochs", type=_positive_int, default=None)
    dia.add_argument("--json", action="store_true")
    dia.add_argument("--plot", metavar="PNG", type=_new_file,
                     help="residual over time and held-out error before/after (linear axes)")
    dia.add_argument("--rate", type=_positive_float, default=100.0)
    _add_topic_arguments(dia)
    _add_cut_argument(dia)
    dia.set_defaults(func=_diagnose)


def _add_thrust_map(sub: argparse._SubParsersAction) -> None:
    """thrust-map: identify the Crazyflie thrust map."""
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


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """demo: ingest, train and evaluate a folder of flights."""
    demo = sub.add_parser("demo", help="ingest, train on one flight and evaluate the others, for a folder")
    demo.add_argument("folder")
    demo.add_argument("--train", help="name of the training flight (default: the first clean one)")
    demo.add_argument("--name", default="demo", help="registered model name (each run adds a version of it)")
    demo.add_argument("--methods", default=",".join(EVALUATION_METHODS))
    demo.add_argument("--plot", metavar="PNG", type=_new_file, default=None)
    demo.add_argument("--horizon", type=_positive_int, default=MHE_HORIZON)
    demo.add_argument("--rate", type=_positive_float, default=100.0)
    demo.add_argument("--system", default=None, choices=["quadrotor", "crazyflie"],
                      help="the prior to train (default: crazyflie when at least two clean flights carry motor PWM "
                           "and battery voltage, else the kinematic quadrotor)")
    demo.set_defaults(func=_demo)


# Help of the arguments defined above without one (kept here, in one block, so the definitions stay short);
# tests/service/test_cli_help.py walks the parser and fails on any argument still without help.
JSON_HELP = "print the result as JSON instead of text"


HELP = {
    ("reproduce", "--task"): "the simulated system of Table I",
    ("reproduce", "--seeds"): "how many seeds (random systems and noise) to average over (default 15, the paper's)",
    ("evaluate", "files"): "flight log files or folders to score the model on (not with --new)",
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
    ("demo", "--methods"): f"comma-separated estimators to run, any of {', '.join(EVALUATION_METHODS)}",
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


def _observers(which) -> str:
    """The pre-training observer setting ``which(kind, rounds)`` of each task, e.g. "cartpole joint, ..."."""
    return ", ".join(f"{task} {which(kind, rounds)}" for task, (kind, rounds) in PAPER_OBSERVER.items())


def _fill_help(parser: argparse.ArgumentParser) -> None:
    """Give the arguments defined without help their text from `HELP` (a --json flag: `JSON_HELP`), and each
    subcommand's page its one-line summary as its description (what `learnest X --help` opens with)."""
    for path, sub in subcommands(parser):
        for action in sub._actions:
            if action.help:
                continue
            name = action.option_strings[-1] if action.option_strings else action.dest
            if name == "--json" and action.nargs == 0:
                action.help = JSON_HELP
            else:
                action.help = HELP.get((" ".join(path), name), action.help)
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction):
                for summary in action._choices_actions:
                    child = action.choices[summary.dest]
                    child.description = child.description or _sentence(summary.help)


def _sentence(summary: str | None) -> str | None:
    """A command's summary as the description of its page: capitalised, with a full stop."""
    if not summary:
        return summary
    return summary[0].upper() + summary[1:] + ("" if summary.endswith(".") else ".")
