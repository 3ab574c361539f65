"""Algorithm 1's training on several records at once: one residual, or an ensemble of them side by side.

`train_knode_pooled` trains one residual on several records (flights of one vehicle): the one-step pairs
of every training record form one pooled loss (8), stepped by one batched RK4 whose step length is each
pair's own record's dt (Adam on shuffled mini-batches of `POOLED_BATCH_PAIRS` pairs drawn across records), and
validation holds out whole records.  Why whole records: time blocks of a flight share its battery, its heating
and its observer's artefacts with the rest of it, so a residual that learned the flight passes their test; a
flight it never saw does not share them.

`train_members_pooled` trains K residuals so, each from its own seed (its initial weights and its mini-batch
order), as one stacked network (`models.residual_net.StackedResidualNet`): each member's loss, gradient, Adam
update and kept epoch are its own, as if it were trained alone, at little more than one member's cost.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput

from .cores import usable_cores
from .envelope import training_envelope
from .knode import HybridModel
from .presets import TrainingConfig
from .systems import System
from .training import TrainingResult, _checked_record, learned_meta, new_residual


@dataclass
class TrainingRecord:
    """One record's Algorithm-1 data for `train_knode_pooled`.

    Attributes
    ----------
    name : str
        The record's name (a flight's), for messages and the model's lineage.
    zeta : array_like, shape (T, n)
        State observations of its pre-training observer, in the system's state units.
    u : array_like, shape (T, n_inputs)
        Its inputs, held over each step (width 0 for an input-free system).
    dt : float
        Its sample period, s.
    """

    name: str
    zeta: ArrayLike
    u: ArrayLike
    dt: float


_ONE_THIRD = 1 / 3
# Pooled training with ``batch_size`` 0 takes Adam steps on shuffled mini-batches of this many one-step pairs
# (about 40 s of flight at 100 Hz; every pair when there are fewer), not one full-batch step per epoch: one step
# per epoch was the paper's setting for one flight of a few thousand pairs, and pooling many flights would keep
# the number of steps and only slow each one down: in the same epochs, mini-batches reach the held-out loss that
# full-batch steps reach only in several times as many (benchmarks/results/pooled_training.md).
POOLED_BATCH_PAIRS = 4096


def _checked_records(system: System, records: list[TrainingRecord], held_out: list[bool],
                     config: TrainingConfig) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """`train_knode_pooled`'s records checked (each by `_checked_record`): ``[(zeta (T, n), u (T, n_inputs), dt s)]``;
    InvalidInput when they, ``held_out`` or ``config.epochs`` cannot be trained on."""
    if len(held_out) != len(records):
        raise InvalidInput(f"held_out has {len(held_out)} entries for {len(records)} records")
    if not records or all(held_out):
        raise InvalidInput("pooled training needs at least one record to train on (every record is held out)")
    return [_checked_record(system, r.zeta, r.u, r.dt, config, r.name) for r in records]


def _pooled_pairs(checked: list, held_out: list[bool], which: bool):
    """The one-step pairs of the records held out (``which`` True) or trained on, as tensors
    ``(z_now, u_now, z_next, step)`` with each pair's dt (P, 1) s; None when there are no such records."""
    import torch

    chosen = [c for c, held in zip(checked, held_out) if held == which]
    if not chosen:
        return None
    z_now = torch.as_tensor(np.concatenate([z[:-1] for z, _, _ in chosen]))
    u_now = torch.as_tensor(np.concatenate([u[:-1] for _, u, _ in chosen]))
    z_next = torch.as_tensor(np.concatenate([z[1:] for z, _, _ in chosen]))
    step = torch.as_tensor(np.concatenate([np.full((len(z) - 1, 1), dt) for z, _, dt in chosen]))
    return z_now, u_now, z_next, step


def _per_record_losses(errors, records: list[TrainingRecord], checked: list, held_out: list[bool]) -> dict:
    """{name: mean squared one-step error} of each held-out record, from ``errors`` (P,) of their pairs in
    order."""
    per_record, offset = {}, 0
    for record, (zeta, _, _), held in zip(records, checked, held_out):
        if held:
            per_record[record.name] = errors[offset:offset + len(zeta) - 1].mean().item()
            offset += len(zeta) - 1
    return per_record


def _rk4_38(field_fn, x, u, dt):
    """One step of torchdiffeq's "rk4" (the 3/8 rule, `rk4_alt_step_func`) of an autonomous x' = f(x, u) with
    a step per row: ``dt`` (B, 1) s.  Same arithmetic as `odeint(..., method="rk4")` over [0, dt]."""
    k1 = field_fn(x, u)
    k2 = field_fn(x + dt * k1 * _ONE_THIRD, u)
    k3 = field_fn(x + dt * (k2 - k1 * _ONE_THIRD), u)
    k4 = field_fn(x + dt * (k1 - k2 + k3), u)
    return x + (k1 + 3 * (k2 + k3) + k4) * dt * 0.125


