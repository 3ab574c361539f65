"""A channel of data in regression form (`ResidualProblem`), a fit of effects to it (`Fit`), and the
autocorrelation-aware information criterion the selection compares fits by (`bic_eff`, `common_bic`);
`models.diagnosis` explains why the criterion counts effective samples."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ResidualProblem:
    """One channel of data in regression form for effect selection.

    Attributes
    ----------
    name : str
        Channel name (``"accelerometer"``, ``"dynamics"``, ...), reported as ``channel``.
    candidates : list of Effect
        Effects the selection may choose from; all sit at their nominal values unless fitted.
    residual : callable
        ``residual(values, rows) -> ndarray (len(rows), k)``: observed minus predicted for parameter
        ``values`` {name: value} on the given row indices.
    n_rows : int
        Number of rows.
    blocks : list of ndarray
        Held-out row blocks of the cross-validation (flights or time); default 5 contiguous blocks.
    frozen : dict
        Parameter name -> why the data cannot identify it; such parameters stay nominal.
    times : ndarray, optional
        (n_rows,) time of each row, s, where rows are samples of a flight (for plotting the residual).
    undetermined : dict
        Parameter name -> why the data's own excitation cannot determine it and what data would (a battery
        that never sags leaves its thrust exponent a mere gain): fitted, never claimed, given no interval.
    excitation : dict
        What the data's signals span (their spreads, with units), as the problem's builder measured it.
    """

    name: str
    candidates: list                       # [Effect]
    residual: Callable                     # (values: dict, rows: ndarray) -> (len(rows), k)
    n_rows: int
    blocks: list = field(default_factory=list)   # held-out blocks (row index arrays): flights or time
    frozen: dict = field(default_factory=dict)   # param name -> why the data cannot identify it (kept nominal)
    times: np.ndarray | None = None              # (n_rows,) s, when rows are samples in time
    undetermined: dict = field(default_factory=dict)   # param name -> why the excitation cannot determine it
    excitation: dict = field(default_factory=dict)     # the data's spread per signal, as measured by the builder

    def __post_init__(self):
        if not self.blocks:
            self.blocks = np.array_split(np.arange(self.n_rows), 5)


@dataclass
class Fit:
    """A least-squares fit of some effects.

    Attributes
    ----------
    effects : list of Effect
    values : dict
        Fitted parameter values {name: value} (frozen parameters are absent).
    residual : ndarray, shape (n_rows, k)
        The residual at those values.
    rss : float
        Residual sum of squares.
    bic : float
        BIC_eff (`bic_eff`).
    tau : float
        Integrated autocorrelation time of the residual, samples.
    """

    effects: list
    values: dict
    residual: np.ndarray
    rss: float
    bic: float
    tau: float       # integrated autocorrelation time of the residual, samples


def autocorrelation_time(residual: np.ndarray) -> float:
    """Integrated autocorrelation time τ = 1 + 2 Σ ρ_k (samples), summed until ρ_k first drops below zero
    (Geyer's initial positive sequence), averaged over the residual's columns."""
    r = residual - residual.mean(axis=0)
    n = len(r)
    if n < 4:
        return 1.0
    spectrum = np.fft.rfft(r, n=2 * n, axis=0)
    acf = np.fft.irfft(spectrum * np.conj(spectrum), axis=0)[:n]
    taus = []
    for column in acf.T:
        if column[0] <= 0:
            continue
        rho = column / column[0]
        negative = np.flatnonzero(rho < 0)
        cut = negative[0] if negative.size else n
        taus.append(1.0 + 2.0 * rho[1:cut].sum())
    return float(np.clip(np.mean(taus), 1.0, n)) if taus else 1.0


def bic_eff(residual: np.ndarray, n_params: int, tau: float | None = None) -> tuple[float, float]:
    """BIC with the effective number of independent samples N/τ (see autocorrelation_time).

    Returns ``(bic, tau)``: N_eff·log(mean r²) + n_params·log(N_eff), with N = residual.size, N_eff at
    least n_params + 2, and τ in samples (the residual's own unless ``tau`` is given; compare models only
    at a common τ, see `common_bic`).
    """
    tau = autocorrelation_time(residual) if tau is None else tau
    n_eff = max(residual.size / tau, n_params + 2.0)
    return n_eff * np.log(max(np.mean(residual**2), 1e-300)) + n_params * np.log(n_eff), tau


def common_bic(fit_: Fit, tau: float) -> float:
    """BIC_eff of ``fit_`` with a given autocorrelation time τ (samples) instead of its own residual's.

    Models compared with each other must share N_eff = N/τ: with each its own, the term N_eff·log(mean r²)
    (whose sign depends on the residual's units) rewards a whiter residual over a smaller one — on a real
    flight it prefers an accelerometer delay that removes far less residual than a tilt, for its whiter residual.
    Differences at a common N_eff, N_eff·log(RSS₁/RSS₀) + Δk·log N_eff, do not depend on the units.
    """
    return bic_eff(fit_.residual, len(fit_.values), tau)[0]
