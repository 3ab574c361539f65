"""The HTML side of the service: server-rendered pages for people, on the same app as the JSON API.

- `pages`: the routes (GET pages, POST forms) - they call the same service functions as the JSON routes
  (service.operations.catalog, service.operations.uploads, service.jobs), never a route function;
  `report_pages`: the evaluation and diagnosis reports; `registry_pages`: the registry across rows.
- `rendering`: the Jinja2 environment, a page or an error page as a response.
- `forms`: form fields -> the API's request models, and the API key of form writes.
- `templates/`: Jinja2, autoescaped, every page extends `base.html`; `static/`: the one stylesheet.

The matplotlib figures the pages embed (`service.local.figures`, with the estimators' colours) and the
reports' headline sentences (`learnest.workflows.headline`) live below this room: the CLI says and draws the
same, and it imports nothing of the web.  Nothing is imported here.
"""
