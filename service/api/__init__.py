"""The HTTP API (FastAPI): `errors` (one handler per kind of exception), `deps` (the dependencies routes and web
pages share), `schemas` (request and response models), `routes/` (one module per resource), and what the app
puts around them (`request_guard`, `server`, `throttle`, `docs`).  The app itself is built above this room and
the web pages' (service.app), so nothing here imports a page.

Nothing is imported here, so the web pages can use `deps` and `schemas` without loading the app.
"""
