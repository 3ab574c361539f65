"""A covariance kept symmetric positive definite, with its Cholesky factor (shared by the UKF and its points)."""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import numpy as np
from scipy.linalg import lapack

from learnest.errors import NumericalWarning

# repairs counted in the current run (`repairs_warned`); None outside a run: each repair warns by itself
_REPAIRS: ContextVar[list[int] | None] = ContextVar("covariance_repairs", default=None)


@contextmanager
def repairs_warned(where: str) -> Iterator[None]:
    """Count the covariance repairs of `spd_factor` inside the block (one estimator run) and warn once at its
    end with `NumericalWarning` naming ``where`` and how many steps were repaired; nothing when none was."""
    counter = [0]
    token = _REPAIRS.set(counter)
    try:
        yield
    finally:
        _REPAIRS.reset(token)
    if counter[0]:
        warnings.warn(f"{where}: the covariance was not positive definite at {counter[0]} step(s) and was "
                      "repaired (its spectrum lifted just above zero); the estimates there are approximate",
                      NumericalWarning, stacklevel=3)


def _repaired() -> None:
    counter = _REPAIRS.get()
    if counter is None:
        warnings.warn("a covariance was not positive definite and was repaired (its spectrum lifted just above "
                      "zero)", NumericalWarning, stacklevel=3)
    else:
        counter[0] += 1


def spd_factor(P: np.ndarray, floor: float = 1e-15) -> tuple[np.ndarray, np.ndarray]:
    """Symmetrise P and return (P, L) with L Lᵀ = P.

    If Cholesky fails, the spectrum is lifted just above zero; if even that fails (a spread of
    eigenvalues beyond double precision), L is a clipped eigen square root instead of a triangle.
    LAPACK's potrf is called directly: numpy's wrapper costs four times more on a 9x9 matrix.
    A repair is reported with `NumericalWarning`: once per run inside `repairs_warned`, else each time.
    """
    P = 0.5 * (P + P.T)
    L, info = lapack.dpotrf(P, lower=1)
    if info == 0:
        return P, L
    _repaired()
    eigval, eigvec = np.linalg.eigh(P)
    P = P + np.eye(len(P)) * (floor * max(1.0, eigval[-1]) - eigval[0])
    L, info = lapack.dpotrf(P, lower=1)
    if info == 0:
        return P, L
    return P, eigvec * np.sqrt(np.maximum(eigval, floor * max(1.0, eigval[-1])))
