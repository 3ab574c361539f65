"""The handlers of the `learnest` subcommands: each takes the parsed arguments and returns the exit status."""
from .access import _audit, _tokens_create, _tokens_list, _tokens_revoke
from .registry import _alias_set, _export, _flights_list, _models_list, _models_show, _serve
from .science import _demo, _diagnose, _evaluate, _ingest, _reproduce, _thrust_map, _train

__all__ = ["_audit", "_tokens_create", "_tokens_list", "_tokens_revoke",
           "_alias_set", "_demo", "_diagnose", "_evaluate", "_export", "_flights_list", "_ingest", "_models_list",
           "_models_show", "_reproduce", "_serve", "_thrust_map", "_train"]
