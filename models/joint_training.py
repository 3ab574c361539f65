"""Joint estimation of the training record's states and the residual: the full-record MHE with Δθ free.

Algorithm 1 first estimates the unmeasured states with an observer and then fits Δθ to them.  Whatever the
observer gets wrong (a model-free KF lags the velocities it infers) becomes data the network learns, and a fit
run to convergence learns it exactly (issue 11: on cartpole seed 0, L-BFGS run to convergence on the KF
observer's states gives KNODE-MHE 5.8e-3, against 0.34e-3 when fitted on the true states).  Here the states
are not fixed: they and the network's weights minimise one weighted least-squares objective over the whole
record,

    J(x_{0:T-1}, θ) = Σ_k ‖(y_k − h(x_k)) / σ_R‖² + Σ_k ‖(x_{k+1} − Φ_θ(x_k, u_k)) / σ_Q‖²,

with Φ_θ one RK4 step of f_prior + Δθ (eq. 7) and σ_R, σ_Q the square roots of the diagonals of the system's
R and Q (the estimators' own tuning): the states must explain the measurements and follow the learned model.
It starts from the observer's states and a zero residual, and runs full-batch L-BFGS (torch's, strong-Wolfe
line search).  The cartpole's default in Table I (`models.presets.PAPER_OBSERVER`): better than the observer
iteration on all 15 seeds (benchmarks/README.md, Table I).
"""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput

from .envelope import training_envelope
from .knode import HybridModel
from .presets import TrainingConfig
from .systems import System
from .training import TrainingResult, new_residual

ITERATIONS = 3000      # L-BFGS iterations in all: on cartpole seed 0 the test error stops falling near 3000
CHUNK = 500            # iterations per L-BFGS call: progress is reported between calls


def train_jointly(system: System, y: ArrayLike, u: ArrayLike, dt: float, zeta: ArrayLike,
                  config: TrainingConfig, iterations: int = ITERATIONS,
                  progress: Callable[[int, float], None] | None = None) -> TrainingResult:
    """Fit the record's states and Δθ together, from the observer's states ``zeta``.

    Parameters
    ----------
    system : System
        The prior (f_prior, h, Q, R, the residual's masks).
    y : array_like, shape (T, m)
        Measurements of the training record, in the system's units.
    u : array_like, shape (T, p)
        Inputs, held over each step (may have width 0).
    dt : float
        Sample period, s.
    zeta : array_like, shape (T, n)
        The observer's state estimates: the starting states.
    config : TrainingConfig
        ``hidden`` and ``seed`` are used.  The rest belongs to Adam and is not used: there are no epochs,
        and nothing is held out (the whole record is fitted; a task that needs a held-out block, such as the
        robot, is not served by this fit).
    iterations : int
        L-BFGS iterations in all.
    progress : callable, optional
        ``progress(iterations_done, objective per sample)`` after every `CHUNK` iterations.

    Returns
    -------
    TrainingResult
        The KNODE (its meta: ``training`` with ``joint_iterations``, the final objective, the envelope of
        the jointly estimated states) and the objective after each chunk in ``losses``.

    Raises
    ------
    InvalidInput
        On mismatched shapes, non-finite values or ``iterations < 1``.
    """
    import torch
    from torchdiffeq import odeint

    from .residual_net import TRAINING_THREADS, torch_threads

    y, zeta = np.asarray(y, dtype=float), np.asarray(zeta, dtype=float)
    u = np.asarray(u, dtype=float).reshape(len(zeta), -1)
    if y.shape[0] != zeta.shape[0] or zeta.shape[1] != system.n or len(zeta) < 3:
        raise InvalidInput(f"joint training needs y (T, m) and zeta (T, {system.n}) of one length T >= 3; got "
                           f"{y.shape} and {zeta.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(zeta)) and np.all(np.isfinite(u))):
        raise InvalidInput("joint training needs finite measurements, states and inputs")
    if iterations < 1:
        raise InvalidInput(f"iterations must be at least 1, got {iterations}")
    with torch_threads(TRAINING_THREADS):
        torch.manual_seed(config.seed)
        mlp = new_residual(system, zeta, u, config.hidden)
        states = torch.tensor(zeta, dtype=torch.float64, requires_grad=True)
        measured, held = torch.as_tensor(y), torch.as_tensor(u[:-1])
        inputs = torch.as_tensor(u)
        sigma_r = torch.as_tensor(np.sqrt(np.diag(system.R)))
        sigma_q = torch.as_tensor(np.sqrt(np.diag(system.Q)))
        t_span = torch.tensor([0.0, dt], dtype=torch.float64)

        def objective():
            def vector_field(_t, x):
                return system.f_prior(x, held) + mlp(torch.cat([x, held], dim=-1))

            following = odeint(vector_field, states[:-1], t_span, method="rk4")[-1]          # eq. (7)
            misfit = ((measured - system.h(states, inputs)) / sigma_r) ** 2
            process = ((states[1:] - following) / sigma_q) ** 2
            return 0.5 * (misfit.sum() + process.sum()) / len(measured)

        optimizer = torch.optim.LBFGS([states, *mlp.parameters()], lr=1.0, max_iter=CHUNK, history_size=100,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-14, tolerance_change=1e-16)

        def closure():
            optimizer.zero_grad()
            value = objective()
            value.backward()
            return value

        losses, started, done = [], time.perf_counter(), 0
        while done < iterations:
            optimizer.param_groups[0]["max_iter"] = min(CHUNK, iterations - done)
            optimizer.step(closure)
            done += optimizer.param_groups[0]["max_iter"]
            with torch.no_grad():
                losses.append(float(objective()))
            if not np.isfinite(losses[-1]):
                raise InvalidInput("joint training diverged (non-finite objective): check Q, R and the record")
            if progress:
                progress(done, losses[-1])
        residual = mlp.export()
        estimated = states.detach().numpy().copy()
    seconds = time.perf_counter() - started
    model = HybridModel(system, "knode", residual,
                        meta={"training": {"hidden": config.hidden, "seed": config.seed,
                                           "joint_iterations": iterations},
                              "final_loss": losses[-1], "seconds": seconds, "best_epoch": None,
                              "best_validation_loss": None,
                              "envelope": training_envelope(estimated, u, [*system.state_names, *system.input_names],
                                                            system.invariant_states, residual)})
    return TrainingResult(model, losses, seconds, [])
