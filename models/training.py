"""Algorithm 1, Phase 1: pre-training observer -> state observations ζ -> one-step predictions (7)
with torchdiffeq's RK4 -> loss (8) -> Adam -> discrete hybrid model f_h = RK4(f_prior + Δθ*).

`train_knode` is the paper's protocol on one record (validation: time blocks of that record); training on
several records at once is `models.pooled_training`'s.

Either way the kept weights are those of the epoch that predicted the held-out data best, epoch -1 being
the prior itself (Δθ ≡ 0); a model whose best epoch is -1 learned nothing that helps, and says so
(``meta["learned"]`` False, `NOT_LEARNED`).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput

from . import residual_frame
from .checks import check_dt, check_sequence
from .envelope import training_envelope
from .knode import HybridModel
from .presets import TrainingConfig
from .systems import System

if TYPE_CHECKING:
    import torch


@dataclass
class TrainingResult:
    """What `train_knode` returns.

    Attributes
    ----------
    model : HybridModel
        The ``"knode"`` model with the kept weights; its meta holds the config, final loss, seconds,
        best epoch, best validation loss, the prior's validation loss (``prior_validation_loss``), ``learned``
        and the training ``envelope`` (`models.envelope`).
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

    @property
    def learned(self) -> bool:
        """False when held-out prediction never improved on the prior (the model equals its prior)."""
        return bool(self.model.meta.get("learned", True))


# What every training surface says of a model whose residual was never kept (best epoch -1).
NOT_LEARNED = "the residual did not improve held-out prediction; this version equals its prior"


# What a model trained with nothing held out says instead: it kept its last epoch, unchecked.
NOT_CHECKED = "nothing was held out, so whether the residual improves prediction was not checked"


def learned_meta(best_epoch: int, validated: bool = True) -> dict:
    """``learned`` (bool) and, when False, ``learned_note`` (`NOT_LEARNED`) for a model's meta: the kept
    epoch is -1 exactly when no epoch predicted the held-out data better than the prior (Δθ ≡ 0).  Without
    held-out data (``validated`` False) ``learned`` is True with the note `NOT_CHECKED`."""
    if not validated:
        return {"learned": True, "learned_note": NOT_CHECKED}
    learned = best_epoch != -1
    return {"learned": learned, **({} if learned else {"learned_note": NOT_LEARNED})}


def _split_rows(pairs: int, fraction: float, layout: str):
    """(fit rows, validation rows) as index tensors; validation is contiguous time, never random samples."""
    import torch

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


def new_residual(system: System, zeta: np.ndarray, u: np.ndarray, hidden: int, frame: str = ""):
    """A `models.residual_net.ResidualNet` at Δθ ≡ 0 in ``frame`` ("": the system's `residual_frame`).

    Its input features (state frame: [ζ, u] (T, n + p), with the system's masks) are standardised by the
    training records' own mean and spread (constant columns left unscaled)."""
    from .residual_net import ResidualNet

    frame = residual_frame.check_frame(frame or system.residual_frame, system.n, system.n_inputs)
    features = residual_frame.features(frame, np.asarray(zeta, dtype=float), np.asarray(u, dtype=float))
    std = features.std(axis=0)
    n_in, n_out = residual_frame.feature_count(frame, system.n, system.n_inputs)
    input_mask, output_mask = system.residual_masks() if frame == "state" else \
        (np.array(residual_frame.body_input_mask(system.residual_blind)), None)
    return ResidualNet(n_in, n_out, hidden, features.mean(axis=0), np.where(std > 1e-9, std, 1.0), input_mask,
                       output_mask, frame=frame)


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
    from . import residual_net  # torch, on first use (module docstring of residual_net)

    with residual_net.torch_threads(residual_net.TRAINING_THREADS):
        return _train_knode(system, zeta, u, dt, config or TrainingConfig(), progress)


