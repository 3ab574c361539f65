"""The science workflows on Flights and simulated systems: train, evaluate, diagnose, Table I.

No FastAPI, SQL or job imports here: the service's routes, jobs, web pages and CLI call these functions,
and so does a notebook (through `learnest`'s public API).
"""
