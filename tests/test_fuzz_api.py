"""Schemathesis against a real server's OpenAPI schema: no 5xx, every response as documented.

A real uvicorn on a free loopback port, zenoh off, an SQLite file holding one small finished
run, so routes that take a run id or a sha256 also see existing rows. Examples are few per
operation: the point is to catch crashes on malformed input quickly, within `make test`.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
)

from server.core.settings import Settings
from tests.helpers import SMALL, free_port, serving, wait_status


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    db = tmp_path_factory.mktemp("fuzz") / "colony.db"
    with serving(Settings(db_url=f"sqlite:///{db}", port=free_port(), zenoh=False)) as (
        url,
        _,
    ):
        with httpx.Client(base_url=url, timeout=30) as client:
            run_id = client.post("/api/runs", json={**SMALL, "generations": 2}).json()["id"]
            wait_status(client, run_id, {"completed"})
        yield schemathesis.openapi.from_url(f"{url}/openapi.json")


SKIPPED = {"/api/events", "/api/runs/{run_id}/best/{figure}.png"}
"""Server-sent events never end and figures take seconds each to render: their own tests cover
them (tests/test_dashboard.py and the figure tests)."""


def test_no_server_error_and_responses_match_the_schema(api_schema: Any) -> None:
    """Every operation, a few generated cases each; any 5xx or undocumented response fails."""
    failures: list[str] = []
    operations = [result.ok() for result in api_schema.get_all_operations()]
    operations = [op for op in operations if op.path not in SKIPPED]
    assert len(operations) >= 10

    for operation in operations:

        @settings(
            max_examples=4,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        @given(case=operation.as_strategy())
        def check(case: Any) -> None:
            response = case.call()
            if response.status_code == 503 and case.path.startswith("/api/robots"):
                return  # documented: no robot service without zenoh
            checks = [not_a_server_error, response_schema_conformance, content_type_conformance]
            case.validate_response(response, checks=checks)

        try:
            check()
        except Exception as exc:
            failures.append(f"{operation.label}: {exc}")
    assert not failures, "\n\n".join(failures)
