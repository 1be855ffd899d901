"""Every client input limit gives a clear 4xx or WireError (docs/security.md)."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from schemas.network import MAX_WEIGHTS, NetworkSpec
from schemas.robots import (
    PushAck,
    RobotMessage,
    RobotStatus,
    StuckRequest,
    decode_message,
    decode_trace,
    encode_message,
)
from schemas.security import MAX_ROBOT_MESSAGE, MAX_TRACE_BYTES
from schemas.wire import MAX_HEADER, WireError, decode_frame, encode_frame
from server.core.settings import Settings
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
        (  # issue 38, attack 10: a run of 5 x 10^12 robot-steps was accepted
            {"population": 10_000, "generations": 100_000, "trials": 5, "steps": 1000},
            "robot steps per run (COLONY_MAX_RUN_STEPS)",
        ),
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


def test_a_network_over_a_million_weights_is_refused() -> None:
    with pytest.raises(ValueError, match=f"the limit is {MAX_WEIGHTS}"):
        NetworkSpec(hidden=(1024, 1024), delays=32)


def test_a_frame_header_over_a_mebibyte_is_refused() -> None:
    frame = encode_frame({"kind": "x", "pad": "a" * MAX_HEADER})
    with pytest.raises(WireError, match="header length"):
        decode_frame(frame)
    decode_frame(encode_frame({"kind": "x", "pad": "a" * (MAX_HEADER - 1000)}))


@pytest.mark.parametrize(
    ("message", "field"),
    [
        (StuckRequest.model_construct(robot="r", sha256="a" * 1_000_000, reason="x", step=0,
                                      nonce="0" * 32), "sha256"),
        (StuckRequest.model_construct(robot="r", sha256="A" * 64, reason="x", step=0,
                                      nonce="0" * 32), "sha256"),
        (PushAck.model_construct(robot="r", push_id="p", accepted=True, sha256=None,
                                 reason="x" * 100_000), "reason"),
        (PushAck.model_construct(robot="r", push_id="p" * 65, accepted=True, sha256=None,
                                 reason=""), "push_id"),
    ],
)  # fmt: skip
def test_robot_messages_bound_every_string_field(message: RobotMessage, field: str) -> None:
    """A robot credential cannot grow the database or the log through a message's strings: a
    sha256 is exactly 64 hex digits, a reason or an id short (attack 5 of issue 38)."""
    with pytest.raises(WireError, match=field):
        decode_message(encode_message(message))
    with pytest.raises(ValueError, match="sha256"):
        RobotStatus(state="running", steps=0, sha256="f" * 65, serial_ok=True)


def test_robot_step_counters_beyond_any_agents_are_refused_on_the_wire() -> None:
    """A step of 2**64 - 1 decoded, then overflowed SQLite's integer on the service thread
    (an OverflowError with a traceback per message, and no reply)."""
    huge = StuckRequest.model_construct(
        robot="r", sha256=None, reason="x", step=2**64 - 1, nonce="0" * 32
    )
    with pytest.raises(WireError, match="step"):
        decode_message(encode_message(huge))
    with pytest.raises(ValueError, match="steps"):
        RobotStatus(state="running", steps=2**64 - 1, sha256=None, serial_ok=True)


def test_in_memory_database_keeps_the_signing_key_in_memory() -> None:
    assert Settings(db_url="sqlite://").server_key_path() is None


def test_deeply_nested_json_is_422_not_500(client: httpx.Client) -> None:
    """Attack 6 of issue 38: a body nested past the parser's recursion limit was a 500 with a
    traceback; it is refused before any parser runs, naming the limit."""
    for depth in (65, 100_000):
        body = b'{"maze": ' + b"[" * depth + b"]" * depth + b"}"
        response = client.post(
            "/api/runs", content=body, headers={"content-type": "application/json"}
        )
        assert response.status_code == 422, response.text
        assert f"nested {depth + 1} deep" in response.json()["detail"]  # the object too
    shallow = b'{"maze": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}'
    answer = client.post("/api/runs", content=shallow, headers={"content-type": "application/json"})
    assert "nested" not in answer.text  # brackets inside a string are not nesting


def test_two_origin_headers_are_403_even_when_the_first_is_the_servers(
    client: httpx.Client,
) -> None:
    own = str(client.base_url).rstrip("/")
    response = client.post(
        "/api/runs",
        json={"population": 4, "generations": 1},
        headers=[("origin", own), ("origin", "http://evil.example")],
    )
    assert response.status_code == 403 and "2 Origin headers" in response.json()["detail"]
