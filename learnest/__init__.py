"""learnest: learning-enhanced state estimation (KNODE-UKF / KNODE-MHE) for Crazyflie flight logs.

The notebook API::

    import learnest as le
    flights = le.read_flights(paths)                   # Flight objects (Flight.to_dataframe())
    knode = le.KNODE(epochs=150).fit(flights[0])       # Algorithm 1 on one flight (or .fit(flights[:8]): pooled);
                                                       # the prior from the flights' inputs: knode.system_
    post = le.ukf(knode.model_, flights[1])            # FilterResult(t, means, covariances, innovations)
    report = le.evaluate(knode.model_, flights[1:])    # MSE per method and flight, medians, improvement
    diagnosis = le.diagnose(flights, model=knode.model_)   # or system="crazyflie": thrust from PWM, rpm or N
    thrust = le.thrust_map(flights[:8], flights[8:])   # thrust map fitted on some flights, scored on others

Names are imported on first use, so ``import learnest`` stays fast (torch, CasADi and filterpy load only
when a model or an estimator is touched).
"""
from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import Conflict, InvalidInput, LearnestError, NotFound, NumericalWarning

try:
    __version__ = _version("learnest")
except PackageNotFoundError:  # pragma: no cover - running from a checkout that was never installed
    __version__ = "0+unknown"

# Imported from a checkout (a notebook started in the repository root puts it first on sys.path): the
# subpackages are the design card's sibling folders, which the installed package maps under `learnest`.
_checkout = Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "ingest" / "__init__.py").is_file():
    __path__.append(str(_checkout))

# public name -> module that defines it (torchdiffeq's habit: a tiny surface over the implementation)
_LAZY = {
    "read_flights": "learnest.ingest",
    "Flight": "learnest.ingest.flight",
    "IngestError": "learnest.ingest.flight",
    "HybridModel": "learnest.models.knode",
    "make_system": "learnest.models.systems",
    "FilterResult": "learnest.estimators.results",
    "KNODE": "learnest.estimators.knode_estimator",
    "MHEResult": "learnest.estimators.results",
    "ukf": "learnest.workflows.estimation",
    "mhe": "learnest.workflows.estimation",
    "evaluate": "learnest.workflows.estimation",
    "diagnose": "learnest.workflows.diagnosis",
    "thrust_map": "learnest.workflows.thrust_map",
}

__all__ = ["KNODE", "Conflict", "FilterResult", "Flight", "HybridModel", "IngestError", "InvalidInput",
           "LearnestError", "MHEResult", "NotFound", "NumericalWarning", "__version__", "diagnose", "evaluate",
           "make_system", "mhe", "read_flights", "thrust_map", "ukf"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'learnest' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)


if TYPE_CHECKING:  # what type checkers and IDEs see
    from .estimators.knode_estimator import KNODE
    from .estimators.results import FilterResult, MHEResult
    from .ingest import read_flights
    from .ingest.flight import Flight, IngestError
    from .models.knode import HybridModel
    from .models.systems import make_system
    from .workflows.diagnosis import diagnose
    from .workflows.estimation import evaluate, mhe, ukf
    from .workflows.thrust_map import thrust_map
