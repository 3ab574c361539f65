"""Algorithm 1, Phase 1: pre-training observer -> state observations ζ -> one-step predictions (7)
with torchdiffeq's RK4 -> loss (8) -> Adam -> discrete hybrid model f_h = RK4(f_prior + Δθ*)."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import ArrayLike
from torchdiffeq import odeint

from learnest.errors import InvalidInput

from .checks import check_dt, check_sequence
from .knode import HybridModel, Residual
from .presets import TrainingConfig
from .systems import System

# Δθ is a one-hidden-layer MLP on a few thousand rows: each operation is microseconds of work, and on
# these 2-core machines torch's intra-op threads cost more in hand-offs than they save (with the Adam
# below, training on a 33-s flight went from 48.6 s to 6.6 s under load: benchmarks/results/training_speed.md).
TRAINING_THREADS = 1


@contextmanager
def _torch_threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` torch intra-op threads, then restore the caller's setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class Adam:
    """``torch.optim.Adam``'s default CPU update (single-tensor path, no weight decay, no amsgrad), the
    same operations in the same order, so the weights are bit-identical (tests/test_knode.py checks it).

    Why not torch.optim: its first ``step()`` imports ``torch._dynamo`` (3-4 s on these machines), longer
    than a whole 150-epoch training run; the update itself is five tensor operations.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params = [p for p in params]
        self.lr, (self.beta1, self.beta2), self.eps = lr, betas, eps
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.steps = 0

    def zero_grad(self) -> None:
        """Drop the gradients (as ``torch.optim`` does by default: set to None, not zeroed)."""
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One Adam update of every parameter that has a gradient."""
        self.steps += 1
        step_size = self.lr / (1 - self.beta1**self.steps)
        bias_correction2_sqrt = (1 - self.beta2**self.steps) ** 0.5
        for param, exp_avg, exp_avg_sq in zip(self.params, self.exp_avg, self.exp_avg_sq):
            if param.grad is None:
                continue
            grad = param.grad
            exp_avg.lerp_(grad, 1 - self.beta1)
            exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
            denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
            param.addcdiv_(exp_avg, denom, value=-step_size)


@dataclass
class TrainingResult:
    """What `train_knode` returns.

    Attributes
    ----------
    model : HybridModel
        The ``"knode"`` model with the kept weights; its meta holds the config, final loss, seconds,
        best epoch and best validation loss.
    losses : list of float
        Mean training loss (eq. 8) per epoch.
    seconds : float
        Wall time of the training loop, s.
    validation_losses : list of float
        Held-out loss per epoch (empty when nothing is held out).
    """

    model: HybridModel
    losses: list = field(default_factory=list)
    seconds: float = 0.0
    validation_losses: list = field(default_factory=list)


class _MLP(torch.nn.Module):
    """Δθ with fixed input standardisation (from the training data) so tanh sees O(1) inputs."""

    mean: torch.Tensor  # buffers registered in __init__
    std: torch.Tensor

    def __init__(self, n_in: int, n_out: int, hidden: int, mean: np.ndarray, std: np.ndarray):
        super().__init__()
        self.hidden_layer = torch.nn.Linear(n_in, hidden, dtype=torch.float64)
        self.output_layer = torch.nn.Linear(hidden, n_out, dtype=torch.float64)
        torch.nn.init.zeros_(self.output_layer.weight)  # start at the prior: Δθ ≡ 0
        torch.nn.init.zeros_(self.output_layer.bias)
        self.register_buffer("mean", torch.as_tensor(mean))
        self.register_buffer("std", torch.as_tensor(std))

    def forward(self, z):
        return self.output_layer(torch.tanh(self.hidden_layer((z - self.mean) / self.std)))

    def export(self) -> Residual:
        """Fold the standardisation into the first layer: W(z-m)/s + b = (W/s) z + (b - W m/s)."""
        w1 = self.hidden_layer.weight.detach().numpy() / self.std.numpy()
        b1 = self.hidden_layer.bias.detach().numpy() - w1 @ self.mean.numpy()
        return Residual([(w1.copy(), b1.copy()),
                         (self.output_layer.weight.detach().numpy().copy(),
                          self.output_layer.bias.detach().numpy().copy())])


def _split_rows(pairs: int, fraction: float, layout: str):
    """(fit rows, validation rows) as index tensors; validation is contiguous time, never random samples."""
    if layout not in ("tail", "spread"):
        raise InvalidInput(f"validation_layout must be 'tail' or 'spread', got {layout!r}")
    held = np.zeros(pairs, dtype=bool)
    n_val = int(round(fraction * pairs))
    if n_val:
        if layout == "tail":
            held[pairs - n_val:] = True
        else:
            half = n_val // 2
            for centre in (0.35, 0.85):
                start = int(centre * pairs) - half // 2
                held[start:start + half] = True
    return torch.as_tensor(np.flatnonzero(~held)), torch.as_tensor(np.flatnonzero(held))


def train_knode(system: System, zeta: ArrayLike, u: ArrayLike, dt: float, config: TrainingConfig | None = None,
                progress: Callable[[int, float], None] | None = None) -> TrainingResult:
    """Fit Δθ so that one RK4 step of f_prior + Δθ from ζ_i lands on ζ_{i+1} (eqs. 7-8).

    Parameters
    ----------
    system : System
        Supplies the prior f_prior and the state size n.
    zeta : array_like, shape (T, n)
        State observations ζ (from a pre-training observer), in the system's state units.
    u : array_like, shape (T, n_inputs)
        Inputs, held over each step (may have width 0).
    dt : float
        Sample period, s.
    config : TrainingConfig, optional
        Default ``TrainingConfig()``.
    progress : callable, optional
        Called as ``progress(epoch, mean_training_loss)`` after every epoch.

    Returns
    -------
    TrainingResult

    Raises
    ------
    InvalidInput
        On wrong shapes, non-finite values, fewer than 3 observations, a bad ``dt``, ``epochs < 1`` or an
        unknown validation layout.
    """
    with _torch_threads(TRAINING_THREADS):
        return _train_knode(system, zeta, u, dt, config or TrainingConfig(), progress)


def _train_knode(system: System, zeta: ArrayLike, u: ArrayLike, dt: float, config: TrainingConfig,
                 progress: Callable[[int, float], None] | None) -> TrainingResult:
    zeta = check_sequence("zeta", zeta, cols=system.n)
    u = check_sequence("u", np.asarray(u, dtype=float).reshape(len(zeta), -1), rows=len(zeta), cols=system.n_inputs)
    if len(zeta) < 3:
        raise InvalidInput(f"training needs at least 3 state observations, got {len(zeta)}")
    dt = check_dt(dt)
    if config.epochs < 1:
        raise InvalidInput(f"epochs must be at least 1, got {config.epochs}")
    torch.manual_seed(config.seed)
    features = np.concatenate([zeta, u], axis=1)
    std = features.std(axis=0)
    mlp = _MLP(features.shape[1], system.n, config.hidden, features.mean(axis=0), np.where(std > 1e-9, std, 1.0))

    pairs = len(zeta) - 1
    fit_rows, val_rows = _split_rows(pairs, config.validation_fraction if pairs >= 10 else 0.0,
                                     config.validation_layout)
    n_fit, n_val = len(fit_rows), len(val_rows)
    z_now, z_next = torch.as_tensor(zeta[:-1]), torch.as_tensor(zeta[1:])
    u_now = torch.as_tensor(u[:-1])
    t_span = torch.tensor([0.0, dt], dtype=torch.float64)

    def rows(idx):
        return z_now[idx], u_now[idx], z_next[idx]

    fit_data, val_data = rows(fit_rows), rows(val_rows)  # gathered once, not every epoch

    def one_step_loss(data):
        x0, u0, target = data

        def vector_field(_t, x):
            return system.f_prior(x, u0) + mlp(torch.cat([x, u0], dim=-1))

        prediction = odeint(vector_field, x0, t_span, method="rk4")[-1]           # eq. (7)
        return ((prediction - target) ** 2).sum(dim=-1).mean()                   # eq. (8)

    optimizer = Adam(mlp.parameters(), lr=config.lr)
    batch = config.batch_size or n_fit
    generator = torch.Generator().manual_seed(config.seed)
    losses, val_losses, started = [], [], time.perf_counter()
    best: tuple[float, dict[str, torch.Tensor] | None, int] = (float("inf"), None, -1)
    if n_val:  # epoch -1 is the prior itself (Δθ starts at zero): training must beat it on held-out data
        with torch.no_grad():
            best = (one_step_loss(val_data).item(),
                    {k: v.clone() for k, v in mlp.state_dict().items()}, -1)
    for epoch in range(config.epochs):
        order = fit_rows[torch.randperm(n_fit, generator=generator)] if batch < n_fit else None
        epoch_loss = 0.0
        for start in range(0, n_fit, batch):
            loss = one_step_loss(fit_data if order is None else rows(order[start:start + batch]))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            epoch_loss += loss.item() * min(batch, n_fit - start)
        losses.append(epoch_loss / n_fit)
        if n_val:
            with torch.no_grad():
                val_losses.append(one_step_loss(val_data).item())
            if val_losses[-1] < best[0]:
                best = (val_losses[-1], {k: v.clone() for k, v in mlp.state_dict().items()}, epoch)
        if progress:
            progress(epoch, losses[-1])
    if best[1] is not None:
        mlp.load_state_dict(best[1])
    seconds = time.perf_counter() - started
    model = HybridModel(system, "knode", mlp.export(),
                        meta={"training": config.as_dict(), "final_loss": losses[-1], "seconds": seconds,
                              # the epoch whose weights are kept: the last one when nothing is held out
                              "best_epoch": best[2] if n_val else config.epochs - 1,
                              "best_validation_loss": best[0] if n_val else None})
    return TrainingResult(model, losses, seconds, val_losses)
