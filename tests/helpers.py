"""Helpers shared by the tests: free loopback ports, polling with a deadline, a dispatcher's
loopback settings, a fast fake evaluator, and a real uvicorn server."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas.run import RunConfig

if TYPE_CHECKING:
    from fastapi import FastAPI

    from server.dispatch import DispatchSettings
    from server.settings import Settings

SERVER_START_S = 60.0


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


def dispatch_settings(port: int, **overrides: Any) -> DispatchSettings:
    """A dispatcher listening on 127.0.0.1:`port` only (multicast scouting off)."""
    from server.dispatch import DispatchSettings

    return DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",), **overrides)


def fake_fitness(genomes: np.ndarray) -> np.ndarray:
    """A deterministic function of each genome alone, as the real fitness is."""
    return np.asarray(np.sin(genomes).sum(axis=1) + genomes[:, 0] ** 2, dtype=np.float64)


def fake_evaluator(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A worker's Evaluator, fast: `fake_fitness`, components of the expected shape."""
    n = genomes.shape[0]
    return fake_fitness(genomes), np.full((n, config.trials, 4), float(generation))


@contextmanager
def serving(settings: Settings) -> Iterator[tuple[str, FastAPI]]:
    """The app under a real uvicorn on `settings.port`; its base URL and the app."""
    import uvicorn

    from server.app import create_app

    app = create_app(settings)
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=settings.port, log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + SERVER_START_S
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            thread.join(0.05)
        yield f"http://127.0.0.1:{settings.port}", app
    finally:
        server.should_exit = True
        thread.join(timeout=30)
