"""The service around the science, in rooms (each a package; pyproject.toml's import contracts keep the order).
The science it serves is `learnest.workflows` (train, evaluate, diagnose, Table I, their typed reports), one
layer below: it imports nothing of the service.

- the surfaces: `cli` (the `learnest` command, over `local`: the service in this process, without HTTP), and the
  app (`app`: the one FastAPI app `learnest serve` runs) over `web` (the HTML pages) and `api` (the JSON API,
  whose dependencies and request models the pages share; it imports no page).
- `operations`: the service functions every surface calls (catalog, comparison, uploads, exports, deletion).
- `jobs`: long work as jobs (runner, executors, tasks, scheduler), and reading an upload in a decoder process.
- `storage`: the tables, the database and its migrations, the blob folder, and the model registry kept in them.
- `config`: the one settings object, the only reader of the environment.

A room imports only the rooms below it: cli -> app -> web -> api -> local -> operations -> jobs -> storage ->
config.
"""
