"""Rendering the web pages: the Jinja2 environment (autoescaped, every page extends templates/base.html), its
filters and the constants every template may read, one page or error page as a response, and the decorator that
shows the service's errors as an error page.  The routes are service.web.pages, .report_pages and
.registry_pages.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from html import escape

from fastapi.responses import HTMLResponse
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape
from pydantic import ValidationError

from learnest.errors import LearnestError
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    METHODS,
    MHE_HORIZON,
    SG_WINDOW,
    SG_WINDOW_RANGE,
)

from ..api.auth import current_principal
from ..local import figures
from ..storage import references
from . import flight_plots, forms, zoomable

PAGE_SIZE = 100


def _when(moment) -> str:
    return moment.strftime("%Y-%m-%d %H:%M:%S") if moment else ""


TEMPLATES = Environment(loader=PackageLoader("learnest.service.web", "templates"),
                        autoescape=select_autoescape(default=True, default_for_string=True),
                        undefined=StrictUndefined,          # a misspelt variable fails the page (and the tests)
                        finalize=lambda value: "" if value is None else value,  # None shows as nothing
                        trim_blocks=True, lstrip_blocks=True)
def _duration(seconds: float) -> str:
    """"42 s", "3 min 20 s", "1 h 05 min"."""
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


TEMPLATES.filters["when"] = _when
TEMPLATES.filters["duration"] = _duration
TEMPLATES.globals.update(NAME_PATTERN=references.NAME, METHODS=METHODS, MHE_HORIZON=MHE_HORIZON,
                         VELOCITY_METHODS=figures.VELOCITY_METHODS, MAX_VEHICLE=forms.MAX_VEHICLE,
                         MAX_NOTES=forms.MAX_NOTES, PAGE_SIZE=PAGE_SIZE,
                         DEFAULT_EPOCHS=CRAZYFLIE_TRAINING.epochs, SG_WINDOW=SG_WINDOW,
                         SG_WINDOW_RANGE=SG_WINDOW_RANGE, PLOTLY_JS_ROUTE=zoomable.PLOTLY_JS_ROUTE,
                         DIAGNOSIS_SPLIT_RULE=DIAGNOSIS_SPLIT_RULE,
                         MIN_GAP_S=flight_plots.MIN_GAP_S,
                         VELOCITY_SG_S=flight_plots.VELOCITY_SG_S)


def page(template: str, title: str, status: int = 200, refresh_s: float | None = None, identify: bool = True,
         **context) -> HTMLResponse:
    """Render templates/`template` (which extends base.html) as a response.

    Parameters
    ----------
    template : str
        File name under templates/.
    title : str
        The page's <title> and <h1> (escaped).
    status : int
        HTTP status of the answer.
    refresh_s : float, optional
        Reload the page after this many seconds (pages of running jobs).
    identify : bool
        Name who is signed in in the header (`with_identity`); False leaves the mark for a page that is cached
        and named per answer.
    **context
        The template's variables.
    """
    html = TEMPLATES.get_template(template).render(title=title, refresh_s=refresh_s, **context)
    return HTMLResponse(with_identity(html) if identify else html, status_code=status)


WHO_MARK = "<!--learnest:who-->"   # in base.html's header: who is signed in goes there, per request


def with_identity(html: str) -> str:
    """``html`` with the header's mark replaced by who the request is and the sign-in or sign-out button.
    Done per answer, after any page cache: a cached page never shows another person's name."""
    who = current_principal.get()
    if who is None or (not who.signed_in and who.allows("admin")):   # an open server: nobody to name
        return html.replace(WHO_MARK, "", 1)
    if not who.signed_in:
        text = "<span class='muted'>reads are public</span> <a href='/ui/signin'>sign in</a>"
    else:
        admin = " <a href='/ui/admin'>admin</a>" if who.allows("admin") else ""
        text = (f"<span id='who'>signed in as <b>{escape(who.name)}</b> ({who.scope})</span>{admin} "
                "<form method='post' action='/ui/signout' style='display:inline'>"
                "<button type='submit' id='sign-out'>sign out</button></form>")
    return html.replace(WHO_MARK, text, 1)


def error_page(status: int, message: str) -> HTMLResponse:
    """The API's status code and message as a page (a form post never gets JSON back)."""
    return page("error.html", f"Error {status}", status, message=message)


def html_errors(handler: Callable) -> Callable:
    """Show the service's errors (LearnestError: its status) and bad form fields (422) as an error page."""
    @functools.wraps(handler)
    def wrapper(*args, **kwargs):
        try:
            return handler(*args, **kwargs)
        except ValidationError as err:
            return error_page(422, forms.validation_message(err))
        except LearnestError as err:
            return error_page(err.status, str(err))
    return wrapper
