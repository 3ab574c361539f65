"""What the fitting flights' own signals can determine, before any claim: the spread of battery voltage, thrust
input, speed and height over the rows a diagnosis fits, and which prior parameters that spread leaves
undetermined (`undetermined_params`).

The battery exponent gamma enters the thrust as (V / V_ref)^gamma.  Against a free thrust gain (a payload, other
motors) only its variation along the data is seen: a change δγ moves the thrust by δγ·(ln V − mean ln V), whose rms is
δγ·σ_V / V̄.  To tell gamma to ±0.3 (a tenth of its physical range [0, 3]) that variation must stand out from what the
prior's thrust already misses along a flight, about 0.5 % on real logs (its held-out specific-force error,
`docs/results/crazyflie-physics.md`).  Hence σ_V / V̄ ≥ 0.005 / 0.3 ≈ 1.7 %: `MIN_VBAT_RELATIVE_SPREAD`.  A battery
held at 3.80 ± 0.01 V (0.3 %) makes gamma one more constant gain; a sag from 4.1 to 3.4 V (5 %) determines it.
"""
from __future__ import annotations

import numpy as np

from . import prior as cf

# the least relative spread (std / mean) of the battery voltage over the fitting rows that determines gamma
# against a free thrust gain (see the module's docstring)
MIN_VBAT_RELATIVE_SPREAD = 0.017
# what the thrust columns carry, by thrust source, and their unit
THRUST_INPUT = {"pwm": ("motor PWM", "of 65535"), "rpm": ("rotor speed", "rad/s"),
                "thrust_n": ("thrust command", "N")}


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=float)
    return {"mean": float(x.mean()), "std": float(x.std()), "min": float(x.min()), "max": float(x.max())}


def excitation(data: list, source: str = "pwm") -> dict:
    """The spread of each signal over the fitting rows of ``data`` (`crazyflie_residual.CrazyflieData`).

    Returns
    -------
    dict
        ``vbat_v``, ``thrust_input`` (the thrust columns' mean over the motors, in ``thrust_input_unit``),
        ``speed_m_s`` and ``height_m``: each {``mean``, ``std``, ``min``, ``max``}; ``vbat_relative_spread``
        σ_V / V̄ (1); ``thrust_beyond_vbat``: the share of the thrust input's variance the battery voltage does
        not explain linearly (1: thrust levels vary at one voltage, 0: they move with the battery alone).
    """
    rows = [d.arrays.keep for d in data]
    vbat = np.concatenate([d.arrays.u[k, 8] for d, k in zip(data, rows)])
    thrust = np.concatenate([d.arrays.u[k, 4:8].mean(axis=1) for d, k in zip(data, rows)])
    speed = np.concatenate([np.linalg.norm(d.arrays.v_world[k], axis=1) for d, k in zip(data, rows)])
    height = np.concatenate([d.arrays.z[k] for d, k in zip(data, rows)])
    beyond = 1.0
    if thrust.std() > 0 and vbat.std() > 0:
        beyond = 1.0 - float(np.corrcoef(thrust, vbat)[0, 1]) ** 2
    name, unit = THRUST_INPUT.get(source, THRUST_INPUT["pwm"])
    return {"vbat_v": _stats(vbat), "vbat_relative_spread": float(vbat.std() / max(vbat.mean(), 1e-9)),
            "thrust_input": _stats(thrust), "thrust_input_name": name, "thrust_input_unit": unit,
            "thrust_beyond_vbat": round(beyond, 4), "speed_m_s": _stats(speed), "height_m": _stats(height)}


def battery_words(stats: dict) -> str:
    """The battery voltage over the fitting rows in words: "3.80 ± 0.005 V (3.79–3.81 V)"."""
    v = stats["vbat_v"]
    return f"{v['mean']:.2f} ± {v['std']:.3f} V ({v['min']:.2f}–{v['max']:.2f} V)"


def undetermined_params(stats: dict, candidates: list) -> dict[str, str]:
    """{parameter: why these flights cannot determine it, and what flight would} for the candidates' parameters
    the excitation ``stats`` (`excitation`) leaves undetermined; such a parameter is fitted but never claimed
    (`models.diagnosis.select_effects`)."""
    names = {p.name for e in candidates for p in e.params}
    out: dict[str, str] = {}
    spread = stats["vbat_relative_spread"]
    if "gamma" in names and stats["vbat_v"]["std"] < 1e-9 and abs(stats["vbat_v"]["mean"] - cf.V_REF) < 1e-6:
        out["gamma"] = (f"the logs carry no battery voltage (a constant {stats['vbat_v']['mean']:.2f} V stands in "
                        "for it): the battery exponent cannot be measured.  Log the battery (pm.vbat) on a flight "
                        "whose battery sags")
    elif "gamma" in names and spread < MIN_VBAT_RELATIVE_SPREAD:
        out["gamma"] = (f"the battery stayed at {battery_words(stats)}, a {100 * spread:.1f} % spread where the "
                        f"battery exponent needs {100 * MIN_VBAT_RELATIVE_SPREAD:.1f} %: at one voltage "
                        f"(V / {cf.V_REF:g} V)^gamma is only a constant gain on the thrust, the same as a payload. "
                        "Fly until it sags (a full battery flown down to about 3.4 V), or the same path at several "
                        "charge levels")
    return out
