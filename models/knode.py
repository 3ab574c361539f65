"""KNODE hybrid model: f_h,c(x, u) = f_prior(x, u) + Δθ(x, u), discretised with RK4 (eqs. 4-5).

`Residual` is the trained MLP as plain float64 arrays; it evaluates in numpy (batched over rows, so one
call propagates every sigma point), torch and CasADi (pure symbols, no callback) from one function.
`HybridModel` is what the estimators consume: prior-only, KNODE and true-dynamics variants differ only
in which continuous vector field they hold.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import casadi as ca
import numpy as np

from learnest.errors import InvalidInput

from . import residual_frame
from .backend import Array, ops_for, rk4_step
from .metadata import with_input_format
from .noise import NoiseModel
from .systems import System, make_system


@dataclass
class Residual:
    """A tanh MLP Δθ; `layers` is a list of (weight (out, in), bias (out,)) float64 arrays.

    Input standardisation is folded into the first layer, so the exported network is exactly the
    trained one and has nothing else to carry around.  `frame` says what the network reads and where its
    output acts (`models.residual_frame`): ``"state"`` Δθ([x, u]) on every row of ẋ, ``"body"`` body-frame
    features and a body-frame force rate rotated into ȧ.
    """

    layers: list
    frame: str = "state"
    # an ensemble's mean carries its members (`models.ensemble`): their spread is the model's uncertainty
    members: list | None = None

    def __call__(self, x, u):
        """Δθ(x, u) as a correction of ẋ, in the namespace of ``x``: numpy (B, n) -> (B, n), torch likewise,
        CasADi (n, 1).

        ``u`` is left out of a state-frame residual when it is None or has width 0.
        """
        return residual_frame.field(self.frame, self.network, x, u)

    def network(self, z):
        """The bare MLP on features ``z`` (`models.residual_frame.features`), in the namespace of ``z``."""
        ops = ops_for(z)
        for i, (weight, bias) in enumerate(self.layers):
            z = ops.linear(z, weight, bias)
            if i < len(self.layers) - 1:
                z = ops.tanh(z)
        return z

    def parametric(self) -> tuple[Residual, ca.SX, np.ndarray]:
        """This network with its weights as CasADi symbols: (network, θ (k, 1), values (k,)).

        Why: code generated from the symbols serves every network of this architecture (compiled once,
        `estimators.native.codegen`), where numeric weights would make each trained network new code.  Only the
        nonzero weights become symbols, in layer order (weight, then bias; CasADi's column-major order
        within each); exact zeros stay structural zeros, so a masked output row (`System.residual_masks`)
        is exactly zero and a blind input is never read.  The zero pattern is thus part of the architecture.
        """
        matrices = []
        for weight, bias in self.layers:
            matrices += [ca.sparsify(ca.DM(np.asarray(weight, dtype=float))),
                         ca.sparsify(ca.DM(np.asarray(bias, dtype=float).reshape(-1, 1)))]
        values = np.concatenate([np.asarray(m.nonzeros(), dtype=float) for m in matrices])
        theta = ca.SX.sym("weights", len(values))
        symbols, offset = [], 0
        for m in matrices:
            symbols.append(ca.SX(m.sparsity(), theta[offset:offset + m.nnz()]))
            offset += m.nnz()
        return Residual(list(zip(symbols[::2], symbols[1::2])), self.frame), theta, values

    def to_dict(self) -> dict:
        """``{"layers": [[weight, bias], ...], "frame": ...}`` as nested lists (JSON); a state-frame residual
        leaves ``frame`` out, as files written before frames existed do."""
        data: dict = {"layers": [[w.tolist(), b.tolist()] for w, b in self.layers]}
        if self.frame != "state":
            data["frame"] = self.frame
        if self.members:
            data["members"] = [m.to_dict() for m in self.members]
        return data

    @classmethod
    def from_dict(cls, data: dict) -> Residual:
        """Inverse of `to_dict` (arrays as float64).

        Raises
        ------
        InvalidInput
            For an unknown frame.
        """
        members = [cls.from_dict(m) for m in data["members"]] if data.get("members") else None
        return cls([(np.asarray(w, dtype=float), np.asarray(b, dtype=float)) for w, b in data["layers"]],
                   residual_frame.check_frame(data.get("frame", "state")), members)


class HybridModel:
    """Continuous vector field + RK4 discretisation + the system's measurement model.

    Satisfies `learnest.estimators.protocols.StateSpaceModel`.

    Parameters
    ----------
    system : System
        The dynamics (prior and true vector fields, measurement model, noise settings).
    kind : {"prior", "true", "knode"}
        Which vector field the model holds: the first-principles prior, the simulator's true dynamics
        (for reference runs), or prior + trained residual.
    residual : Residual, optional
        Required for ``"knode"``; when given it is added to the base field whatever the kind.
    meta : dict, optional
        Free metadata (training settings, losses, ...), saved with the model.
    noise : NoiseModel, optional
        The noise this model's filters run with, identified on its training flights
        (`estimators.noise_identification`); None: never identified (the system's fixed noise is used).
    prior_noise : NoiseModel, optional
        The noise of this model's prior identified the same way on the same flights: what a fair comparison
        runs the prior-only filters with (`estimators.prepared.prepare`).

    Raises
    ------
    InvalidInput
        If ``kind`` is unknown, or ``"knode"`` comes without a residual.
    """

    def __init__(self, system: System, kind: str = "prior", residual: Residual | None = None,
                 meta: dict | None = None, noise: NoiseModel | None = None,
                 prior_noise: NoiseModel | None = None) -> None:
        if kind not in ("prior", "true", "knode"):
            raise InvalidInput(f"model kind must be 'prior', 'true' or 'knode', not {kind!r}")
        if (kind == "knode") != (residual is not None):
            raise InvalidInput("a 'knode' model needs a trained residual, and only a 'knode' model has one")
        self.system, self.kind, self.residual, self.meta = system, kind, residual, dict(meta or {})
        self.noise, self.prior_noise = noise, prior_noise

    @property
    def n(self) -> int:
        """Number of states (9 for the quadrotor: p (m), v (m/s), a (m/s²))."""
        return self.system.n

    @property
    def n_inputs(self) -> int:
        """Number of inputs (0 for an autonomous system)."""
        return self.system.n_inputs

    @property
    def n_meas(self) -> int:
        """Number of measurements."""
        return self.system.n_meas

    def f_c(self, x: Array, u: Array) -> Array:
        """Continuous vector field dx/dt: the prior (or the true field for ``"true"``), plus the residual
        of a ``"knode"`` model.  Same namespace and shape as ``x``."""
        base = self.system.f_true(x, u) if self.kind == "true" else self.system.f_prior(x, u)
        return base + self.residual(x, u) if self.residual is not None else base

    def step(self, x: Array, u: Array, dt: float) -> Array:
        """Discrete model f_h(x, u) = RK4(f_h,c) over ``dt`` s; x may be a batch (B, n) of sigma points."""
        return rk4_step(self.f_c, x, u, dt)

    def h(self, x: Array, u: Array | None = None) -> Array:
        """Predicted measurement(s) of the system: (n,) -> (m,), (B, n) -> (B, m)."""
        return self.system.h(x, u)

    def parametric(self) -> tuple[HybridModel, ca.SX, np.ndarray]:
        """This model with its numbers as CasADi symbols: (model, θ (k, 1), values (k,)).

        θ = [the vector field's physical parameters that `System.symbolic_params` names (sorted by name),
        the residual's nonzero weights (`Residual.parametric`)].  Code generated from the returned
        model's ``step``/``h`` with θ as an input depends on the system, its numeric-only parameters
        and the network's architecture and masks, not on the trained weights or identified parameters:
        the estimators compile it once for all models of an architecture.
        """
        field_name = "true_params" if self.kind == "true" else "prior_params"
        params = getattr(self.system, field_name)
        names = self.system.symbolic_params(params)
        physical = ca.SX.sym("physical", len(names))
        symbolic = {**params, **{name: physical[i] for i, name in enumerate(names)}}
        system = replace(self.system, true_params=symbolic) if self.kind == "true" else \
            replace(self.system, prior_params=symbolic)
        values = np.array([float(params[name]) for name in names])
        residual, weights, weight_values = None, ca.SX(0, 1), np.zeros(0)
        if self.residual is not None:
            residual, weights, weight_values = self.residual.parametric()
        model = HybridModel(system, self.kind, residual, self.meta, self.noise, self.prior_noise)
        return model, ca.vertcat(physical, weights), np.concatenate([values, weight_values])

    def __repr__(self) -> str:
        return f"HybridModel({self.system.name}, {self.kind})"

    # -- persistence: everything needed to rebuild the model, no pickle --------------------------
    def save(self, path: str | Path) -> None:
        """Write the model as JSON (format ``learnest-model/1``, no pickle), atomically via ``path.tmp``.

        The noise models are optional keys: a file without them loads as a model whose noise was never
        identified."""
        data = {"format": "learnest-model/1", "system": self.system.name, "kind": self.kind,
                "prior_params": self.system.prior_params, "true_params": self.system.true_params,
                "residual": self.residual.to_dict() if self.residual else None, "meta": self.meta,
                "noise": self.noise.to_dict() if self.noise else None,
                "prior_noise": self.prior_noise.to_dict() if self.prior_noise else None}
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(data))
        tmp.replace(path)  # atomic: a crash never leaves half a model behind

    @classmethod
    def load(cls, path: str | Path) -> HybridModel:
        """Read a model written by `save`.

        Raises
        ------
        InvalidInput
            If the file cannot be read or is not a ``learnest-model/1`` file.
        """
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise InvalidInput(f"{path}: not a readable learnest model ({err})") from None
        if data.get("format") != "learnest-model/1":
            raise InvalidInput(f"{path}: not a learnest model file (format {data.get('format')!r})")
        system = make_system(data["system"], prior_params=data["prior_params"],
                             true_params=data["true_params"])
        residual = Residual.from_dict(data["residual"]) if data["residual"] else None
        noise, prior_noise = (NoiseModel.from_dict(data[key]) if data.get(key) else None
                              for key in ("noise", "prior_noise"))
        # a model stored before the integer input format gets it from its sentence: fed as it was trained
        return cls(system, data["kind"], residual, with_input_format(data.get("meta")), noise, prior_noise)
