"""The service around the science, in rooms (each a package; pyproject.toml's import contracts keep the order):

- `experiments`: the workflows on flights (train, evaluate, diagnose, Table I) and their typed reports; no web,
  SQL or job machinery.
- the surfaces: `api` (the JSON API and the app that serves it), `web` (the HTML pages), `cli` (the `learnest`
  command, over `local`: the service in this process, without HTTP).
- `operations`: the service functions every surface calls (catalog, comparison, uploads, exports, deletion).
- `jobs`: long work as jobs (runner, executors, tasks, scheduler), and reading an upload in a decoder process.
- `storage`: the tables, the database and its migrations, the blob folder, and the model registry kept in them.
- `config`: the one settings object, the only reader of the environment.

A room imports only the rooms below it: surfaces -> local -> operations -> jobs -> storage -> config.
"""
