"""The files a workflow reads and writes: flight logs in (`learnest.ingest`: a batch read past its unreadable
files, one file's format, a flight's summary, the take-off/landing cut's grammar) and state estimates out
(`estimators.export`: the format a file name asks for, the estimates written in it)."""
from __future__ import annotations

from learnest.estimators.export import format_of, write_estimates
from learnest.ingest import IngestError, detect, read_flights, summary
from learnest.ingest.align import cut_text, parse_cut
from learnest.ingest.batch import format_errors, read_batch

__all__ = ["IngestError", "cut_text", "detect", "format_errors", "format_of", "parse_cut", "read_batch",
           "read_flights", "summary", "write_estimates"]
