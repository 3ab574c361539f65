"""The service functions: what the JSON routes, the web pages and the in-process facade (`service.local`) all
call, so a route and a page that show or change the same thing cannot disagree (full-stack-fastapi-template's
`crud.py` habit).  Each surface then shapes the answer its own way: JSON in service.api, HTML in service.web,
dicts for the CLI in service.local.

- `catalog`: reading what is stored (flights, models, versions, jobs, evaluations); NotFound with the message
  every surface shows.
- `comparison`: the registry across rows: the evaluations list, a version's lineage, versions side by side.
- `uploads`: the one way a flight gets in (staged, deduplicated, read, stored), and a flight cut again.
- `exports`: a stored evaluation's state estimates as data.
- `deletion`: deleting flights, versions and evaluations, and what depends on each.

They sit above the jobs (a delete checks that nothing still runs; an export reads the result cache's key) and
the storage (tables, blobs and the model registry), and import nothing of the HTTP API or the pages.  Import
from the module that defines a name.
"""
