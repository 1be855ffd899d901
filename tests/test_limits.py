"""Every client input limit gives a clear 4xx or WireError (docs/security.md)."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from schemas.robots import decode_message, decode_trace
from schemas.security import MAX_ROBOT_MESSAGE, MAX_TRACE_BYTES
from schemas.wire import WireError
from server.settings import Settings
from tests.helpers import free_port, serving


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    db = tmp_path_factory.mktemp("limits") / "c.db"
    settings = Settings(db_url=f"sqlite:///{db}", zenoh=False, executors=0, port=free_port())
    with serving(settings) as (url, _), httpx.Client(base_url=url, timeout=30) as c:
        yield c


def test_body_over_the_limit_is_413(client: httpx.Client) -> None:
    big = b'{"maze": "' + b"x" * (2 << 20) + b'"}'
    declared = client.post("/api/runs", content=big, headers={"content-type": "application/json"})
    assert declared.status_code == 413 and "limit" in declared.json()["detail"]
    chunked = client.post(
        "/api/runs",
        content=iter([big[:1000], big[1000:]]),
        headers={"content-type": "application/json"},
    )
    assert chunked.status_code == 413


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"population": 10_000, "network": "paper-largest"}, "population x weights"),
        ({"population": 10_000, "trials": 100, "steps": 1000}, "robot steps"),
        ({"maze": "/etc/passwd"}, "not a shipped maze"),
        ({"population": 20_000}, "population"),
    ],
)
def test_run_limits_are_422(client: httpx.Client, body: dict[str, object], words: str) -> None:
    response = client.post("/api/runs", json=body)
    assert response.status_code == 422
    assert words in response.json()["detail"]


def test_oversized_robot_payloads_are_refused() -> None:
    with pytest.raises(WireError, match="exceeds"):
        decode_message(b"\0" * (MAX_ROBOT_MESSAGE + 1))
    with pytest.raises(WireError, match="exceeds"):
        decode_trace(b"\0" * (MAX_TRACE_BYTES + 1))


def test_in_memory_database_keeps_the_signing_key_in_memory() -> None:
    assert Settings(db_url="sqlite://").server_key_path() is None