def train_knode_pooled(system: System, records: list[TrainingRecord], held_out: list[bool],
                       config: TrainingConfig | None = None,
                       progress: Callable[[int, float], None] | None = None) -> TrainingResult:
    """Fit one Δθ to the one-step pairs of several records at once (eqs. 7-8 with one pooled loss),
    validating on whole held-out records.

    Every pair (ζ_i, u_i, ζ_{i+1}) of every training record weighs the same in the loss (a longer flight
    brings more pairs); pairs never cross records.  Each epoch passes once over all training pairs in shuffled
    mini-batches, each one batched RK4 with every pair stepped by its own record's dt.  The
    residual's input standardisation and the training envelope come from the training records only.

    Parameters
    ----------
    system : System
        The prior shared by every record (the same vehicle).
    records : list of TrainingRecord
        The records, each with at least 3 observations.
    held_out : list of bool
        Per record: True to hold it out whole for validation.  At least one record must be trained on;
        with none held out nothing is validated and the last epoch is kept.
    config : TrainingConfig, optional
        Default ``TrainingConfig()``; ``validation_fraction`` and ``validation_layout`` are not used (the
        held-out records are the validation); ``batch_size`` 0 means mini-batches of `POOLED_BATCH_PAIRS`
        pairs (all of them when there are fewer), recorded in the meta as ``batch_pairs``.
    progress : callable, optional
        Called as ``progress(epoch, mean_training_loss)`` after every epoch.

    Returns
    -------
    TrainingResult
        Its model's meta as `train_knode`'s, plus ``validation`` ("held-out records"),
        ``validation_losses_per_record`` {name: loss of the kept weights on that held-out record},
        ``training_records`` and ``validation_records`` (names).

    Raises
    ------
    InvalidInput
        On a bad record (shapes, non-finite values, fewer than 3 observations, bad dt), a ``held_out``
        of another length, every record held out, or ``epochs < 1``.
    """
    return train_members_pooled(system, records, held_out, config, 1, progress)[0]


def train_members_pooled(system: System, records: list[TrainingRecord], held_out: list[bool],
                         config: TrainingConfig | None = None, members: int = 1,
                         progress: Callable[[int, float], None] | None = None) -> list[TrainingResult]:
    """``members`` residuals trained as `train_knode_pooled` trains one, member k from seed ``config.seed + k``,
    as stacked networks, one group of members per core, each group on its own thread (module docstring).

    Parameters
    ----------
    system, records, held_out, config
        As `train_knode_pooled`'s.
    members : int
        How many residuals (1 trains the plain network, exactly as `train_knode_pooled`).
    progress : callable, optional
        ``progress(epoch, mean training loss of the first group's members)`` after every epoch of that group.

    Returns
    -------
    list of TrainingResult
        One per member, as `train_knode_pooled` returns it, its meta's ``training`` with its own seed;
        ``seconds`` is the wall time of training them all.

    Raises
    ------
    InvalidInput
        As `train_knode_pooled`, and for ``members`` below 1.
    """
    from . import residual_net

    if members < 1:
        raise InvalidInput(f"an ensemble needs at least one member, got {members}")
    with residual_net.torch_threads(residual_net.TRAINING_THREADS):
        return _train_members(system, records, held_out, config or TrainingConfig(), members, progress)


def _repeated(data, members: int):
    """``data``'s columns with their rows repeated ``members`` times (each member scores every pair)."""
    return data if members == 1 or data is None else tuple(column.repeat(members, 1) for column in data)


@dataclass
class _MemberFit:
    """One member's training: its losses per epoch, the prior's held-out loss, and its kept weights."""

    losses: list[float]
    validation_losses: list[float]
    prior_loss: float | None
    best: tuple[float, dict | None, int]      # (held-out loss, weights, epoch); weights None: nothing held out


def _fit_members(system: System, nets: list, seeds: list[int], fit_data, val_data, config: TrainingConfig,
                 batch: int, progress: Callable[[int, float], None] | None) -> list[_MemberFit]:
    """The epochs of `train_members_pooled` for ``nets`` (one plain network, or several stacked), member k's
    mini-batches drawn by its own seed ``seeds[k]``."""
    import torch

    from .residual_net import Adam, StackedResidualNet

    members = len(nets)
    net = nets[0] if members == 1 else StackedResidualNet(nets)
    val_rows, full, n_fit = _repeated(val_data, members), _repeated(fit_data, members), len(fit_data[0])

    def member_losses(data):      # (K,): each member's mean squared error over its own rows
        errors = _squared_errors(system, net, data)
        return errors.mean()[None] if members == 1 else errors.reshape(members, -1).mean(dim=1)

    def states():
        return [{k: v.clone() for k, v in net.state_dict().items()}] if members == 1 else net.member_states()

    optimizer = Adam(net.parameters(), lr=config.lr)
    generators = [torch.Generator().manual_seed(seed) for seed in seeds]
    fits = [_MemberFit([], [], None, (float("inf"), None, -1)) for _ in range(members)]
    if val_rows is not None:  # epoch -1 is the prior itself: training must beat it on the held-out records
        with torch.no_grad():
            at_prior, initial = member_losses(val_rows).tolist(), states()
        for fit, loss, state in zip(fits, at_prior, initial):
            fit.prior_loss, fit.best = loss, (loss, state, -1)
    for epoch in range(config.epochs):
        orders = [torch.randperm(n_fit, generator=g) for g in generators] if batch < n_fit else None
        epoch_loss = np.zeros(members)
        for start in range(0, n_fit, batch):
            rows = full if orders is None else \
                tuple(column[torch.cat([order[start:start + batch] for order in orders])] for column in fit_data)
            loss = member_losses(rows)
            optimizer.zero_grad()
            loss.sum().backward()
            optimizer.step()
            epoch_loss += np.asarray(loss.tolist()) * min(batch, n_fit - start)
        for fit, total in zip(fits, epoch_loss):
            fit.losses.append(float(total / n_fit))
        if val_rows is not None:
            with torch.no_grad():
                scores = member_losses(val_rows).tolist()
            current = states() if any(sc < fit.best[0] for sc, fit in zip(scores, fits)) else []
            for k, (fit, score) in enumerate(zip(fits, scores)):
                fit.validation_losses.append(score)
                if score < fit.best[0]:
                    fit.best = (score, current[k], epoch)
        if progress:
            progress(epoch, float(np.mean(epoch_loss) / n_fit))
    final = states()
    for fit, state in zip(fits, final):
        if fit.best[1] is None:     # nothing held out: the last epoch is kept
            fit.best = (fit.best[0], state, config.epochs - 1)
    return fits


