"""How `learnest serve` runs the app: uvicorn on the starting app (`starting.create_app`, which listens at once
and loads the service behind it), with the timeouts and connection limits of the settings
(`service.api.server.uvicorn_options`)."""
from __future__ import annotations

from ..api.server import uvicorn_options
from ..config import Settings

STARTING_APP = "learnest.service.app.starting:create_app"   # by name: every uvicorn worker process imports it


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
