"""Security: REST bearer token, bind refusal, signed robot commands, zenoh usrpwd and TLS."""

from __future__ import annotations

import datetime
import json
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics.evolution import RunLoop
from robot_agent.verify import Verifier
from schemas.run import RunConfig
from schemas.security import ZenohClientAuth, ZenohRoles, ZenohRouterAuth
from server.core.keys import load_or_create_key
from server.core.lab import certificates
from server.core.settings import Settings
from server.robots.signing import Signer
from server.runs.dispatch import Dispatcher
from server.runs.outbox import Written
from server.runs.scheduler import Scheduler
from tests.helpers import dispatch_settings, eventually, fake_evaluator, free_port, serving
from worker.main import WorkerSettings, WorkerStats, run_worker

TOKEN = "s3cret-token"


@pytest.fixture
def client(tmp_path: Path) -> Iterator[httpx.Client]:
    """A real uvicorn server with a token and no evaluators (runs stay queued)."""
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'c.db'}",
        zenoh=False,
        executors=0,
        api_token=TOKEN,
        port=free_port(),
    )
    with serving(settings) as (url, _), httpx.Client(base_url=url, timeout=30) as c:
        yield c


def test_mutations_need_the_token(client: httpx.Client) -> None:
    missing = client.post("/api/runs", json={})
    assert missing.status_code == 401
    assert missing.headers["www-authenticate"].startswith("Bearer")
    assert "missing API token" in missing.json()["detail"]
    wrong = client.post("/api/runs", json={}, headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 401 and "invalid" in wrong.json()["detail"]
    ok = client.post("/api/runs", json={}, headers={"Authorization": f"Bearer {TOKEN}"})
    assert ok.status_code == 201
    assert client.post(f"/api/runs/{ok.json()['id']}/cancel").status_code == 401


def test_reads_open_by_default_and_closed_by_config(client: httpx.Client, tmp_path: Path) -> None:
    assert client.get("/api/runs").status_code == 200
    closed = Settings(
        db_url=f"sqlite:///{tmp_path / 'd.db'}",
        zenoh=False,
        executors=0,
        api_token=TOKEN,
        read_open=False,
        port=free_port(),
    )
    with serving(closed) as (url, _), httpx.Client(base_url=url, timeout=30) as c:
        assert c.get("/api/runs").status_code == 401
        assert c.get("/api/runs", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
        assert c.get(f"/api/runs?access_token={TOKEN}").status_code == 200  # EventSource
        assert c.get("/healthz").status_code == 200
        assert c.get("/").status_code == 200  # the dashboard shell asks for the token


def test_cli_sends_the_token(client: httpx.Client) -> None:
    args = ["run", "start", "--population", "8", "--server", str(client.base_url)]
    runner = CliRunner()
    refused = runner.invoke(cli, args, env={"COLONY_API_TOKEN": ""})
    assert refused.exit_code == 1 and "401" in refused.output
    done = runner.invoke(cli, args, env={"COLONY_API_TOKEN": TOKEN})
    assert done.exit_code == 0, done.output
    assert "run 1" in done.output


def test_server_refuses_a_public_bind_without_token() -> None:
    result = CliRunner().invoke(
        cli, ["server", "--host", "0.0.0.0", "--no-zenoh"], env={"COLONY_API_TOKEN": ""}
    )
    assert result.exit_code == 2
    assert "COLONY_API_TOKEN" in result.output and "--token" in result.output


def test_server_key_created_with_mode_600_and_served(client: httpx.Client, tmp_path: Path) -> None:
    path = tmp_path / "server-key.pem"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    pem = client.get("/api/server-key").text
    assert pem == Signer(load_or_create_key(path)).public_pem
    path.chmod(0o644)
    with pytest.raises(ValueError, match="readable by others"):
        load_or_create_key(path)


DOC = json.dumps({"weights": [0.5, -1.0], "spec": "paper-best"})


def _pair(tmp_path: Path, robot: str = "bot1") -> tuple[Signer, Verifier]:
    signer = Signer.from_file(tmp_path / "key.pem")
    return signer, Verifier(signer.public_pem.encode(), robot, tmp_path / "agent")


def test_signed_push_accepted_once_and_nowhere_else(tmp_path: Path) -> None:
    signer, verifier = _pair(tmp_path)
    seq, sig = signer.sign(kind="push", robot="bot1", push_id="p1", document=DOC)
    ok = verifier.check(kind="push", push_id="p1", seq=seq, signature=sig, document=DOC)
    assert ok is None
    again = verifier.check(kind="push", push_id="p1", seq=seq, signature=sig, document=DOC)
    assert again is not None and "replayed" in again
    other = Verifier(signer.public_pem.encode(), "bot2", tmp_path / "other")
    wrong_robot = other.check(kind="push", push_id="p1", seq=seq, signature=sig, document=DOC)
    assert wrong_robot is not None and "bad signature" in wrong_robot
    unsigned = other.check(kind="push", push_id="p1", seq=seq, signature="", document=DOC)
    assert unsigned is not None and "unsigned" in unsigned
    # the highest seq survives an agent restart
    restarted = Verifier(signer.public_pem.encode(), "bot1", tmp_path / "agent")
    assert restarted.last_seq == seq


@settings(max_examples=30, deadline=None)
@given(position=st.integers(0, len(DOC) - 1), char=st.characters(codec="ascii"))
def test_any_tampered_document_is_refused(position: int, char: str) -> None:
    tampered = DOC[:position] + char + DOC[position + 1 :]
    signer = Signer.from_file(None)
    seq, sig = signer.sign(kind="push", robot="bot1", push_id="p", document=DOC)
    verifier = Verifier(signer.public_pem.encode(), "bot1", Path(tempfile.mkdtemp()))
    reason = verifier.check(kind="push", push_id="p", seq=seq, signature=sig, document=tampered)
    assert (reason is None) == (tampered == DOC)


def test_sequence_strictly_increases_when_the_clock_stalls(tmp_path: Path) -> None:
    signer = Signer(load_or_create_key(tmp_path / "k.pem"), clock=lambda: 5)
    assert [signer.next_seq() for _ in range(3)] == [5, 6, 7]


# ------------------------------------------------------------------ zenoh


GENERATION = RunConfig(population=8, generations=1, trials=1, steps=5, job_size=3)


def _scheduler() -> Scheduler:
    """One run of one generation to serve."""
    scheduler = Scheduler()
    scheduler.add(1, RunLoop(GENERATION), running=True)
    return scheduler


def _run_worker(port: int, auth: ZenohClientAuth, scheduler: Scheduler) -> list[Written]:
    """A real worker with `auth` until the generation is told (or 20 s): what was told."""
    import threading

    stop = threading.Event()
    settings = WorkerSettings(
        connect=(f"tcp/127.0.0.1:{port}",), name=auth.user or "w", backoff_max_s=0.2, auth=auth
    )
    stats: list[WorkerStats] = []
    thread = threading.Thread(
        target=lambda: stats.append(run_worker(settings, stop, evaluator=fake_evaluator))
    )
    thread.start()
    told: list[Written] = []

    def generation_told() -> bool:
        taken = scheduler.take_told()
        scheduler.written(taken)
        told.extend(taken)
        return bool(told)

    eventually(generation_told, timeout=20.0)
    stop.set()
    thread.join(10.0)
    assert not thread.is_alive()
    assert stats[0].jobs_done >= 1 and stats[0].errors == 0
    return told


def test_zenoh_usrpwd_right_password_gets_jobs_wrong_cannot_connect(tmp_path: Path) -> None:
    users = tmp_path / "users.txt"
    users.write_text("worker:right-pass\n")
    port = free_port()
    scheduler = _scheduler()
    router = ZenohRouterAuth(dictionary_file=users, roles=ZenohRoles(workers=("worker",)))
    with Dispatcher(dispatch_settings(port, auth=router), scheduler) as dispatcher:
        bad = WorkerSettings(
            connect=(f"tcp/127.0.0.1:{port}",), name="worker", auth=ZenohClientAuth("worker", "x")
        )
        with pytest.raises(zenoh.ZError):
            zenoh.open(bad.zenoh_config())
        anonymous = WorkerSettings(connect=(f"tcp/127.0.0.1:{port}",), name="anon")
        with pytest.raises(zenoh.ZError):
            zenoh.open(anonymous.zenoh_config())
        told = _run_worker(port, ZenohClientAuth("worker", "right-pass"), scheduler)
        assert dispatcher.alive()
    assert [(w.run_id, w.told.generation, w.last) for w in told] == [(1, 0, True)]
    assert [w.name for w in scheduler.workers()] == ["worker"]


def _certificates(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A new CA and a router certificate for localhost / 127.0.0.1 signed by it (as
    `colony lab init --tls` makes them)."""
    now = datetime.datetime(2024, 1, 1, tzinfo=datetime.UTC)
    ca, cert, key = certificates(["localhost", "127.0.0.1"], now)
    paths = tmp_path / "ca.pem", tmp_path / "cert.pem", tmp_path / "key.pem"
    for path, pem in zip(paths, (ca, cert, key), strict=True):
        path.write_text(pem)
    return paths


def test_zenoh_tls_with_a_test_ca_connects_and_without_it_does_not(tmp_path: Path) -> None:
    ca, cert, key = _certificates(tmp_path)
    port = free_port()
    router = ZenohRouterAuth(certificate=cert, private_key=key)
    settings = dispatch_settings(port, auth=router)
    settings = type(settings)(listen=(f"tls/127.0.0.1:{port}",), auth=router)
    with Dispatcher(settings, _scheduler()):
        untrusted = WorkerSettings(connect=(f"tls/localhost:{port}",), name="u")
        with pytest.raises(zenoh.ZError):
            zenoh.open(untrusted.zenoh_config())
        trusted = WorkerSettings(
            connect=(f"tls/localhost:{port}",), name="t", auth=ZenohClientAuth(root_ca=ca)
        )
        with zenoh.open(trusted.zenoh_config()) as session:
            assert session.info.routers_zid()
