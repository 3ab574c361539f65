"""Jobs: long work behind `202 Accepted`, run by this server process and tracked in the database.

- `runner`: job rows (queued -> running -> succeeded | failed | cancelled), this process's ownership of them (a lease),
  and the sweep of jobs a crashed server left behind.
- `services`: what a job needs, opened once per process (database, blobs, executor, runner).
- `executors`: where the heavy work runs (a local process pool, or Dask); `tasks`: what runs there.
- `training`, `evaluation`, `diagnosis`: start and run one kind of job each; `result_cache`: the
  per-flight evaluation results an evaluation reuses.
- `scheduler`: evaluate new flights with the aliased model, in exactly one process.
"""