def _train_knode(system: System, zeta: ArrayLike, u: ArrayLike, dt: float, config: TrainingConfig,
                 progress: Callable[[int, float], None] | None) -> TrainingResult:
    import torch
    from torchdiffeq import odeint

    from .residual_net import Adam

    zeta, u, dt = _checked_record(system, zeta, u, dt, config)
    torch.manual_seed(config.seed)
    mlp = new_residual(system, zeta, u, config.hidden, config.residual_frame)

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
            return system.f_prior(x, u0) + mlp.rates(x, u0)

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
    prior_loss = best[0] if n_val else None
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
    residual = mlp.export()
    model = HybridModel(system, "knode", residual,
                        meta={"training": config.as_dict(), "final_loss": losses[-1], "seconds": seconds,
                              # the epoch whose weights are kept: the last one when nothing is held out
                              "best_epoch": best[2] if n_val else config.epochs - 1,
                              "best_validation_loss": best[0] if n_val else None,
                              "prior_validation_loss": prior_loss,   # the held-out loss of the prior (Δθ ≡ 0)
                              # where the training data lie: evaluations report records outside it
                              "envelope": training_envelope(zeta, u, [*system.state_names, *system.input_names],
                                                            system.invariant_states, residual),
                              **learned_meta(best[2] if n_val else config.epochs - 1, validated=bool(n_val))})
    return TrainingResult(model, losses, seconds, val_losses)


# The residual inputs a pooled model is blind to besides the system's own (`System.residual_blind`): the attitude.
# Why: the mocap tilt of a quadrotor is its horizontal acceleration (tilt ≈ a_h / g), so a residual reading the
# attitude reads the acceleration state the Crazyflie prior already hides from it, and learns how that state evolves
# along the training trajectories rather than the vehicle.  Trained on circles, helices and ramps that all turn one
# way, such a residual pulls the acceleration it settles on (tau_s Δθ) inwards along the tilt, and further on a
# family whose tilt spreads wider (figure-eights), whose open-loop position prediction it makes worse where a residual
# blind to the attitude makes it better.  Flights of the trained families cannot show this: they prefer seeing the
# attitude (the results page `docs/results/family-holdout.md`, "Blind to the attitude").
# The prior keeps the attitude's physics: it turns the thrust by R(q).
ATTITUDE_INPUTS = ("qx", "qy", "qz", "qw")


# The battery voltage is a flight's condition, not the vehicle's: its range in a training set is whichever batteries
# were flown, each flight sweeps its own stretch of it as it drains (a residual reading it can tell flights and times
# apart), and the prior already carries its physics (the thrust map's battery term and each flight's thrust gain).
BATTERY_INPUTS = ("vbat",)


def attitude_blind(system: System, battery: bool = False) -> System:
    """``system`` with its residual also blind to the attitude inputs (`ATTITUDE_INPUTS`) it has, and with
    ``battery`` to the battery voltage (`BATTERY_INPUTS`); unchanged when it has none (the kinematic quadrotor).
    Only the masks change: the prior, its parameters and the state are the same, and the trained residual's first
    layer carries exact zeros on those inputs."""
    from dataclasses import replace

    names = (*ATTITUDE_INPUTS, *(BATTERY_INPUTS if battery else ()))
    extra = tuple(k for k in names if k in system.input_names and k not in system.residual_blind)
    return replace(system, residual_blind=(*system.residual_blind, *extra)) if extra else system


def _checked_record(system: System, zeta: ArrayLike, u: ArrayLike, dt: float,
                    config: TrainingConfig, name: str = "") -> tuple[np.ndarray, np.ndarray, float]:
    """One record's training data checked: ``(zeta (T, n), u (T, n_inputs), dt s)``; InvalidInput (its
    message starting with the record's ``name`` when given) when they or ``config.epochs`` cannot be trained on."""
    label = f"{name}: " if name else ""
    zeta = check_sequence(f"{label}zeta", zeta, cols=system.n)
    u = check_sequence(f"{label}u", np.asarray(u, dtype=float).reshape(len(zeta), -1), rows=len(zeta),
                       cols=system.n_inputs)
    if len(zeta) < 3:
        raise InvalidInput(f"{label}training needs at least 3 state observations, got {len(zeta)}")
    dt = check_dt(dt)
    if config.epochs < 1:
        raise InvalidInput(f"epochs must be at least 1, got {config.epochs}")
    return zeta, u, dt
