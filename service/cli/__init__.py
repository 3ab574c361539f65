"""The `learnest` command line: `parser` (the subcommands and their arguments), `commands` (what each
subcommand does), `formatting` (the text they print), `run` (the entry point, `main`)."""
from .formatting import diagnosis_lead, format_model, format_report, format_trained, headline_lines
from .parser import HELP, JSON_HELP, build_parser, subcommands
from .run import main

__all__ = ["HELP", "JSON_HELP", "build_parser", "diagnosis_lead", "format_model", "format_report", "format_trained",
           "headline_lines", "main", "subcommands"]
