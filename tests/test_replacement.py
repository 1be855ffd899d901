"""The replacement policy for stuck robots, end to end: the real server app with its own zenoh
router and robot service (COLONY_REPLACEMENT=off, an API token), agents as threads over BasicX
emulator ptys driving a controller straight into the paper maze's walls, verifying the server's
signatures. `off` leaves the robot its controller, a robot's own `rank` wins over the colony's
`off`, and the stuck ledger records the policy and the steps run before the next stuck event."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics.document import ControllerDocument
from robot_agent.stuck import StuckConfig
from schemas.network import NetworkSpec
from schemas.robots import Replacement, StuckRequest, decode_message, encode_message, replace_key
from schemas.wire import encode_frame
from server.core.models import Robot, Run
from server.core.settings import Settings
from server.runs import crud
from tests.helpers import (
    QUICK,
    WAIT,
    Link,
    client_config,
    constant_drive,
    eventually,
    free_port,
    online,
    save,
    serving,
    virtual_robot,
)

TOKEN = "replacement-test-token"
STUCK = StuckConfig(contact_steps=5)


@dataclass
class Server:
    url: str
    link: Link
    run_id: int
    wall: ControllerDocument
    """Drives straight on at 0.9: stuck at the first wall, again after every escape."""
    key: bytes
    """The server's public key: agents verify every replacement with it."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("replacement")
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
        executors=1,
        api_token=TOKEN,
        replacement="off",
    )
    wall = constant_drive(0.9, 0.9, NetworkSpec())
    with (
        serving(settings) as (url, app),
        httpx.Client(base_url=url, timeout=30, headers=auth()) as client,
    ):
        run_id = client.post("/api/runs", json=QUICK).json()["id"]
        assert eventually(
            lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed", 120
        )
        service = app.state.robots
        with service.sessions.begin() as db:  # the wall controller belongs to the run
            crud.put_controller(
                db,
                sha256=wall.sha256,
                document=wall.to_json(),
                run_id=run_id,
                generation=None,
                fitness=None,
            )
        link = Link(app.state.zenoh, service, f"tcp/127.0.0.1:{zport}", zport)
        yield Server(url, link, run_id, wall, app.state.signer.public_pem.encode())


def auth() -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}"}


def ledger(client: httpx.Client, robot: str) -> list[dict[str, Any]]:
    response = client.get(f"/api/robots/{robot}/stuck")
    assert response.status_code == 200, response.text
    events: list[dict[str, Any]] = response.json()["events"]
    return events


def test_colony_off_keeps_the_controller_and_the_ledger_counts_its_steps(
    server: Server, tmp_path: Path
) -> None:
    save(tmp_path, server.wall)
    with (
        virtual_robot("r-off", server.link, tmp_path, stuck=STUCK, server_key=server.key) as (
            agent,
            _,
        ),
        httpx.Client(base_url=server.url, timeout=30) as client,
    ):
        assert agent.wait_for(lambda: agent.stuck_events >= 2, WAIT)
        assert eventually(lambda: len(ledger(client, "r-off")) >= 2, WAIT)
        assert agent.controller == server.wall  # never replaced
        first, second = ledger(client, "r-off")[:2]
        for event in (first, second):
            assert event["policy"] == "off" and event["replacement_sha256"] is None
            assert event["controller_sha256"] == server.wall.sha256
            assert event["answer"] == "replacement is off for this robot"
        # the robot resumed the wall controller after its escape: the next event closes it
        assert first["steps_run"] == second["step"] - first["step"] > 0
        body = client.get("/api/robots/r-off/stuck").json()
        [wall] = body["controllers"]  # which controller ran for how long, and how often it stuck
        closed = [e["steps_run"] for e in body["events"] if e["steps_run"] is not None]
        assert wall["sha256"] == server.wall.sha256 and wall["steps_run"] == sum(closed)
        assert wall["stuck_events"] == len(body["events"])
        assert wall["seconds_run"] == pytest.approx(sum(closed) * 0.1)
        shown = CliRunner().invoke(cli, ["robot", "stuck", "r-off", "--server", server.url])
        assert shown.exit_code == 0 and "controllers in these events of r-off" in shown.output
        detail = client.get("/api/robots/r-off").json()
        assert (detail["replacement"], detail["replacement_source"]) == ("off", "colony")
    assert (tmp_path / "controller.json").read_text() == server.wall.to_json()


