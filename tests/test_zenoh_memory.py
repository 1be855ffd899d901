"""No zenoh shared memory: without it off, the server's RSS grows by 16 MiB per local robot.

zenoh enables shared memory by default: a session that sends a message above 3 KiB (a trace
batch while a backlog drains, a job) allocates a 16 MiB pool, and the router maps the pool of
every such peer. The server's and the agent's zenoh configs turn it off; these tests send large
queries and replies over real zenoh on 127.0.0.1 and check no shared memory became resident.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from robot_agent.agent import AgentSettings
from server.runs.dispatch import DispatchSettings
from tests.helpers import client_config, dispatch_settings, free_port

STATUS = Path("/proc/self/status")
pytestmark = pytest.mark.skipif(
    not STATUS.exists() or "RssShmem:" not in STATUS.read_text(), reason="needs Linux /proc"
)


def shared_mib() -> float:
    """This process's resident shared memory (where zenoh's pools show up), in MiB."""
    for line in STATUS.read_text().splitlines():
        if line.startswith("RssShmem:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no RssShmem line")


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


@pytest.fixture
def router(port: int) -> Iterator[zenoh.Session]:
    session = zenoh.open(dispatch_settings(port).zenoh_config())
    queryable = session.declare_queryable("load/echo", lambda q: q.reply("load/echo", b"r" * 8000))
    try:
        yield session
    finally:
        queryable.undeclare()  # type: ignore[no-untyped-call]
        session.close()  # type: ignore[no-untyped-call]


def test_the_shared_memory_defaults_are_off() -> None:
    for conf in (DispatchSettings().zenoh_config(), AgentSettings("r").zenoh_config()):
        assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


@pytest.mark.parametrize("client", ["agent", "worker"])
def test_large_messages_allocate_no_shared_memory(
    router: zenoh.Session, port: int, endpoint: str, client: str
) -> None:
    before = shared_mib()
    configs = [
        AgentSettings(f"mem-{i}", connect=(endpoint,)).zenoh_config()
        if client == "agent"
        else client_config(port)  # zenoh's defaults, as a worker's: only the router protects it
        for i in range(4)
    ]
    sessions = [zenoh.open(conf) for conf in configs]
    try:
        for session in sessions:
            replies = list(session.get("load/echo", payload=b"q" * 10_000, timeout=10))
            assert [r.ok.payload.to_bytes() for r in replies if r.ok] == [b"r" * 8000]
        # with zenoh's default each of the 4 clients (and the router) held a 16 MiB pool
        assert shared_mib() - before < 4.0
    finally:
        for session in sessions:
            session.close()  # type: ignore[no-untyped-call]
