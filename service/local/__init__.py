"""The service in this process, without HTTP: the model registry and flight store as the CLI's commands (and
scripts, benchmarks, notebooks) use them.  Beside the JSON API and the web pages it is the third surface over the
same service functions (service.operations) and jobs.

It uses the same database and blob folder as `learnest serve` (LEARNEST_HOME, or LEARNEST_DATABASE_URL), so a
model trained by `learnest train` is `name:version` for the API and the web pages too, and the reverse.
Modules: `services` (settings, Services opened here, watching a job), `flights` (storing local files as an
upload would), `training`, `evaluation`, `browsing` (reading the registry), `serving` (`learnest serve`); their
public names are here.  Below the web pages and the CLI, so both use them: `figures` (the matplotlib figures of
reports and stored versions; the CLI's --plot files) and `palette` (one colour per estimator).

- `add_flight`: store a flight's log file(s) as POST /flights does (service.operations.uploads.add_flight: raw files +
  normalized flight as blobs, one row, deduplicated by sha256).
- `train`: register the next version of a model trained on those flights (one, or several of one vehicle), as
  POST /models does (a training job on a one-process local pool, with the same provenance), and wait for it.
  Interrupted (Ctrl-C), the job is
  cancelled, its worker stopped and its reserved version removed: nothing half-registered is left.
- `register_repaired`: register a diagnosis' repaired model as the next version of a name (its fitting flight
  stored as by an upload), as POST /diagnoses with "register" does.
- `evaluate`: store the flights (as `add_flight`) and evaluate a registered version on them as POST /evaluations
  does, here and now (`InlineExecutor`); the evaluation is then in the registry, its page and its exports.
- `export`: write a stored evaluation's state estimates (service.operations.exports).
- `load_model`: "NAME" (its latest ready version), "NAME:VERSION" or "NAME@ALIAS" -> HybridModel, through
  service.storage.registry.load_model_ref; a reference that names nothing usable is a NotFound or Conflict listing the
  known models.
- `serve`: run the HTTP app under uvicorn with the settings' timeouts and limits (`learnest serve`); the app is
  named to uvicorn by import path, so this facade imports neither the app nor the API.

The CLI states its requests in a few of the service's own names, given here beside the facade's functions: the
`Settings` (LEARNEST_*), one scheduler round (`evaluate_new_once`), this process set up to run the networks
(`init_worker`), and the grammar of model names, references and topics (`check_name`, `parse_ref`, `check_topic`,
from `service.storage.references`).  An evaluation's settings are `learnest.workflows.vocabulary.EvaluationSettings`;
`EstimatorSettings` is the same type with its result-cache ``key``, under the name scripts know.

Every name is imported on first use: checking a reference's form loads no database stack, and the CLI's usage
errors come before anything heavy.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# public name -> module that defines it (relative to this package)
_LAZY = {
    **dict.fromkeys(["known_models", "list_flights", "list_models", "load_model", "set_alias", "show_model"],
                    ".browsing"),
    **dict.fromkeys(["evaluate", "export"], ".evaluation"),
    **dict.fromkeys(["UnreadableFile", "add_flight", "flight_files"], ".flights"),
    **dict.fromkeys(["cli_settings", "local_services", "registry_database", "wait_for_job", "watching_stages"],
                    ".services"),
    "serve": ".serving",
    **dict.fromkeys(["TrainingFailed", "abandon_training", "register_repaired", "train"], ".training"),
    "Settings": "..config",
    "EstimatorSettings": "..jobs.result_cache",
    "evaluate_new_once": "..jobs.scheduler",
    "init_worker": "..jobs.executors",
    **dict.fromkeys(["check_name", "check_topic", "parse_ref"], "..storage.references"),
}

__all__ = ["EstimatorSettings", "Settings", "TrainingFailed", "UnreadableFile", "abandon_training", "add_flight",
           "check_name", "check_topic", "cli_settings", "evaluate", "evaluate_new_once", "export", "flight_files",
           "init_worker", "known_models", "list_flights", "list_models", "load_model", "local_services", "parse_ref",
           "register_repaired", "registry_database", "serve", "set_alias", "show_model", "train", "wait_for_job",
           "watching_stages"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)


if TYPE_CHECKING:  # what type checkers and IDEs see
    from ..config import Settings
    from ..jobs.executors import init_worker
    from ..jobs.result_cache import EstimatorSettings
    from ..jobs.scheduler import evaluate_new_once
    from ..storage.references import check_name, check_topic, parse_ref
    from .browsing import known_models, list_flights, list_models, load_model, set_alias, show_model
    from .evaluation import evaluate, export
    from .flights import UnreadableFile, add_flight, flight_files
    from .services import cli_settings, local_services, registry_database, wait_for_job, watching_stages
    from .serving import serve
    from .training import TrainingFailed, abandon_training, register_repaired, train
