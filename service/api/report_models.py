"""Response schemas built from the typed reports (`learnest.records.Record` subclasses), so ``/docs`` and
``/openapi.json`` show every typed field with its description, from one definition.

Each schema allows extra keys: a report carries more than its typed fields (`Record.extra`), and those keys
are part of the JSON contract.  Routes serve the stored JSON itself (`Record.to_dict`, key for key); the
schema documents it.
"""
from __future__ import annotations

import types
import typing
from dataclasses import MISSING, fields
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from learnest.models.metadata import ModelMetadata
from learnest.records import BOOKKEEPING, Record
from learnest.workflows.reports import DiagnosisReport, EvaluationReport

_BUILT: dict[type, type[BaseModel]] = {}


def _translate(hint: Any) -> Any:
    """``hint`` with every Record class replaced by its schema."""
    if isinstance(hint, type) and issubclass(hint, Record):
        return schema_of(hint)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if not args:
        return hint
    translated = tuple(_translate(a) for a in args)
    if origin in (types.UnionType, typing.Union):
        return typing.Union[translated]   # noqa: UP007 (built from a tuple)
    return origin[translated]


def schema_of(record: type[Record]) -> type[BaseModel]:
    """The pydantic model of a `Record` class: its typed fields (types, defaults, docs), extra keys allowed."""
    if record in _BUILT:
        return _BUILT[record]
    hints = typing.get_type_hints(record)
    definitions: dict[str, Any] = {}
    for f in fields(record):
        if f.name in BOOKKEEPING:
            continue
        description = f.metadata.get("doc")
        if f.default is not MISSING:
            spec = Field(f.default, description=description)
        elif f.default_factory is not MISSING:
            spec = Field(default_factory=f.default_factory, description=description)
        else:
            spec = Field(description=description)
        definitions[f.name] = (_translate(record.SCHEMA.get(f.name, hints[f.name])), spec)
    model = create_model(record.__name__ + "Out", __config__=ConfigDict(extra="allow"),
                         __doc__=record.__doc__, **definitions)
    _BUILT[record] = model
    return model


DiagnosisReportOut = schema_of(DiagnosisReport)
ModelMetadataOut = schema_of(ModelMetadata)
EvaluationReportOut = schema_of(EvaluationReport)


class FlightLink(BaseModel):
    """A flight a version was trained or validated on, by its lineage record."""

    model_config = ConfigDict(extra="allow")

    id: int | None = None
    name: str | None = None
    sha256: Any = Field(None, description="the flight's sha256 (its source files')")
    exists: bool = Field(description="the flight is still stored")
    href: str | None = None


class VersionLineage(BaseModel):
    """Where a version comes from and what was made from it."""

    model_config = ConfigDict(extra="allow")

    ref: str = Field(description='"name:version"')
    training_flight: FlightLink = Field(description="the first training flight")
    training_flights: list[FlightLink] = Field(description="every flight it was trained on")
    validation_flights: list[FlightLink] = Field(description="flights held out whole to choose the kept epoch")
    learned: bool | None = Field(None, description="False: no epoch beat the prior, the version equals its prior")
    learned_note: str | None = None
    parent: dict[str, Any] | None = Field(None, description="{ref, exists, href} of the version it derives from")
    children: list[dict[str, Any]] = Field(description="[{ref, href}] of versions derived from it")
    diagnosis: dict[str, Any] | None = Field(None, description="the diagnosis that produced it: id, href, "
                                                               "effects_added, before, after")
    analysed_by_diagnoses: list[dict[str, Any]]
    job: dict[str, Any] | None = None
    aliases: list[str]
    evaluations: list[dict[str, Any]]
