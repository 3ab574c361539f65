"""How many cores this process may run on: the bound for the threads that training and noise identification
start (one stacked group of ensemble members, or one group of flights, per core)."""
from __future__ import annotations

import os


def usable_cores() -> int:
    """The cores this process may use (its CPU affinity where the platform has one, else the machine's count),
    at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1
