"""The handlers of the subcommands that read or move registry rows (flights, models, alias, export) and of
`serve`: no torch, no worker set-up."""
from __future__ import annotations

import json
import sys

from ..arguments import SERVE_LIMITS, _export_format
from ..formatting import format_model


def _flights_list(args) -> int:
    """The stored flights (service.local.list_flights)."""
    from ...local import list_flights

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
    """The registered models (service.local.list_models)."""
    from ...local import list_models

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
    from ...local import show_model

    out = show_model(args.ref)
    print(json.dumps(out, indent=2, default=str) if args.json else format_model(out))
    return 0


def _alias_set(args) -> int:
    """Point NAME@ALIAS at VERSION (service.local.set_alias)."""
    from ...local import set_alias

    out = set_alias(args.name, args.version, args.alias)
    before = out["previous_version"]
    print(json.dumps(out, indent=2) if args.json else
          f"{out['name']}@{out['alias']} -> version {out['version']}"
          + ("" if before is None else f" (was {before})" if before != out["version"] else " (unchanged)"))
    return 0


def _export(args) -> int:
    """Write a stored evaluation's state estimates (service.operations.exports) as CSV, Parquet or MCAP."""
    from ...local import export

    fmt = args.format or _export_format(args.output)
    flights = export(args.evaluation_id, args.output, fmt, args.flight)
    methods = sorted({m for f in flights for m in f.methods})
    print(f"wrote {args.output} ({fmt}): {len(flights)} flight(s) "
          f"({', '.join(f.flight for f in flights)}), methods {', '.join(methods)}")
    return 0


def _serve(args) -> int:
    """The HTTP service (FastAPI app factory service.app.factory:create_app under uvicorn); docs at /docs."""
    import os

    from ...local import Settings, serve

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
    if not _may_serve(args, settings):
        return 2
    # the starting app listens at once and loads the service behind it (seconds of imports and migrations):
    # /health and / answer from the first moment (service.app.starting, named to uvicorn by import path)
    serve(settings, args.host, args.port, args.workers)
    return 0


def _may_serve(args, settings) -> bool:
    """False (said why) for a server open to everyone on an address other than this machine's loopback: no
    LEARNEST_API_KEY, no token in the registry, and no ``--insecure``."""
    from ...local.access import any_access_token

    if _loopback(args.host) or settings.api_key is not None or any_access_token(settings):
        if args.insecure:
            print("learnest: --insecure changes nothing here: the server is on loopback or has tokens",
                  file=sys.stderr)
        return True
    if args.insecure:
        print(f"learnest: serving {args.host} with no token (--insecure): anyone who reaches it may read, upload and "
              "delete everything", file=sys.stderr)
        return True
    print(f"learnest serve: error: refusing to serve {args.host} with no token: anyone who reaches it could read, "
          "upload and delete everything. Make an admin token first (`learnest tokens create NAME --scope admin`) or "
          "set LEARNEST_API_KEY; or serve 127.0.0.1 (this machine only); --insecure serves it open anyway",
          file=sys.stderr)
    return False


def _loopback(host: str) -> bool:
    """Whether ``host`` (an address or name to listen on) is this machine's loopback only."""
    import ipaddress

    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False
