"""Command line and (later) HTTP service on top of ingest, models and estimators."""
