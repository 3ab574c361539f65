"""The HTML side of the service: server-rendered pages for people, on the same app as the JSON API.

- `pages`: the routes (GET pages, POST forms) - they call the same service functions as the JSON routes
  (service.operations.catalog, service.operations.uploads, service.jobs), never a route function;
  `report_pages`: the evaluation and diagnosis reports; `registry_pages`: the registry across rows.
- `rendering`: the Jinja2 environment, a page or an error page as a response.
- `forms`: form fields -> the API's request models, and the API key of form writes.
- `figures`: matplotlib figures as PNG (pages embed them, the CLI writes them to files).
- `templates/`: Jinja2, autoescaped, every page extends `base.html`; `static/`: the one stylesheet.

Nothing is imported here, so `figures` can be used (by the CLI) without loading FastAPI.
"""
