"""Failed API-key attempts are throttled per client address: after
``LEARNEST_KEY_FAILURES`` wrong or missing keys within ``LEARNEST_KEY_FAILURE_WINDOW_S`` seconds, that
address's writes get 429 with Retry-After until the oldest of those failures leaves the window, so a key
cannot be guessed at the speed the server answers.  The count lives in memory (per server process): a
restart forgets it, which costs a guesser one window.
"""
from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable

MAX_ADDRESSES = 10_000   # addresses remembered at once: a flood of spoofed sources cannot grow memory


class KeyThrottle:
    """Counts failed key attempts per client address in a sliding window.

    Parameters
    ----------
    max_failures : int
        Failures within the window after which the address is refused (0: never throttle).
    window_s : float
        Length of the window, s.
    clock : callable
        Seconds, monotonic (tests pass a fake one).
    """

    def __init__(self, max_failures: int, window_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_failures, self.window_s, self.clock = max_failures, window_s, clock
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()   # the guard runs on the event loop, the web forms in worker threads

    def retry_after(self, address: str) -> int | None:
        """Whole seconds until ``address`` may try again, or None when it is not throttled."""
        if self.max_failures <= 0:
            return None
        with self._lock:
            recent = self._recent(address)
            if len(recent) < self.max_failures:
                return None
            return max(1, math.ceil(recent[0] + self.window_s - self.clock()))

    def failed(self, address: str) -> None:
        """Record one failed attempt of ``address``."""
        if self.max_failures <= 0:
            return
        with self._lock:
            recent = self._recent(address)
            recent.append(self.clock())
            while len(recent) > self.max_failures:
                recent.popleft()
            self._failures[address] = recent
            self._failures.move_to_end(address)
            while len(self._failures) > MAX_ADDRESSES:
                self._failures.popitem(last=False)

    def _recent(self, address: str) -> deque[float]:
        recent = self._failures.get(address, deque())
        while recent and recent[0] <= self.clock() - self.window_s:
            recent.popleft()
        if not recent:
            self._failures.pop(address, None)
        return recent

    def message(self, retry_after: int) -> str:
        """The 429's detail."""
        return (f"too many failed API-key attempts from this address ({self.max_failures} within "
                f"{self.window_s:g} s, LEARNEST_KEY_FAILURES / LEARNEST_KEY_FAILURE_WINDOW_S): retry in "
                f"{retry_after} s")


def client_address(scope_or_request) -> str:
    """The client's address of an ASGI scope or a Starlette request ("unknown" without one)."""
    client = scope_or_request.get("client") if isinstance(scope_or_request, dict) else scope_or_request.client
    return str(client[0]) if client else "unknown"
