"""A model's metadata as a type, and the integer version of the inputs a stored model was trained on.

A `models.knode.HybridModel` carries a free ``meta`` dict (saved with it).  `ModelMetadata` is the typed
view of what every surface reads from it (the system, the prior's parameters, the flights it was trained
and validated on, whether it learned anything, its training envelope, its input format); its `to_dict`
gives back the dict it was read from, key for key.

Input format.  A model is fed, at evaluation, the inputs it was trained on.  Those changed over the life of
the Crazyflie prior, and a model recorded which it saw as a sentence in ``meta["attitude_input"]``.  The
integer ``format_version`` replaces comparing sentences: newly trained models record it, and `input_format`
maps the sentences of models stored before it to the same integers, so they keep loading and evaluating on
the inputs they were trained on.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from learnest.records import Record, doc

# The inputs of a prior that turns thrust into acceleration through the attitude (the Crazyflie's):
RAW_ATTITUDE = 0            # the mocap attitude as logged
ATTITUDE_CALIBRATED_FORMAT = 1   # the attitude rotated onto the flight's thrust axis, heading removed
THRUST_GAIN_FORMAT = 2      # as 1, and the battery voltage carrying the flight's thrust gain

# the sentences models recorded in meta["attitude_input"] before the integer existed (kept for reading them)
ATTITUDE_CALIBRATED = "mocap attitude calibrated onto the thrust axis, heading removed"
THRUST_GAIN_CALIBRATED = ATTITUDE_CALIBRATED + "; thrust gain calibrated per flight"
FORMAT_SENTENCES = {ATTITUDE_CALIBRATED: ATTITUDE_CALIBRATED_FORMAT, THRUST_GAIN_CALIBRATED: THRUST_GAIN_FORMAT}
FORMAT_DESCRIPTIONS = {RAW_ATTITUDE: "the mocap attitude as logged", ATTITUDE_CALIBRATED_FORMAT: ATTITUDE_CALIBRATED,
                       THRUST_GAIN_FORMAT: THRUST_GAIN_CALIBRATED}


def input_format(meta: Mapping | None) -> int:
    """The integer input format of a model's meta: its ``format_version`` when it records one, else the
    format its ``attitude_input`` sentence names (`FORMAT_SENTENCES`), else `RAW_ATTITUDE` (a model that
    recorded neither was trained on the attitude as logged)."""
    meta = meta or {}
    version = meta.get("format_version")
    if isinstance(version, int) and not isinstance(version, bool):
        return version
    return FORMAT_SENTENCES.get(str(meta.get("attitude_input")), RAW_ATTITUDE)


def format_meta(version: int) -> dict:
    """What a newly trained model of a thrust-through-attitude prior records about its inputs: the integer
    ``format_version`` and, for people reading the file, the sentence saying what it means."""
    return {"attitude_input": FORMAT_DESCRIPTIONS[version], "format_version": version}


def with_input_format(meta: Mapping | None) -> dict:
    """``meta`` with ``format_version`` set (`input_format`) when it has an ``attitude_input`` sentence but no
    integer: how a model stored before the integer is read.  Other metas are returned as they are."""
    meta = dict(meta or {})
    if "format_version" not in meta and "attitude_input" in meta:
        meta["format_version"] = input_format(meta)
    return meta


@dataclass(frozen=True)
class FlightLineage(Record):
    """One flight a model was trained or validated on (an entry of its meta's ``training_flights``)."""

    name: str | None = field(default=None, metadata=doc("the flight's name"))
    sha256: list[str] = field(default_factory=list, metadata=doc("sha256 of each of the flight's source files"))
    samples: int | None = field(default=None, metadata=doc("samples of the flight used"))
    dt: float | None = field(default=None, metadata=doc("sample period, s"))
    thrust_gain: float | None = field(default=None, metadata=doc("the flight's thrust gain against the prior's "
                                                                 "map, dimensionless (only where it has one)"))


@dataclass(frozen=True)
class ModelMetadata(Record):
    """What a model's meta says about it (`Record`: `to_dict` gives back the meta, key for key).

    Attributes
    ----------
    system : str or None
        The prior's name ("quadrotor", "crazyflie"); None when the meta does not say (then the model
        file's ``system`` is the authority).
    training_flights, validation_flights : list of FlightLineage
        The flights it was trained on, and those held out whole to choose the kept epoch (empty for one
        flight, whose validation is time blocks of it).
    learned : bool or None
        False when no epoch predicted the held-out data better than the prior (the model equals its prior);
        None when the meta does not say.
    learned_note : str or None
        What ``learned: False`` means, in words.
    envelope : dict or None
        The training envelope (per state and input: the range seen in training, `models.envelope`).
    format_version : int or None
        The inputs it was trained on (`input_format`: 0 raw attitude, 1 attitude calibrated, 2 and the
        thrust gain); `format` reads it for models stored before it was recorded.
    training : dict or None
        The training settings (epochs, hidden width, learning rate, ...).
    residual_scale, residual_scale_groups, residual_scale_note, residual_scale_choice
        The scale of the residual kept, the groups held out in turn to choose it, the choice in words and its
        table (`learnest.estimators.group_training`).
    prior_params : dict or None
        {name: value in SI units} of the prior; only in `of_model` (a meta does not hold it).
    """

    NESTED: ClassVar[dict[str, tuple[str, type[Record]]]] = {"training_flights": ("list", FlightLineage),
                                                              "validation_flights": ("list", FlightLineage)}

    system: str | None = field(default=None, metadata=doc('the prior, "quadrotor" or "crazyflie"'))
    training_flights: list[FlightLineage] = field(default_factory=list,
                                                  metadata=doc("the flights it was trained on"))
    validation_flights: list[FlightLineage] = field(default_factory=list,
                                                    metadata=doc("flights held out whole to choose the kept epoch"))
    learned: bool | None = field(default=None, metadata=doc("False: no epoch beat the prior on held-out data, the "
                                                            "model equals its prior"))
    learned_note: str | None = field(default=None, metadata=doc("what learned: false means, in words"))
    envelope: dict[str, Any] | None = field(default=None, metadata=doc("the range of each state and input seen "
                                                                       "in training (SI units)"))
    format_version: int | None = field(default=None, metadata=doc("the inputs it was trained on: 0 raw attitude, "
                                                                  "1 calibrated attitude, 2 and the per-flight "
                                                                  "thrust gain"))
    training: dict[str, Any] | None = field(default=None, metadata=doc("training settings (epochs, hidden, lr, ...)"))
    residual_scale: float | None = field(default=None, metadata=doc(
        "the scale s of the residual kept, f = f_prior + s Δθ (1.0 the whole residual; None: stored before it)"))
    residual_scale_groups: list[str] = field(default_factory=list, metadata=doc(
        "the groups of training flights (e.g. trajectory families) held out in turn to choose the scale"))
    residual_scale_note: str | None = field(default=None, metadata=doc(
        "how the scale was chosen, or why none was (one trajectory family: nothing to hold out)"))
    residual_scale_choice: dict[str, Any] | None = field(default=None, metadata=doc(
        "the choice: rule, groups' flights, the inner trainings' validation flights and kept epochs, per scale and "
        "held-out group the inner gap gains (%), seconds"))
    prior_params: dict[str, Any] | None = field(default=None, metadata=doc(
        "the prior's parameters, SI units (kg, m, s, ...); from the model file beside its meta (`of_model`)"))

    @classmethod
    def of_model(cls, meta: Mapping | None, prior_params: Mapping) -> ModelMetadata:
        """The metadata of a model: its ``meta`` with ``format_version`` read (`with_input_format`), and its
        prior's parameters (which the model file keeps beside the meta); `to_dict` then carries both."""
        return cls.from_dict({**with_input_format(meta), "prior_params": dict(prior_params)})

    @property
    def format(self) -> int:
        """The integer input format (`input_format` of the meta: read from the sentence of an older model)."""
        return input_format(self.to_dict())
