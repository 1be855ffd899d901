"""Helpers shared by the tests: free loopback ports and polling with a deadline."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def eventually(
    predicate: Callable[[], bool], timeout: float = 60.0, interval: float = 0.05
) -> bool:
    """Poll a condition that no event announces (a REST view, a table) until a deadline."""
    deadline = time.monotonic() + timeout
    tick = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            return False
        tick.wait(interval)
    return True
