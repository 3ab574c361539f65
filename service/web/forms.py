"""Form posts: fields -> the JSON API's request models, and what a form says about the token it needs.

A form sends every field as text and an empty field for "not given"; the parsers here turn that into the
same pydantic request models the JSON routes take, so a form and a JSON body are checked by the same rules
and fail with the same messages (a pydantic ValidationError, which the pages show as a 422 page).  Only the
types are read leniently (``strict=False``: "5" is 5 in a form, where a JSON body must send a number).

Tokens: a form post needs the scope of the JSON route it stands for (service.api.access); the request guard
checks the web session's cookie before any route reads the body, and a form says beforehand whether the
browser's sign-in may use it (`form_access`).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from fastapi import Request, UploadFile
from fastapi.responses import RedirectResponse
from pydantic import ValidationError

from learnest.errors import InvalidInput

from ..api.deps import principal
from ..api.schemas import AliasIn, DiagnosisRequest, EvaluationRequest, TrainRequest

MAX_VEHICLE, MAX_NOTES = 200, 10_000   # the JSON upload's Form(max_length=...) limits


# -- tokens ----------------------------------------------------------------------------------------------
FormAccess = Literal["open", "allowed", "signin", "denied"]


def form_access(request: Request, needs: str = "write") -> FormAccess:
    """What a form needing ``needs`` (write or admin) says about the token: nothing ("open": a server without
    tokens), who may use it ("allowed"), a link to sign in ("signin": nobody is signed in) or that the
    signed-in token's scope is too narrow ("denied")."""
    who = principal(request)
    if who is None or (not who.signed_in and who.allows("admin")):
        return "open"
    if not who.signed_in:
        return "signin"
    return "allowed" if who.allows(needs) else "denied"


def redirect(url: str) -> RedirectResponse:
    """303 to the page of what a form made (a reload then never posts twice)."""
    return RedirectResponse(url, status_code=303)


# -- fields -> request models ------------------------------------------------------------------------------
def optional(text: str | None) -> str | None:
    """An empty form field means "not given" (the API's default)."""
    text = (text or "").strip()
    return text or None


def chosen_files(files: list[UploadFile | str]) -> list[UploadFile]:
    """The files of an upload form; InvalidInput when none was chosen."""
    chosen = [f for f in files if not isinstance(f, str) and f.filename]  # no file chosen: a nameless empty part
    if not chosen:
        raise InvalidInput("choose the log file(s) of one flight to upload")
    return chosen


def upload_text(vehicle: str, notes: str) -> tuple[str | None, str | None]:
    """(vehicle, notes) of an upload form, None when empty; InvalidInput when one is too long."""
    if len(vehicle) > MAX_VEHICLE or len(notes) > MAX_NOTES:
        raise InvalidInput(f"vehicle: at most {MAX_VEHICLE} characters; notes: at most {MAX_NOTES}")
    return optional(vehicle), optional(notes)


def train_request(name: str, flight_id: str, epochs: str, include_bad: str | None,
                  flight_ids: Sequence[str] = (), system: str = "", group_by: str = "") -> TrainRequest:
    """The train form as POST /models' body (ValidationError names the bad field): a flight's page sends its
    ``flight_id``, the flight list the checked ``flight_ids`` (one checked is one flight, several train one
    model on all of them); an empty ``system`` is the default prior, an empty ``group_by`` the default grouping."""
    body: dict[str, object] = {"name": name.strip(), "epochs": optional(epochs), "include_bad": include_bad is not None}
    checked = [i for i in flight_ids if i.strip()]
    if len(checked) > 1:
        body["flight_ids"] = checked
    elif checked or optional(flight_id):
        body["flight_id"] = checked[0] if checked else flight_id
    else:
        raise InvalidInput("choose the flight(s) to train on")
    if optional(system):
        body["system"] = system.strip()
    if optional(group_by):
        body["group_by"] = group_by.strip()
    return TrainRequest.model_validate(body, strict=False)


def alias_version(version: str) -> int:
    """The alias form's version, checked as PUT /models/{name}/aliases/{alias}'s body."""
    return AliasIn.model_validate({"version": version}, strict=False).version


def evaluation_request(model: str, flights: list[str], methods: list[str], horizon: str,
                       include_bad: str | None, sg_window: str = "") -> EvaluationRequest:
    """The evaluate form as POST /evaluations' body; no flight checked means "all-other", an empty SG window
    the default."""
    if not methods:
        raise InvalidInput("choose at least one estimator")
    body = {"model": model, "flights": flights or "all-other", "methods": methods, "horizon": horizon,
            "include_bad": include_bad is not None}
    if sg_window.strip():
        body["sg_window"] = sg_window.strip()
    return EvaluationRequest.model_validate(body, strict=False)


def diagnosis_request(flights: list[str], model: str, system: str, methods: list[str], epochs: str,
                      register: str | None, register_as: str) -> DiagnosisRequest:
    """The diagnose form as POST /diagnoses' body: the checked flights in the order listed (the split
    depends on it), an empty model "train one on the fitting flight", ``register`` checked: the repaired
    model becomes the next version of ``register_as``."""
    if not flights:
        raise InvalidInput("choose the flight(s) to diagnose")
    if not methods:
        raise InvalidInput("choose at least one estimator")
    body = {"flights": flights, "model": optional(model), "system": system or "quadrotor", "methods": methods}
    if optional(epochs):
        body["epochs"] = epochs.strip()
    if register is not None:
        if not optional(register_as):
            raise InvalidInput("register: give the model name the repaired model is registered under")
        body["register"] = register_as.strip()
    return DiagnosisRequest.model_validate(body, strict=False)


def validation_message(err: ValidationError) -> str:
    """One line naming each bad field, as the JSON API's 422 detail does."""
    return "; ".join(_field_message(e) for e in err.errors())


def _field_message(error) -> str:
    field = ".".join(str(part) for part in error.get("loc", ()))
    return f"{field}: {error.get('msg', 'invalid')}" if field else error.get("msg", "invalid")
