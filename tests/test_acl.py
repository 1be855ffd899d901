"""Roles on zenoh: a lab from `colony lab init`, a real server, worker and robot with their
own credentials, and each credential tried at what its role may not do (docs/security.md)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
import zenoh
from typer.testing import CliRunner

from colony.cli import app as cli
from robot_agent.agent import Agent, AgentSettings
from robot_agent.driver import BasicXDriver
from robot_agent.emulator import BasicXEmulator, FirmwareConfig
from robot_agent.sim_body import SimBody
from robot_agent.tracker import EmulatedTracker
from schemas.answer import CONSOLIDATION, TARGET, one_answer
from schemas.network import NetworkSpec
from schemas.robots import (
    POSE_LIMIT,
    TrackerPose,
    ack_key,
    alive_key,
    encode_message,
    traces_key,
    tracker_key,
)
from schemas.security import ZenohClientAuth, ZenohRoles
from schemas.wire import KEY_JOB_NEXT, JobRequest, encode, next_key
from server.core.lab import init_lab
from server.core.settings import Settings
from tests.helpers import (
    client_config,
    eventually,
    free_port,
    online,
    random_controller,
    router_config,
    save,
    serving,
    wait_status,
)
from worker.main import WorkerSettings, run_worker

WAIT = 30.0
RUN = {"population": 8, "generations": 3, "trials": 1, "steps": 20, "seed": 4, "job_size": 2}


@dataclass
class LabServer:
    url: str
    token: str
    endpoint: str
    env: dict[str, dict[str, str]]
    """Each process's env file as a dict: "server", "wk", "bot1", "bot2", "tracker"."""


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


def auth(env: dict[str, str]) -> ZenohClientAuth:
    return ZenohClientAuth(env["COLONY_ZENOH_USER"], env["COLONY_ZENOH_PASSWORD"])


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LabServer]:
    tmp = tmp_path_factory.mktemp("lab")
    made = init_lab(tmp / "lab", workers=["wk"], robots=["bot1", "bot2"], server_host="127.0.0.1")
    env = {"server": read_env(made.server_env)}
    envs = {**made.worker_envs, **made.robot_envs, **made.tracker_envs}
    env |= {name: read_env(path) for name, path in envs.items()}
    server = env["server"]
    zport = free_port()
    settings = Settings(
        db_url=f"sqlite:///{tmp / 'colony.db'}",
        port=free_port(),
        zenoh_listen=[f"tcp/127.0.0.1:{zport}"],
        workers=0,
        api_token=server["COLONY_API_TOKEN"],
        server_key=Path(server["COLONY_SERVER_KEY"]),
        zenoh_users_file=Path(server["COLONY_ZENOH_USERS_FILE"]),
        zenoh_roles_file=Path(server["COLONY_ZENOH_ROLES_FILE"]),
    )
    with serving(settings) as (url, _app):
        yield LabServer(url, server["COLONY_API_TOKEN"], f"tcp/127.0.0.1:{zport}", env)


@contextmanager
def session_of(lab: LabServer, env: dict[str, str]) -> Iterator[zenoh.Session]:
    settings = WorkerSettings(
        connect=(lab.endpoint,), name=env["COLONY_ZENOH_USER"], auth=auth(env)
    )
    with zenoh.open(settings.zenoh_config()) as session:
        yield session


@contextmanager
def worker(lab: LabServer) -> Iterator[None]:
    stop = threading.Event()
    settings = WorkerSettings(
        connect=(lab.endpoint,), name="wk.host-1", backoff_max_s=0.2, auth=auth(lab.env["wk"])
    )
    thread = threading.Thread(target=run_worker, args=(settings, stop))
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(WAIT)


@contextmanager
def robot(
    lab: LabServer, name: str, state: Path, firmware: FirmwareConfig | None = None
) -> Iterator[tuple[Agent, BasicXEmulator]]:
    key = Path(lab.env[name]["COLONY_SERVER_PUBLIC_KEY"]).read_bytes()
    settings = AgentSettings(
        robot_id=name,
        connect=(lab.endpoint,),
        state_dir=state,
        server_key=key,
        require_signature=True,
        request_timeout=1.0,
        auth=auth(lab.env[name]),
    )
    with (
        BasicXEmulator(SimBody.create("paper", seed=1), firmware) as emulator,
        BasicXDriver.open(emulator.port_path) as driver,
        Agent(settings, driver) as agent,
    ):
        yield agent, emulator


def client(lab: LabServer) -> httpx.Client:
    return httpx.Client(
        base_url=lab.url, headers={"Authorization": f"Bearer {lab.token}"}, timeout=WAIT
    )


