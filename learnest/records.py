"""Typed views of the JSON reports learnest stores and serves, which give back that JSON key for key.

A report (a diagnosis, an evaluation, a model's meta) is stored as JSON and its keys are a contract: the
web pages, the CLI's ``--json``, stored rows of older versions and users' scripts read them.  A `Record` is
a frozen dataclass whose typed fields name what every reader relies on (with units in their docs); keys it
does not type are kept in ``extra``, and the typed keys the JSON carried in ``present``, so
`to_dict` gives back, key for key, the JSON `from_dict` read, for every report, old or new (what the tests check;
the package itself never reads a report only to write it back).  A producer builds its report as the type
(`Record.of`: the keys it gives, typed or not, are the JSON's keys), and serialises it once, where it is stored or
handed to a user as a dict.  A record reads like its JSON (``record["key"]``, ``record.get("key")``), so the
functions that read stored reports read a record as well.

Nested records are declared in the class's ``NESTED`` {field: (shape, Record class)}, shape one of "one",
"list" or "dict" (a dict of records keyed by name); ``SCHEMA`` names the type a plain-JSON field documents.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

BOOKKEEPING = ("extra", "present")


def doc(text: str) -> dict:
    """Field metadata carrying the field's description (what the API schema shows)."""
    return {"doc": text}


def _plain(value: Any) -> Any:
    if isinstance(value, Record):
        return value.to_dict()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


@dataclass(frozen=True)
class Record:
    """Base of the typed reports: ``extra`` holds every key not typed, ``present`` the typed keys the JSON
    carried (a typed field absent from the JSON stays absent from `to_dict`; None, for a record built in
    code: every typed field)."""

    NESTED: ClassVar[dict[str, tuple[str, type[Record]]]] = {}
    # {field: the type its schema documents} where the field holds the JSON of a type defined elsewhere
    # (a dict whose shape a dataclass describes, e.g. `estimators.yardsticks.FlightYardsticks`)
    SCHEMA: ClassVar[dict[str, Any]] = {}

    extra: dict[str, Any] = field(default_factory=dict, kw_only=True, metadata=doc("keys not typed, as stored"))
    present: frozenset[str] | None = field(default=None, kw_only=True, repr=False, compare=False,
                                           metadata=doc("the typed keys the JSON carried (None: all)"))

    @classmethod
    def typed_fields(cls) -> list[str]:
        """Names of the typed fields, in declaration order."""
        return [f.name for f in fields(cls) if f.name not in BOOKKEEPING]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]):
        """Read the JSON (a dict) of this report; unknown keys go to ``extra``."""
        typed = cls.typed_fields()
        values: dict[str, Any] = {}
        for name in typed:
            if name not in data:
                continue
            value = data[name]
            shape, kind = cls.NESTED.get(name, ("", Record))
            if value is not None and shape == "one" and isinstance(value, Mapping):
                value = kind.from_dict(value)
            elif value is not None and shape == "list" and isinstance(value, list):
                value = [kind.from_dict(v) if isinstance(v, Mapping) else v for v in value]
            elif value is not None and shape == "dict" and isinstance(value, Mapping):
                value = {k: kind.from_dict(v) if isinstance(v, Mapping) else v for k, v in value.items()}
            values[name] = value
        return cls(**values, extra={k: v for k, v in data.items() if k not in typed},
                   present=frozenset(values))

    @classmethod
    def of(cls, **values: Any):
        """The record a producer builds from its values: the typed ones are its fields, the others its ``extra``,
        and `to_dict` gives exactly the keys given (a typed field not given stays absent, as from a JSON that
        never had the key)."""
        typed = set(cls.typed_fields())
        return cls(**{k: v for k, v in values.items() if k in typed},
                   extra={k: v for k, v in values.items() if k not in typed},
                   present=frozenset(k for k in values if k in typed))

    def updated(self, **values: Any):
        """This record with ``values`` set: typed ones as fields (present from then on), the others in ``extra``."""
        typed = set(self.typed_fields())
        present = None if self.present is None else self.present | {k for k in values if k in typed}
        return replace(self, **{k: v for k, v in values.items() if k in typed},
                       extra={**self.extra, **{k: v for k, v in values.items() if k not in typed}}, present=present)

    def __contains__(self, key: object) -> bool:
        if key not in self.typed_fields():
            return key in self.extra
        return self.present is None or key in self.present

    def __getitem__(self, key: str) -> Any:
        """The value of the JSON's ``key`` (a nested record as a record); KeyError when the JSON has no such key."""
        if key not in self:
            raise KeyError(key)
        return getattr(self, key) if key in self.typed_fields() else self.extra[key]

    # read by key, never iterated (Python would iterate by __getitem__(0), 1, ...): `to_dict` is the JSON to iterate
    __iter__ = None

    def get(self, key: str, default: Any = None) -> Any:
        """``self[key]``, or ``default`` when the JSON has no such key."""
        return self[key] if key in self else default

    def to_dict(self) -> dict[str, Any]:
        """The JSON it was read from (or that it stands for), key for key."""
        out = {name: _plain(getattr(self, name)) for name in self.typed_fields()
               if self.present is None or name in self.present}
        out.update(self.extra)
        return out


# what a reader of a report entry takes: the stored JSON or the record it stands for (both read by key)
ReportView = Mapping[str, Any] | Record
