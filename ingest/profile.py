"""What a flight says about the vehicle and its sensors (`flight_profile`), and how two profiles differ
(`profile_mismatches`): a model records its training flight's profile, and evaluating it on a flight from
another vehicle, sensor rate or attitude source warns.

The profile is read from the metadata the adapters write (``meta["vehicle"]``, ``original_rates``,
``attitude_source``, ``topics``, ``mass_kg``, ``controller``, ``mocap_resolution_m``), so it works for every
format and for flights stored before it existed.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .flight import Flight

# Rates that differ by more than this fraction are different sensor settings (a 50 Hz radio log against a
# 100 Hz one), not the jitter of one setting.  Compared as the model sees them (`_seen`): above the grid rate
# a stream is low-passed onto the grid, so a 250 Hz uSD accelerometer and a 100 Hz one give the same input.
RATE_TOLERANCE = 0.2
# Masses that differ by more than this fraction are different vehicles or payloads (a deck is ~3 g of 30 g).
MASS_TOLERANCE = 0.05


def flight_profile(flight: Flight) -> dict:
    """The vehicle and sensor record of a flight.

    Returns
    -------
    dict
        ``vehicle`` (name or None), ``adapter``, ``rates_hz`` {"acc", "mocap", "grid"} (the accelerometer's and
        the mocap's rates as logged, and the Flight's grid; None when unknown), ``attitude_source``
        ("mocap" or the onboard estimate it came from), ``mocap_source`` (motion capture, the pose the vehicle
        received, or an onboard estimate), ``mocap_resolution_m`` (0 when finer than 10 µm), ``mass_kg`` and
        ``controller`` (when a sidecar gave them).
    """
    meta = flight.meta
    rates = meta.get("original_rates") or {}
    topics = meta.get("topics") or {}
    mocap_source = meta.get("mocap_source") or topics.get("pose_source") or "motion capture"
    attitude = meta.get("attitude_source")
    if attitude is None:
        attitude = "onboard estimate" if topics.get("pose_source") == "onboard estimate" else "mocap"
    return {"vehicle": meta.get("vehicle"), "adapter": meta.get("adapter"),
            "rates_hz": {"acc": _rounded(rates.get("acc")), "mocap": _rounded(rates.get("mocap")),
                         "grid": _rounded(meta.get("rate_hz") or (flight.rate_hz if len(flight.t) > 1 else None))},
            "attitude_source": attitude, "mocap_source": mocap_source,
            "mocap_resolution_m": meta.get("mocap_resolution_m"),
            "mass_kg": meta.get("mass_kg"), "controller": meta.get("controller")}


def _rounded(value) -> float | None:
    return None if value is None else round(float(value), 1)


def profile_mismatches(trained: dict | None, flight: dict) -> list[str]:
    """How a flight's profile differs from the training flight's, one sentence each ([] when alike or when
    the model recorded no profile).

    Parameters
    ----------
    trained : dict or None
        The model's ``meta["training_profile"]`` (`flight_profile` of its training flight).
    flight : dict
        `flight_profile` of the flight evaluated.
    """
    if not trained:
        return []
    warnings = []
    if trained.get("vehicle") and flight.get("vehicle") and str(trained["vehicle"]) != str(flight["vehicle"]):
        warnings.append(f"another vehicle: flight from {flight['vehicle']}, model trained on {trained['vehicle']}")
    for stream in ("acc", "mocap", "grid"):
        ours, theirs = (trained.get("rates_hz") or {}).get(stream), (flight.get("rates_hz") or {}).get(stream)
        if ours and theirs and abs(_seen(theirs, flight, stream) - _seen(ours, trained, stream)) > \
                RATE_TOLERANCE * _seen(ours, trained, stream):
            warnings.append(f"another {stream} rate: {theirs:g} Hz, model trained at {ours:g} Hz")
    if _attitude_kind(trained) != _attitude_kind(flight):
        warnings.append(f"another attitude source: {flight.get('attitude_source')}, model trained with "
                        f"{trained.get('attitude_source')}")
    ours, theirs = trained.get("mass_kg"), flight.get("mass_kg")
    if ours and theirs and abs(theirs - ours) > MASS_TOLERANCE * ours:
        warnings.append(f"another mass: {1000 * theirs:.1f} g, model trained on {1000 * ours:.1f} g")
    if trained.get("controller") and flight.get("controller") and trained["controller"] != flight["controller"]:
        warnings.append(f"another controller: {flight['controller']}, model trained with {trained['controller']}")
    return warnings


def _seen(rate: float, profile: dict, stream: str) -> float:
    """The rate a model sees of a sensor stream: a stream faster than the flight's grid is low-passed and
    brought to the grid (`ingest.align.anti_alias`), so a 500 Hz and a 100 Hz accelerometer both reach the
    model at the 100 Hz grid, band-limited to 40 Hz; only a stream slower than the grid (interpolated between
    its samples) reaches it at its own rate."""
    grid = (profile.get("rates_hz") or {}).get("grid")
    return min(rate, grid) if stream != "grid" and grid else rate


def _attitude_kind(profile: dict) -> str:
    """"mocap" or "onboard": the wording of the sources differs between formats, the kind is what matters."""
    return "onboard" if "onboard" in str(profile.get("attitude_source") or "") else "mocap"
