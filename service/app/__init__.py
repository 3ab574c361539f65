"""The app: one FastAPI application over the JSON API (`service.api`) and the web pages (`service.web`), and
what `learnest serve` runs.

- `factory`: `create_app`, the factory that builds the app from both rooms (routers, middleware, start-up);
- `starting`: the app uvicorn is given, which listens at once and loads `factory`'s app behind it (`learnest
  serve` names it to uvicorn by import path, `service.local.serving`, so the CLI imports nothing of this room).

It sits above both rooms, so neither imports the other's assembly: `api` never imports `web`, and the pages
use only the API's shared dependencies and request models.  Nothing is imported here, so `starting` loads
without the service behind it.
"""