def test_a_robots_own_rank_wins_over_the_colonys_off(server: Server, tmp_path: Path) -> None:
    with server.link.service.sessions.begin() as db:
        run = db.get(Run, server.run_id)
        assert run is not None
        champion = crud.champion(db, run=run)  # the run completed: its validated champion
        assert champion is not None
        best = ControllerDocument.from_json(champion.document)
    with (
        virtual_robot("r-rank", server.link, tmp_path, stuck=STUCK, server_key=server.key) as (
            agent,
            _,
        ),
        httpx.Client(base_url=server.url, timeout=30, headers=auth()) as client,
    ):
        assert eventually(lambda: online(client, "r-rank"), WAIT)  # idle: no controller yet
        own = client.put("/api/robots/r-rank/replacement", json={"policy": "rank"})
        assert own.status_code == 200, own.text
        assert (own.json()["replacement"], own.json()["replacement_source"]) == ("rank", "robot")
        listed = {r["id"]: r for r in client.get("/api/robots").json()}
        assert listed["r-rank"]["replacement"] == "rank"
        assert listed["r-rank"]["replacement_source"] == "robot"
        colony = {r["id"]: r for r in client.get("/api/colony").json()["robots"]}
        assert colony["r-rank"]["replacement_source"] == "robot"

        pushed = client.post("/api/robots/r-rank/controller", json={"sha256": server.wall.sha256})
        assert pushed.json()["accepted"], pushed.text
        assert agent.wait_for(lambda: agent.controller == best, WAIT)
        (event,) = ledger(client, "r-rank")
        assert event["policy"] == "rank" and event["controller_sha256"] == server.wall.sha256
        assert event["replacement_sha256"] == best.sha256
        assert event["answer"] == f"the validated champion of run {server.run_id}"
        assert event["steps_run"] is None  # the replacement is running

        # an operator push comes before the replacement's next stuck event: no steps for it
        pushed = client.post("/api/robots/r-rank/controller", json={"sha256": server.wall.sha256})
        assert pushed.json()["accepted"], pushed.text
        assert eventually(lambda: len(ledger(client, "r-rank")) >= 2, WAIT)
        first, second = ledger(client, "r-rank")[:2]
        assert first["steps_run"] is None
        assert second["policy"] == "rank" and second["controller_sha256"] == server.wall.sha256

        # back to the colony's policy, through the CLI
        result = CliRunner().invoke(
            cli,
            ["robot", "replacement", "r-rank", "colony", "--server", server.url, "--token", TOKEN],
        )
        assert result.exit_code == 0, result.output
        assert "off (colony)" in result.output
        detail = client.get("/api/robots/r-rank").json()
        assert (detail["replacement"], detail["replacement_source"]) == ("off", "colony")
        table = CliRunner().invoke(cli, ["robots", "--server", server.url], env={"COLUMNS": "200"})
        assert table.exit_code == 0 and "replacement" in table.output
        row = next(line for line in table.output.splitlines() if "r-rank" in line)
        assert "off (colony)" in row


def test_policy_changes_need_the_token_and_a_known_value(server: Server, tmp_path: Path) -> None:
    with (
        virtual_robot("r-api", server.link, tmp_path) as _,
        httpx.Client(base_url=server.url, timeout=30) as client,
    ):
        assert eventually(lambda: online(client, "r-api"), WAIT)
        path = "/api/robots/r-api/replacement"
        assert client.put(path, json={"policy": "off"}).status_code == 401
        for body in ({"policy": "random"}, {"policy": 1}, {}):
            refused = client.put(path, json=body, headers=auth())
            assert refused.status_code == 422, body
            assert refused.json()["detail"].startswith("policy: "), refused.text
        unknown = client.put(
            "/api/robots/nobody/replacement", json={"policy": "off"}, headers=auth()
        )
        assert unknown.status_code == 404
        assert client.get("/api/robots/nobody/stuck").status_code == 404
        assert client.get("/api/robots/r-api").json()["replacement_source"] == "colony"
        cli_refused = CliRunner().invoke(
            cli, ["robot", "replacement", "r-api", "random", "--server", server.url]
        )
        assert cli_refused.exit_code == 2


def test_a_robot_cannot_choose_its_policy_and_an_unknown_stored_one_is_ignored(
    server: Server,
) -> None:
    """The policy is read from the server's database, never from the robot: a stuck request
    naming one is malformed, and a stored policy this server does not know (a newer release's)
    gives way to the colony's (`off` here)."""
    with server.link.service.sessions.begin() as db:
        db.add(Robot(id="r-newer", status="online", replacement="someday"))
    request = StuckRequest(
        robot="r-newer", sha256=server.wall.sha256, reason="x", step=1, nonce=secrets.token_hex(16)
    )
    choosing = encode_frame({**request.model_dump(mode="json"), "policy": "rank"})
    with zenoh.open(client_config(server.link.port)) as rogue:
        refused = list(rogue.get(replace_key("r-newer"), payload=choosing, timeout=WAIT))
        answered = list(
            rogue.get(replace_key("r-newer"), payload=encode_message(request), timeout=WAIT)
        )
    assert len(refused) == 1 and refused[0].err is not None
    assert b"malformed" in refused[0].err.payload.to_bytes()
    assert len(answered) == 1 and answered[0].ok is not None
    reply = decode_message(answered[0].ok.payload.to_bytes())
    assert isinstance(reply, Replacement) and reply.document is None
    assert reply.reason == "replacement is off for this robot"
    with httpx.Client(base_url=server.url, timeout=30) as client:
        (event,) = ledger(client, "r-newer")
        detail = client.get("/api/robots/r-newer").json()
    assert event["policy"] == "off"
    assert (detail["replacement"], detail["replacement_source"]) == ("off", "colony")
