"""One folder per log format (reader, writer)."""