def _groups(members: int) -> list[list[int]]:
    """The members split into one contiguous group per core (at most), each trained on its own thread: torch
    releases the interpreter's lock inside its operations, and one stacked group keeps one core busy."""
    count = max(1, min(members, usable_cores()))
    return [[int(k) for k in chunk] for chunk in np.array_split(np.arange(members), count)]


def _train_members(system: System, records: list[TrainingRecord], held_out: list[bool], config: TrainingConfig,
                   members: int, progress: Callable[[int, float], None] | None) -> list[TrainingResult]:
    import torch

    checked = _checked_records(system, records, held_out, config)
    train_zeta = np.concatenate([z for (z, _, _), held in zip(checked, held_out) if not held])
    train_u = np.concatenate([u for (_, u, _), held in zip(checked, held_out) if not held])
    nets = []
    for k in range(members):    # each member's initial weights from its own seed, as if trained alone
        torch.manual_seed(config.seed + k)
        nets.append(new_residual(system, train_zeta, train_u, config.hidden, config.residual_frame))
    fit_data, val_data = _pooled_pairs(checked, held_out, False), _pooled_pairs(checked, held_out, True)
    batch = min(config.batch_size or POOLED_BATCH_PAIRS, len(fit_data[0]))
    started = time.perf_counter()
    groups = _groups(members)

    def fit_group(index: int) -> list[_MemberFit]:   # the first group reports the progress
        group = groups[index]
        return _fit_members(system, [nets[k] for k in group], [config.seed + k for k in group], fit_data, val_data,
                            config, batch, progress if index == 0 else None)

    if len(groups) == 1:
        fits = fit_group(0)
    else:
        with ThreadPoolExecutor(max_workers=len(groups)) as pool:
            fits = [fit for part in pool.map(fit_group, range(len(groups))) for fit in part]
    seconds = time.perf_counter() - started
    results = []
    for k, (member, fit) in enumerate(zip(nets, fits)):
        member.load_state_dict(fit.best[1])
        per_record = {}
        if val_data is not None:
            with torch.no_grad():
                per_record = _per_record_losses(_squared_errors(system, member, val_data), records, checked,
                                                held_out)
        residual = member.export()
        best_epoch = fit.best[2]
        model = HybridModel(system, "knode", residual,
                            meta={"training": replace(config, seed=config.seed + k).as_dict(),
                                  "final_loss": fit.losses[-1], "seconds": seconds, "best_epoch": best_epoch,
                                  "best_validation_loss": fit.best[0] if val_data is not None else None,
                                  "prior_validation_loss": fit.prior_loss,
                                  "validation": "held-out records" if val_data is not None else "none",
                                  "batch_pairs": batch, "validation_losses_per_record": per_record,
                                  "training_records": [r.name for r, held in zip(records, held_out) if not held],
                                  "validation_records": [r.name for r, held in zip(records, held_out) if held],
                                  "envelope": training_envelope(train_zeta, train_u,
                                                                [*system.state_names, *system.input_names],
                                                                system.invariant_states, residual),
                                  **learned_meta(best_epoch, validated=val_data is not None)})
        results.append(TrainingResult(model, fit.losses, seconds, fit.validation_losses))
    return results


def _squared_errors(system: System, net, data):
    """Per-pair squared one-step errors (P,) of ``system``'s prior plus ``net`` on ``data`` (z_now, u_now, z_next,
    step): one RK4 step of eq. (7) from each pair, scored by eq. (8)."""
    x0, u0, target, step = data
    prediction = _rk4_38(lambda x, u: system.f_prior(x, u) + net.rates(x, u), x0, u0, step)
    return ((prediction - target) ** 2).sum(dim=-1)
