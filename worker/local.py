"""Worker processes started beside the server (`colony server --workers N`).

Each is a fresh interpreter running `colony worker --exit-with-parent` (spawned, never forked:
the server's zenoh session is already open) that connects over loopback exactly like a remote
worker. They stop with the server (SIGTERM, current job delivered first) and, if the server is
SIGKILLed, notice their new parent and exit by themselves.
"""

from __future__ import annotations

import contextlib
import logging
import re
import signal
import subprocess
import sys

log = logging.getLogger(__name__)

_TCP = re.compile(r"^tcp/(?P<host>\[[^\]]*\]|[^:/]+):(?P<port>\d+)$")
_ANY = {"0.0.0.0", "[::]", "*"}


def local_endpoint(listen: tuple[str, ...], connect: tuple[str, ...]) -> str:
    """Where a local worker connects: the first tcp listen endpoint over loopback, else the
    first router the server itself connects to. ValueError if there is neither."""
    for endpoint in listen:
        match = _TCP.match(endpoint)
        if match and int(match["port"]) > 0:
            host = match["host"]
            if host in _ANY:
                host = "127.0.0.1"
            return f"tcp/{host}:{match['port']}"
    if connect:
        return connect[0]
    raise ValueError(
        f"local workers need a tcp listen endpoint with a fixed port or a connect endpoint; "
        f"got listen={list(listen)} connect={list(connect)}"
    )


class LocalWorkers:
    """`count` `colony worker` subprocesses connected to `endpoint`, each evaluating on
    `threads` threads; stop them exactly once."""

    def __init__(
        self, count: int, endpoint: str, *, threads: int = 1, log_level: str = "WARNING"
    ) -> None:
        if count < 0:
            raise ValueError(f"count must be >= 0, got {count}")
        argv = [
            sys.executable,
            "-c",
            "from colony.cli import main; main()",
            "worker",
            "--connect",
            endpoint,
            "--exit-with-parent",
            "--threads",
            str(threads),
            "--log-level",
            log_level,
        ]
        self.processes: list[subprocess.Popen[bytes]] = []
        try:
            for _ in range(count):
                self.processes.append(subprocess.Popen(argv, stdin=subprocess.DEVNULL))
        except BaseException:
            self.stop(timeout=5.0)
            raise
        if count:
            log.info("started %d local workers connecting to %s", count, endpoint)

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.processes]

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM all (each delivers its current job), wait, SIGKILL stragglers, reap."""
        for proc in self.processes:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
        for proc in self.processes:
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                log.warning("local worker %d ignored SIGTERM; killing it", proc.pid)
                proc.kill()
                proc.wait()
        self.processes = []
