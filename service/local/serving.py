"""How `learnest serve` runs the app: uvicorn on the starting app (`service.app.starting.create_app`, which
listens at once and loads the service behind it), with the timeouts and connection limits of the settings.

The app and the HTTP protocol (`service.api.server.DeadlineH11Protocol`) are named to uvicorn by import path,
never imported here: every uvicorn worker process imports them itself, and this facade, which the CLI uses,
stays below the app and the API it starts.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..config import Settings

STARTING_APP = "learnest.service.app.starting:create_app"
HTTP_PROTOCOL = "learnest.service.api.server:DeadlineH11Protocol"


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """The keyword arguments of `uvicorn.run` / `uvicorn.Config` that the settings decide.

    Parameters
    ----------
    settings : Settings
        The server's settings.

    Returns
    -------
    dict
        Proxy headers, the HTTP protocol class (by import path), keep-alive, concurrency, header size and
        graceful shutdown.
    """
    proxies = settings.trusted_proxy_addresses
    # uvicorn believes X-Forwarded-For from 127.0.0.1 unless told otherwise: on loopback anyone could then
    # choose the address the key throttle counts.  Believed only from the configured proxies.
    return {"proxy_headers": bool(proxies), "forwarded_allow_ips": ",".join(proxies) if proxies else "",
            "http": HTTP_PROTOCOL,
            "timeout_keep_alive": settings.keep_alive_s,
            "limit_concurrency": settings.limit_concurrency or None,
            "h11_max_incomplete_event_size": settings.max_header_bytes,
            "timeout_graceful_shutdown": settings.graceful_shutdown_s}


def serve(settings: Settings, host: str, port: int, workers: int | None = None) -> None:
    """Run the HTTP service under uvicorn until it is stopped.

    Parameters
    ----------
    settings : Settings
        The server's settings, already validated; the app reads its own from the environment, in every worker.
    host : str
        Address to listen on.
    port : int
        Port to listen on.
    workers : int, optional
        uvicorn worker processes (None: uvicorn's default, one).
    """
    import uvicorn

    uvicorn.run(STARTING_APP, factory=True, host=host, port=port, workers=workers, **uvicorn_options(settings))