def no_answer(session: zenoh.Session, key: str, payload: bytes) -> bool:
    """True when the router refused the query: no reply of any kind before the timeout."""
    return not list(session.get(key, payload=payload, timeout=1.0))


def test_roles_let_each_credential_do_its_part_and_nothing_else(
    lab: LabServer, tmp_path: Path
) -> None:
    anonymous = WorkerSettings(connect=(lab.endpoint,), name="anon")
    with pytest.raises(zenoh.ZError):
        zenoh.open(anonymous.zenoh_config())

    heard: list[str] = []
    with (
        session_of(lab, lab.env["wk"]) as rogue_worker,
        session_of(lab, lab.env["bot1"]) as rogue_robot,
        client(lab) as http,
        robot(lab, "bot2", tmp_path / "bot2"),
    ):
        # a worker's credentials cannot act as another worker
        assert no_answer(rogue_worker, next_key("other"), encode(JobRequest(worker="other")))
        # a worker's credentials listen to everything and hold every query open: nothing
        # reaches them, and the run below completes regardless
        listener = rogue_worker.declare_subscriber("evocolony/**", lambda s: heard.append(str(s)))
        holder = rogue_worker.declare_queryable("evocolony/**", lambda q: heard.append(str(q)))
        # a robot's credentials cannot act as a worker, or as another robot
        assert no_answer(rogue_robot, next_key("bot1"), encode(JobRequest(worker="bot1")))
        assert no_answer(rogue_robot, traces_key("bot2"), b"")
        rogue_robot.put(ack_key("bot2"), b"")
        fake_alive = rogue_robot.liveliness().declare_token(alive_key("bot3"))

        with worker(lab):
            run_id = http.post("/api/runs", json=RUN).json()["id"]
            done = wait_status(http, run_id, {"completed", "failed"})
        assert done["status"] == "completed", done
        workers = {w["name"] for w in http.get("/api/workers").json()}
        assert "bot1" not in workers and "other" not in workers

        assert eventually(lambda: online(http, "bot2"), timeout=WAIT)
        pushed = http.post("/api/robots/bot2/controller", json={"run_id": run_id})
        assert pushed.status_code == 200 and pushed.json()["accepted"], pushed.text
        assert http.get("/api/robots/bot3").status_code == 404
        fake_alive.undeclare()  # type: ignore[no-untyped-call]
        listener.undeclare()  # type: ignore[no-untyped-call]
        holder.undeclare()  # type: ignore[no-untyped-call]
    assert heard == []


def test_only_the_tracker_credential_gives_a_robot_its_poses(
    lab: LabServer, tmp_path: Path
) -> None:
    """Issue 37: an overhead tracker publishes each robot's pose on its tracker key under its
    own role; the server stores them with the robot's samples as `pose_source: "tracker"`. A
    robot's credential cannot report where it (or another robot) is."""
    save(tmp_path / "bot1", random_controller(23, NetworkSpec()))  # it moves
    tracker_env = lab.env["tracker"]
    as_tracker = WorkerSettings(
        connect=(lab.endpoint,),
        name="tracker",
        auth=ZenohClientAuth(
            tracker_env["COLONY_TRACKER_USER"], tracker_env["COLONY_TRACKER_PASSWORD"]
        ),
    )
    with (
        robot(lab, "bot1", tmp_path / "bot1", FirmwareConfig(pose_request=False)) as (agent, body),
        session_of(lab, lab.env["bot2"]) as rogue_robot,
        zenoh.open(as_tracker.zenoh_config()) as tracker_session,
        client(lab) as http,
    ):
        assert eventually(lambda: online(http, "bot1"), timeout=WAIT)
        with EmulatedTracker(tracker_session, "bot1", body) as tracker:
            assert eventually(lambda: tracker.published >= 5, timeout=WAIT)
            began = agent.delivered
            for _ in range(10):  # a far-off pose between each of the tracker's
                lie = TrackerPose(robot="bot1", at=time.time(), x=POSE_LIMIT, y=0, theta=0)
                rogue_robot.put(tracker_key("bot1"), encode_message(lie))
                delivered = agent.delivered
                assert agent.wait_for(lambda: agent.delivered > delivered, WAIT)  # noqa: B023
            assert agent.wait_for(lambda: agent.delivered >= began + 40, WAIT)
        samples = http.get("/api/robots/bot1/traces", params={"limit": 30}).json()["samples"]
    assert agent.pose_source == "odometry"  # the robot itself cannot tell
    assert {s["pose_source"] for s in samples} == {"tracker"}
    assert all(s["pose"][0] != POSE_LIMIT for s in samples)
    assert len({tuple(s["pose"]) for s in samples}) > 10  # it moves, and the poses follow


