"""The science workflows on Flights and simulated systems: train, evaluate, diagnose, Table I.

One layer between the estimators and the service: no FastAPI, SQL or job imports here.  The service's routes,
jobs and web pages call these functions, the CLI calls them (its only door to the science, with the service's
in-process facade `service.local` beside it), and so does a notebook (through `learnest`'s public API).

Besides the workflows themselves (`flights`, `estimation`, `diagnosis*`, `thrust_map`, `table1`, `reports`),
four modules give the CLI the science's names it states and reads: `vocabulary` (methods, presets, gap plans,
errors, gains), `files` (flight logs read, estimates written), `learning` (the prior a set of flights calls for)
and `headline` (a report's answer in one sentence, as the web pages say it too).

Nothing is imported here, so a module of this package loads only what it needs.
"""
