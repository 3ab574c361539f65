"""Joint estimation of the training record's states and the residual: the full-record MHE with Δθ free.

Algorithm 1 first estimates the unmeasured states with an observer and then fits Δθ to them.  Whatever the
observer gets wrong (a model-free KF lags the velocities it infers) becomes data the network learns, and a fit
run to convergence learns it exactly: the learned model is then far worse than one fitted on the true states.
Here the states are not fixed: they and the network's weights θ minimise one weighted least-squares objective
over the whole record,

    J(x_{0:T-1}, θ) = Σ_k ‖(y_k − h(x_k)) / σ_R‖² + Σ_k ‖(x_{k+1} − Φ_θ(x_k, u_k)) / σ_Q‖² + λ ‖θ‖²,

with Φ_θ one RK4 step of f_prior + Δθ (eq. 7) and σ_R, σ_Q the square roots of the diagonals of the system's
R and Q (the estimators' own tuning): the states must explain the measurements and follow the learned model.

Why the weight prior λ‖θ‖²: one record pins the residual down only along the path it took. Fitted closely without
it, the network explains the record to its noise level and is wrong off that path, worse than a long L-BFGS
fit whose early stop is its only regulariser. The iteration count still regularises: the result is not the optimum
of J, and running more iterations makes the learned model worse. Both were chosen on seeds outside Table I: the
count on seeds 15-17 with the paper's masks (Δθ seeing every state and correcting every derivative; not
re-checked with `Cartpole`'s), λ = `WEIGHT_PRIOR` on seeds 15-19 with `Cartpole`'s (the accelerations only, blind
to the cart's position); the evidence is on the results page `docs/results/table1.md`, "How the KNODE is
trained".

How: Levenberg–Marquardt.  The normal equations are block-tridiagonal in the states (one n × n block per
sample; a sample touches only its neighbours) with a dense border for θ, so each step is the MHE's compiled
block Cholesky with the border's columns as extra right-hand sides and a small Schur complement for θ:
O(T n³ + T n P²) per iteration: linear in the record's length, so a whole record is one fit.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput
from learnest.models import residual_frame
from learnest.models.backend import rk4_step
from learnest.models.envelope import training_envelope
from learnest.models.knode import HybridModel
from learnest.models.presets import TrainingConfig
from learnest.models.systems import System
from learnest.models.training import TrainingResult, new_residual

from .native.block_tridiagonal import BlockTridiagonal
from .params import EstimatorParams
from .prepared import model_params

ITERATIONS = 40        # Levenberg–Marquardt iterations at most: part of the regularisation (module docstring)
# λ of the weight prior λ‖θ‖², in the units of J's whitened squared residuals: a Gaussian prior θ ~ N(0, I/λ) on the
# weights of a network with standardised inputs.  Not scaled by the record's length, on purpose: the data's pull
# grows with each sample while a prior's stays, so a longer record is fitted more closely, as it should be.
WEIGHT_PRIOR = 3.0
RELATIVE_TOLERANCE = 1e-9   # stop when an accepted step lowers J by less than this fraction


def train_jointly(system: System, y: ArrayLike, u: ArrayLike, dt: float, zeta: ArrayLike,
                  config: TrainingConfig, iterations: int = ITERATIONS, weight_prior: float = WEIGHT_PRIOR,
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
        Levenberg–Marquardt iterations at most.
    weight_prior : float
        λ of the penalty λ‖θ‖² on the network's weights (≥ 0; whitened units, as J).
    progress : callable, optional
        ``progress(iteration, J / 2 per sample)`` after every step taken.

    Returns
    -------
    TrainingResult
        The KNODE (its meta: ``training`` with ``joint_iterations`` (steps taken) and ``weight_prior``, the final
        objective, the envelope of the jointly estimated states) and J / 2 per sample after each step taken
        in ``losses``.

    Raises
    ------
    InvalidInput
        On mismatched shapes, non-finite values, ``iterations < 1`` or a negative ``weight_prior``.
    """
    import torch

    from learnest.models.residual_net import TRAINING_THREADS, torch_threads

    y, zeta = np.asarray(y, dtype=float), np.asarray(zeta, dtype=float)
    u = np.asarray(u, dtype=float).reshape(len(zeta), -1)
    if y.shape[0] != zeta.shape[0] or zeta.shape[1] != system.n or len(zeta) < 3:
        raise InvalidInput(f"joint training needs y (T, m) and zeta (T, {system.n}) of one length T >= 3; got "
                           f"{y.shape} and {zeta.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(zeta)) and np.all(np.isfinite(u))):
        raise InvalidInput("joint training needs finite measurements, states and inputs")
    if iterations < 1:
        raise InvalidInput(f"iterations must be at least 1, got {iterations}")
    if not weight_prior >= 0:
        raise InvalidInput(f"weight_prior must be at least 0, got {weight_prior}")
    started = time.perf_counter()
    with torch_threads(TRAINING_THREADS):
        torch.manual_seed(config.seed)
        mlp = new_residual(system, zeta, u, config.hidden, config.residual_frame)
        with torch.no_grad():   # weights of inputs Δθ is blind to never act: start them at 0, not in the prior
            mlp.hidden_layer.weight *= mlp.input_mask
        # J is whitened by the prior estimators' own tuning: the full-record MHE's weights
        tuning = model_params(HybridModel(system, "prior"), zeta[0], dt)
        problem = _JointProblem(system, y, u, tuning, mlp, weight_prior)
        states, theta, losses = _levenberg_marquardt(problem, zeta, problem.theta0(), iterations, progress)
        steps_taken, losses = len(losses), losses or [problem.cost(states, theta)]
        problem.load(theta)
        residual = mlp.export()
    model = HybridModel(system, "knode", residual,
                        meta={"training": {"hidden": config.hidden, "seed": config.seed,
                                           "joint_iterations": steps_taken, "weight_prior": weight_prior},
                              "final_loss": losses[-1], "seconds": time.perf_counter() - started,
                              "best_epoch": None, "best_validation_loss": None,
                              "envelope": training_envelope(states, u, [*system.state_names, *system.input_names],
                                                            system.invariant_states, residual)})
    return TrainingResult(model, losses, model.meta["seconds"], [])


class _JointProblem:
    """J's residuals and their Jacobian blocks, whitened (W = diag(1/σ_Q)): measurement rows r_m (T, m), process
    rows r_q (T-1, n), and per step ∂r_m/∂x_k = -h_k, ∂r_q/∂x_k = -a_k = -W A_k, ∂r_q/∂x_{k+1} = W,
    ∂r_q/∂θ = -b_k = -W B_k.  ``tuning`` is the prior's estimator bundle: its dt (s) and the Q, R that whiten."""

    def __init__(self, system: System, y: np.ndarray, u: np.ndarray, tuning: EstimatorParams, mlp,
                 weight_prior: float):
        import torch
        from torch.func import functional_call, jacrev, vmap

        self.mlp, self.weight_prior = mlp, weight_prior
        self.names = [name for name, _ in mlp.named_parameters()]
        self.shapes = [p.shape for _, p in mlp.named_parameters()]
        buffers = dict(mlp.named_buffers())
        self.y, self.u = torch.as_tensor(y), torch.as_tensor(u)
        self.inv_sigma_r = torch.as_tensor(1.0 / np.sqrt(np.diag(tuning.R)))
        self.inv_sigma_q = 1.0 / np.sqrt(np.diag(tuning.Q))
        dt = tuning.dt
        self.h = system.h

        def field(x, u_k, theta):
            weights = {**self._unflatten(theta), **buffers}
            return system.f_prior(x, u_k) + residual_frame.field(
                mlp.frame, lambda z: functional_call(mlp, weights, (z,)), x, u_k)

        def step(x, u_k, theta):
            return rk4_step(lambda s, v: field(s, v, theta), x, u_k, dt)

        self.steps = vmap(step, in_dims=(0, 0, None))
        self.step_jacobians = vmap(jacrev(step, argnums=(0, 2)), in_dims=(0, 0, None))
        self.measurement_jacobians = vmap(jacrev(lambda x, u_k: system.h(x, u_k)))

    def _unflatten(self, theta):
        out, offset = {}, 0
        for name, shape in zip(self.names, self.shapes):
            size = int(np.prod(shape))
            out[name] = theta[offset:offset + size].reshape(shape)
            offset += size
        return out

    def theta0(self) -> np.ndarray:
        return np.concatenate([p.detach().numpy().ravel() for p in self.mlp.parameters()])

    def load(self, theta: np.ndarray) -> None:
        """Write θ into the network (its export is the trained residual)."""
        import torch

        with torch.no_grad():
            for param, value in zip(self.mlp.parameters(), self._unflatten(torch.as_tensor(theta)).values()):
                param.copy_(value)

    def residuals(self, states: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import torch

        x, th = torch.as_tensor(states), torch.as_tensor(theta)
        with torch.no_grad():
            r_m = ((self.y - self.h(x, self.u)) * self.inv_sigma_r).numpy()
            r_q = (x[1:] - self.steps(x[:-1], self.u[:-1], th)).numpy() * self.inv_sigma_q
        return r_m, r_q

    def cost(self, states: np.ndarray, theta: np.ndarray) -> float:
        """J / 2 per sample."""
        r_m, r_q = self.residuals(states, theta)
        return 0.5 * float((r_m**2).sum() + (r_q**2).sum() + self.weight_prior * theta @ theta) / len(states)

    def jacobians(self, states: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened h_k (T, m, n), a_k (T-1, n, n), b_k (T-1, n, P)."""
        import torch

        x, th = torch.as_tensor(states), torch.as_tensor(theta)
        a, b = self.step_jacobians(x[:-1], self.u[:-1], th)
        h = self.measurement_jacobians(x, self.u).numpy() * self.inv_sigma_r.numpy()[None, :, None]
        return h, a.numpy() * self.inv_sigma_q[None, :, None], b.numpy() * self.inv_sigma_q[None, :, None]


def normal_equations(problem: _JointProblem, states: np.ndarray, theta: np.ndarray) -> dict:
    """The Gauss–Newton system of J at (states, θ): JᵀJ's parts and the gradient Jᵀr.

    Returns
    -------
    dict
        ``transition`` A_k (T-1, n, n) (unwhitened ∂x_{k+1}/∂x_k of the model's step), ``measurement`` the
        whitened H_k (T, m, n), ``border`` (T, n, P) and ``corner`` (P, P) of JᵀJ (the corner with the weight
        prior), ``grad_x`` (T, n) and ``grad_theta`` (P,) of Jᵀr.
    """
    r_m, r_q = problem.residuals(states, theta)
    h, a, b = problem.jacobians(states, theta)      # whitened: a = W A, b = W B with W = diag(1/σ_Q)
    w = np.diag(problem.inv_sigma_q)
    # process row k: ∂/∂x_k = -a_k, ∂/∂x_{k+1} = W, ∂/∂θ = -b_k; measurement row k: ∂/∂x_k = -h_k
    border = np.zeros((*states.shape, theta.size))
    border[:-1] += np.einsum("kmi,kmp->kip", a, b)
    border[1:] -= np.einsum("mi,kmp->kip", w, b)
    grad_x = -np.einsum("kmi,km->ki", h, r_m)
    grad_x[:-1] -= np.einsum("kmi,km->ki", a, r_q)
    grad_x[1:] += r_q @ w
    return {"transition": a / problem.inv_sigma_q[None, :, None], "measurement": h, "border": border,
            "corner": np.einsum("kmp,kmq->pq", b, b) + problem.weight_prior * np.eye(theta.size),
            "grad_x": grad_x, "grad_theta": -np.einsum("kmp,km->p", b, r_q) + problem.weight_prior * theta}


def _levenberg_marquardt(problem: _JointProblem, states: np.ndarray, theta: np.ndarray, iterations: int,
                         progress: Callable[[int, float], None] | None) -> tuple[np.ndarray, np.ndarray, list]:
    """Marquardt-scaled damping (λ_LM diag(JᵀJ)), raised ×5 until a step lowers J, lowered ×3 after it.

    Returns the states, θ and J/2 per sample after each step taken (empty when none lowered J)."""
    T, n = states.shape
    m = problem.y.shape[1]
    # the MHE's compiled block Cholesky (estimators/native/btd.c): R⁻¹ = I (H is whitened), m + n rows for the damping
    solver = BlockTridiagonal(n, m + n, T, np.diag(problem.inv_sigma_q**2), np.eye(m + n))
    cost, damping, losses = problem.cost(states, theta), 1e-3, []
    if not np.isfinite(cost):
        raise InvalidInput("joint training cannot start: the objective is not finite at the observer's states")
    for iteration in range(iterations):
        equations = normal_equations(problem, states, theta)
        taken = False
        while damping < 1e10:
            try:
                step_x, step_theta = solve_bordered_tridiagonal(
                    solver, equations["transition"], equations["measurement"], equations["border"],
                    equations["corner"], -equations["grad_x"], -equations["grad_theta"], damping)
                trial = problem.cost(states + step_x, theta + step_theta)
            except np.linalg.LinAlgError:   # round-off lost positive definiteness: damp harder
                trial = np.inf
            if trial < cost:
                decrease = (cost - trial) / cost
                states, theta, cost, taken = states + step_x, theta + step_theta, trial, True
                damping = max(damping / 3, 1e-9)
                break
            damping *= 5
        if not taken:
            break
        losses.append(cost)
        if progress:
            progress(iteration + 1, cost)
        if decrease < RELATIVE_TOLERANCE:
            break
    return states, theta, losses


def solve_bordered_tridiagonal(solver, transition: np.ndarray, measurement: np.ndarray, border: np.ndarray,
                               corner: np.ndarray, rhs_x: np.ndarray, rhs_theta: np.ndarray,
                               damping: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Solve [[M, C], [Cᵀ, S]] [δx; δθ] = [r_x; r_θ] for the joint fit's Gauss–Newton matrix.

    M is the full-record MHE's matrix (no arrival cost): diagonal blocks M_k = H_kᵀH_k + [k < T-1] A_kᵀQ⁻¹A_k
    + [k > 0] Q⁻¹, off-diagonal blocks M_{k,k+1} = -A_kᵀQ⁻¹.  With damping λ_LM > 0 the diagonals of M and S
    are scaled by (1 + λ_LM) (Marquardt).  M is factored by the MHE's block Cholesky (`BlockTridiagonal`,
    compiled C; the damping enters as extra measurement rows), the θ part through the Schur complement.

    Parameters
    ----------
    solver : estimators.mhe_gn.BlockTridiagonal
        Built for n states, m + n measurement rows, at least T nodes, R⁻¹ = I; its Q⁻¹ is the Q⁻¹ of M.
    transition : ndarray, shape (T-1, n, n)
        A_k = ∂x_{k+1}/∂x_k of the model's step.
    measurement : ndarray, shape (T, m, n)
        H_k, whitened (R = I).
    border : ndarray, shape (T, n, P)
        C, by state block.
    corner : ndarray, shape (P, P)
        S (symmetric).
    rhs_x : ndarray, shape (T, n)
    rhs_theta : ndarray, shape (P,)
    damping : float

    Returns
    -------
    (δx (T, n), δθ (P,))

    Raises
    ------
    ValueError
        If the shapes do not fit each other or the solver (its compiled code would read out of bounds).
    numpy.linalg.LinAlgError
        If the matrix is not positive definite.
    """
    T, n = rhs_x.shape
    P = rhs_theta.size
    m = measurement.shape[1]
    if (solver.n, solver.m) != (n, m + n) or T > solver.Lmax or transition.shape != (T - 1, n, n) or \
            measurement.shape != (T, m, n) or border.shape != (T, n, P) or corner.shape != (P, P):
        raise ValueError(f"solve_bordered_tridiagonal: shapes do not fit a solver for n={solver.n}, m+n={solver.m}")
    q_inv = solver.Qi
    diagonal = np.einsum("kmi,kmi->ki", measurement, measurement)         # diag(M_k), for Marquardt's scaling
    diagonal[:-1] += np.einsum("kji,jl,kli->ki", transition, q_inv, transition)
    diagonal[1:] += np.diag(q_inv)
    damped = np.zeros((T, n, n))
    damped[:, np.arange(n), np.arange(n)] = np.sqrt(damping * diagonal + 1e-12)   # + 1e-12: a state no row reaches
    rows = np.ascontiguousarray(np.concatenate([measurement, damped], axis=1))
    transitions = np.zeros((T, n, n))     # the solver reads one per node; the last node has none
    transitions[:-1] = transition
    factor = solver.factor(T, transitions, rows, np.zeros((n, n)))
    flat_border = border.reshape(T * n, P)
    solved = np.stack([solver.solve(factor, column.reshape(T, n)).ravel()
                       for column in np.concatenate([flat_border, rhs_x.reshape(-1, 1)], axis=1).T], axis=1)
    m_inv_c, m_inv_r = solved[:, :P], solved[:, P]
    schur = corner - flat_border.T @ m_inv_c
    schur[np.arange(P), np.arange(P)] += damping * np.diag(corner) + 1e-12
    step_theta = np.linalg.solve(schur, rhs_theta - flat_border.T @ m_inv_r)
    step_x = m_inv_r - m_inv_c @ step_theta
    return step_x.reshape(T, n), step_theta
