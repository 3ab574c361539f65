"""Failed API-key attempts are throttled per client network: after
``LEARNEST_KEY_FAILURES`` wrong or missing keys within ``LEARNEST_KEY_FAILURE_WINDOW_S`` seconds, that
network's wrong keys get 429 with Retry-After until the oldest of those failures leaves the window, so a key
cannot be guessed at the speed the server answers.  The right key always passes: a throttle that refused it too
would let anyone on the network lock the key's owner out by sending wrong keys.  The count lives in memory
(per server process): a restart forgets it, which costs a guesser one window.

A network, not an address: one host usually holds many addresses of its /24 (IPv4, loopback too) or /64
(IPv6, where a single host is commonly handed the whole /64), so counting per address gave each new source
address a fresh allowance (`client_network`).
"""
from __future__ import annotations

import ipaddress
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable

MAX_ADDRESSES = 10_000   # networks remembered at once: a flood of spoofed sources cannot grow memory
IPV4_PREFIX, IPV6_PREFIX = 24, 64   # the bits of an address that name its client network


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
        """Whole seconds until ``address`` (a client network) may try a wrong key again, or None when it is not
        throttled."""
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
        return (f"too many failed API-key attempts from this network ({self.max_failures} within "
                f"{self.window_s:g} s, LEARNEST_KEY_FAILURES / LEARNEST_KEY_FAILURE_WINDOW_S): retry in "
                f"{retry_after} s")


def client_address(scope_or_request) -> str:
    """The client's network of an ASGI scope or a Starlette request (`client_network` of its address;
    "unknown" without one)."""
    client = scope_or_request.get("client") if isinstance(scope_or_request, dict) else scope_or_request.client
    return client_network(str(client[0])) if client else "unknown"


def client_network(address: str) -> str:
    """The network a client address is counted in: its IPv4 /24 (loopback included) or IPv6 /64, as
    ``"192.0.2.0/24"``; an IPv4-mapped IPv6 address counts as its IPv4 one, and a text that is no address
    (a Unix socket's) counts as itself.

    >>> client_network("127.0.0.77"), client_network("2001:db8::1"), client_network("::ffff:10.1.2.3")
    ('127.0.0.0/24', '2001:db8::/64', '10.1.2.0/24')
    """
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return address
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    prefix = IPV4_PREFIX if ip.version == 4 else IPV6_PREFIX
    return str(ipaddress.ip_network(f"{ip}/{prefix}", strict=False))
