"""The torch side of training: Δθ as a torch module, the Adam update, and the thread setting.

Kept apart from `models.training` so that importing the training API (or anything that imports it) does
not import torch, which takes seconds; `train_knode` imports this module when it runs.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch

from . import residual_frame
from .knode import Residual

# Δθ is a one-hidden-layer MLP on a few thousand rows: each operation is microseconds of work, and on
# these 2-core machines torch's intra-op threads cost more in hand-offs than they save, several times over
# (benchmarks/results/training_speed.md).
TRAINING_THREADS = 1


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` torch intra-op threads, then restore the caller's setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class Adam:
    """``torch.optim.Adam``'s default CPU update (single-tensor path, no weight decay, no amsgrad), the
    same operations in the same order, so the weights are bit-identical (tests/models/test_knode.py checks it).

    Why not torch.optim: its first ``step()`` imports ``torch._dynamo``, which takes longer than a whole
    150-epoch training run; the update itself is five tensor operations.
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


class ResidualNet(torch.nn.Module):
    """Δθ with fixed input standardisation (from the training data) so tanh sees O(1) inputs."""

    mean: torch.Tensor  # buffers registered in __init__
    std: torch.Tensor
    input_mask: torch.Tensor
    output_mask: torch.Tensor

    def __init__(self, n_in: int, n_out: int, hidden: int, mean: np.ndarray, std: np.ndarray,
                 input_mask: np.ndarray | None = None, output_mask: np.ndarray | None = None, frame: str = "state"):
        super().__init__()
        self.frame = frame   # what the network reads and where it acts (`models.residual_frame`)
        self.hidden_layer = torch.nn.Linear(n_in, hidden, dtype=torch.float64)
        self.output_layer = torch.nn.Linear(hidden, n_out, dtype=torch.float64)
        torch.nn.init.zeros_(self.output_layer.weight)  # start at the prior: Δθ ≡ 0
        torch.nn.init.zeros_(self.output_layer.bias)
        self.register_buffer("mean", torch.as_tensor(mean))
        self.register_buffer("std", torch.as_tensor(std))
        # masks (`System.residual_masks`): inputs Δθ does not see, derivatives it does not correct
        self.register_buffer("input_mask", torch.ones(n_in, dtype=torch.float64) if input_mask is None
                             else torch.as_tensor(input_mask, dtype=torch.float64))
        self.register_buffer("output_mask", torch.ones(n_out, dtype=torch.float64) if output_mask is None
                             else torch.as_tensor(output_mask, dtype=torch.float64))

    def forward(self, z):
        """Δθ = m_out ⊙ (W₂ tanh(W₁ (m_in ⊙ (z - mean) / std) + b₁) + b₂).

        Parameters
        ----------
        z : (..., n_in) float64 tensor
            Network inputs, in the units of the training data.

        Returns
        -------
        (..., n_out) float64 tensor
        """
        hidden = torch.tanh(self.hidden_layer(self.input_mask * (z - self.mean) / self.std))
        return self.output_mask * self.output_layer(hidden)

    def rates(self, x, u):
        """Δθ(x, u) as a correction of ẋ (B, n): the network on the frame's features, mapped back to ẋ."""
        return residual_frame.field(self.frame, self, x, u)

    def export(self) -> Residual:
        """Fold the standardisation and the masks into the weights: W(m_in(z-μ)/s) + b = (W m_in/s) z +
        (b - (W m_in/s) μ); masked outputs become zero rows.  The exported network is the trained one."""
        w1 = self.hidden_layer.weight.detach().numpy() * (self.input_mask.numpy() / self.std.numpy())
        b1 = self.hidden_layer.bias.detach().numpy() - w1 @ self.mean.numpy()
        out = self.output_mask.numpy()
        return Residual([(w1.copy(), b1.copy()),
                         (self.output_layer.weight.detach().numpy() * out[:, None],
                          self.output_layer.bias.detach().numpy() * out)], self.frame)


class StackedResidualNet(torch.nn.Module):
    """K `ResidualNet` s of one shape trained side by side as one module: each member's layers are a slice of
    stacked weights, so one batched matrix product evaluates every member on its own rows.

    Why: a residual of 16 hidden units on a mini-batch of a few thousand pairs costs microseconds per operation,
    and training is bound by the number of operations, not their size; K members in one set of operations cost
    little more than one.  The members' parameters are disjoint, so the gradient of the sum of their losses is
    each member's own gradient, and Adam (elementwise) updates each as if it were trained alone.

    Parameters
    ----------
    members : sequence of ResidualNet
        Their initial weights (each from its own seed), one frame, one input standardisation and masks.
    """

    def __init__(self, members) -> None:
        super().__init__()
        members = list(members)
        first = members[0]
        self.frame, self.count = first.frame, len(members)
        for name in ("mean", "std", "input_mask", "output_mask"):
            self.register_buffer(name, getattr(first, name).clone())
        self.hidden_weight = torch.nn.Parameter(torch.stack([m.hidden_layer.weight.detach() for m in members]))
        self.hidden_bias = torch.nn.Parameter(torch.stack([m.hidden_layer.bias.detach() for m in members])[:, None])
        self.output_weight = torch.nn.Parameter(torch.stack([m.output_layer.weight.detach() for m in members]))
        self.output_bias = torch.nn.Parameter(torch.stack([m.output_layer.bias.detach() for m in members])[:, None])

    def forward(self, z):
        """Each member on its own block of rows.

        Parameters
        ----------
        z : (K * B, n_in) float64 tensor
            Member k's B rows at ``k * B : (k + 1) * B``.

        Returns
        -------
        (K * B, n_out) float64 tensor
        """
        rows = z.shape[0] // self.count
        scaled = (self.input_mask * (z - self.mean) / self.std).reshape(self.count, rows, -1)
        hidden = torch.tanh(torch.baddbmm(self.hidden_bias, scaled, self.hidden_weight.transpose(1, 2)))
        out = torch.baddbmm(self.output_bias, hidden, self.output_weight.transpose(1, 2))
        return self.output_mask * out.reshape(self.count * rows, -1)

    def rates(self, x, u):
        """Δθ(x, u) of each member on its block of rows, as a correction of ẋ (K * B, n)."""
        return residual_frame.field(self.frame, self, x, u)

    def member_states(self) -> list[dict]:
        """Each member's weights as a `ResidualNet` state dict (copies)."""
        buffers = {name: getattr(self, name).clone() for name in ("mean", "std", "input_mask", "output_mask")}
        return [{"hidden_layer.weight": self.hidden_weight[k].detach().clone(),
                 "hidden_layer.bias": self.hidden_bias[k, 0].detach().clone(),
                 "output_layer.weight": self.output_weight[k].detach().clone(),
                 "output_layer.bias": self.output_bias[k, 0].detach().clone(), **buffers}
                for k in range(self.count)]
