"""A model's numbers as one input of its compiled functions, so their C code depends on its architecture only.

Why: `estimators.native.codegen` caches a library by the hash of its source.  With a model's trained weights,
identified parameters and sample time baked into the CasADi graph as constants, every trained model would be
new source and a new compilation, which takes far longer than running the estimators on a flight (the first use of
an architecture on the results page `docs/results/speed.md`).  Built from
`symbolic_model`, the functions take those numbers as an input vector filled once per estimator, and the
second model of an architecture (system, hidden sizes, residual masks) loads the library the first built.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from .protocols import StateSpaceModel


@dataclass
class SymbolicModel:
    """A model whose numbers are CasADi symbols.

    Attributes
    ----------
    model : StateSpaceModel
        ``step(x, u, dt)`` and ``h(x, u)`` over SX symbols, with symbols in place of the numbers.
    dt : casadi.SX
        The sample time (s) as a scalar symbol: pass it to ``model.step``.
    params : casadi.SX, shape (k, 1)
        Every symbol, [dt, the model's θ]: make it an input of each function built from ``model``.
    values : ndarray, shape (k,)
        Their values for this model: fill them into that input once.
    """

    model: Any
    dt: ca.SX
    params: ca.SX
    values: np.ndarray


def symbolic_model(model: StateSpaceModel, dt: float) -> SymbolicModel:
    """``model`` with dt and, when it has ``parametric()`` (as `HybridModel`), its weights and physical
    parameters as symbols; any other model keeps its numbers as constants (code per model, as before)."""
    dt_symbol = ca.SX.sym("dt")
    make = getattr(model, "parametric", None)
    if make is None:
        symbolic, theta, values = model, ca.SX(0, 1), np.zeros(0)
    else:
        symbolic, theta, values = make()
    return SymbolicModel(symbolic, dt_symbol, ca.vertcat(dt_symbol, theta),
                         np.concatenate([[float(dt)], np.asarray(values, dtype=float)]))