def test_a_second_agent_of_a_robot_is_refused_under_its_role(
    lab: LabServer, tmp_path: Path
) -> None:
    """The robot role may claim its own robot (`agent_key`) and look for other claims: a
    second agent with bot1's credentials finds the first and stops; the first runs on."""
    with robot(lab, "bot1", tmp_path / "first") as (first, _):
        assert first.connected.wait(WAIT)
        with robot(lab, "bot1", tmp_path / "second") as (second, _):
            assert second.wait_for(lambda: second.other_agent is not None, WAIT)
            assert second.other_agent == first.address
            assert not second.connected.is_set()
        assert first.connected.is_set() and first.other_agent is None


def test_a_public_zenoh_listen_needs_a_lab(tmp_path: Path) -> None:
    public = Settings(db_url=f"sqlite:///{tmp_path / 'c.db'}", zenoh_listen=["tcp/0.0.0.0:7447"])
    from server.app import create_app

    with pytest.raises(ValueError, match=r"without authentication: .*colony lab init"):
        create_app(public)
    result = CliRunner().invoke(
        cli, ["server", "--db", f"sqlite:///{tmp_path / 'c.db'}", "--zenoh-listen", "tcp/[::]:7447"]
    )
    assert result.exit_code == 2 and "colony lab init" in result.output
    users = tmp_path / "users"
    users.write_text("w:p\n")
    with pytest.raises(ValueError, match="users file and a roles file go together"):
        create_app(public.model_copy(update={"zenoh_users_file": users}))


def test_lab_init_writes_private_credentials_and_refuses_to_overwrite(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        cli,
        [
            "lab",
            "init",
            str(tmp_path / "lab"),
            "--server-host",
            "10.0.0.1",
            "--tls",
            "--robots",
            "2",
            "--workers",
            "1",
        ],
    )
    assert result.exit_code == 0, result.output
    lab = tmp_path / "lab"
    roles = ZenohRoles.from_file(lab / "zenoh-roles.json")
    assert roles == ZenohRoles(
        workers=("local", "worker-1"), robots=("evbot-1", "evbot-2"), trackers=("tracker",)
    )
    for secret in [
        "zenoh-users",
        "server.env",
        "zenoh-key.pem",
        "server-key.pem",
        "robots/evbot-1.env",
        "workers/worker-1.env",
        "trackers/tracker.env",
    ]:
        assert (lab / secret).stat().st_mode & 0o077 == 0, secret
    robot_env = read_env(lab / "robots" / "evbot-1.env")
    assert robot_env["COLONY_CONNECT"] == "tls/10.0.0.1:7447"
    assert robot_env["COLONY_ROBOT_ID"] == robot_env["COLONY_ZENOH_USER"] == "evbot-1"
    passwords = [line.split(":", 1)[1] for line in (lab / "zenoh-users").read_text().splitlines()]
    assert len(set(passwords)) == len(passwords) == 5
    tracker_env = read_env(lab / "trackers" / "tracker.env")
    assert tracker_env["COLONY_TRACKER_USER"] == "tracker"
    assert tracker_env["COLONY_CONNECT"] == robot_env["COLONY_CONNECT"]
    assert not (lab / "ca-key.pem").exists()  # nothing may mint more certificates
    with pytest.raises(ValueError, match=r"must not contain '\.'"):
        ZenohRoles(workers=("lab.pc",))
    again = CliRunner().invoke(cli, ["lab", "init", str(lab), "--server-host", "h"])
    assert again.exit_code == 2 and "not empty" in again.output


def test_answers_from_two_answerers_are_refused_not_raced(caplog: pytest.LogCaptureFixture) -> None:
    """A second queryable on the server's key (without roles, e.g. on the server host) makes
    the answer an error in the log, never the winner of a race."""
    port = free_port()
    with zenoh.open(router_config(port)) as server, zenoh.open(client_config(port)) as rogue:
        server.declare_queryable(KEY_JOB_NEXT, lambda q: q.reply(q.key_expr, b"server"))
        assert (
            one_answer(
                server.get(next_key("w"), target=TARGET, consolidation=CONSOLIDATION),
                next_key("w"),
                logging.getLogger("test"),
            )
            == b"server"
        )
        rogue.declare_queryable(KEY_JOB_NEXT, lambda q: q.reply(q.key_expr, b"rogue"))
        with zenoh.open(client_config(port)) as worker:

            def two_answerers() -> bool:
                replies = worker.get(next_key("w"), target=TARGET, consolidation=CONSOLIDATION)
                return one_answer(replies, next_key("w"), logging.getLogger("test")) is None

            assert eventually(two_answerers, timeout=WAIT)
    assert "2 answerers replied where only the server may" in caplog.text
