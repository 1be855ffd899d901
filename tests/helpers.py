"""Helpers shared by the tests (tests never import each other): free loopback ports, polling
with a deadline, a dispatcher's loopback settings, zenoh router and client configurations, a
fast fake evaluator, a scheduler on a fake clock, `colony evolve`'s champion, a worker thread,
a real uvicorn server, the REST API's small run, robot controllers and agents on BasicX
emulators, and the store's manager steps.

Imports stay light: the app, zenoh, the agent and the science are imported where they are used.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas.network import PRESETS, NetworkSpec
from schemas.run import RunConfig

if TYPE_CHECKING:
    import httpx
    import zenoh
    from fastapi import FastAPI

    from evorobotics.document import ControllerDocument
    from evorobotics.evolution import Told
    from robot_agent.agent import Agent, AgentSettings
    from robot_agent.emulator import BasicXEmulator
    from schemas.wire import Result
    from server.core.settings import Settings
    from server.robots.service import RobotService
    from server.robots.settings import RobotSettings
    from server.robots.signing import Signer
    from server.runs.dispatch import DispatchSettings
    from server.runs.lifecycle import RunManager
    from server.runs.outbox import Written
    from server.runs.policy import Policy
    from server.runs.scheduler import Scheduler
    from worker.main import Evaluator, WorkerStats

SERVER_START_S = 60.0
WAIT = 30.0
"""Seconds to wait for a zenoh, robot or worker event."""
AGENT_WAIT = 20.0
"""Seconds to wait for an agent's own steps over its emulator (no server involved)."""
QUICK = {"population": 8, "generations": 2, "steps": 10, "job_size": 4}
"""A run that completes in about a second."""
SMALL = {"population": 12, "generations": 5, "steps": 20, "job_size": 5}
"""The REST API's small run (`check_small_run`): 5 generations of 12."""
RUN_TIMEOUT_S = 60.0
TINY = RunConfig(population=6, generations=3, steps=5, trials=1, job_size=2, seed=11)
REACTIVE = PRESETS["reactive"]


_HANDED: set[int] = set()
"""Ports `free_port` gave this process: the OS may offer one again before its user binds it."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, never one given before (a test's
    HTTP and zenoh ports differ even when neither is bound yet)."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _HANDED:
            _HANDED.add(port)
            return port


COLONY = [sys.executable, "-c", "from colony.cli import main; main()"]
"""The `colony` command of this interpreter, for a subprocess."""


def wait_until(
    predicate: Callable[[], bool], what: str, timeout: float = 60.0, tick: float = 0.02
) -> None:
    """Poll state that no event announces (a REST API's, a process's) until a deadline; a
    TimeoutError names `what`."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        pause.wait(tick)


class Processes:
    """A test's colony processes (a server, workers), each logging to NAME.log in `tmp`, kept
    for a failure's post-mortem; `close` kills and reaps every one (stopped ones too)."""

    def __init__(self, tmp: Path, client: httpx.Client) -> None:
        self.tmp = tmp
        self.client = client
        self.procs: list[subprocess.Popen[bytes]] = []

    def spawn(self, argv: list[str], env: dict[str, str], log: str) -> subprocess.Popen[bytes]:
        with (self.tmp / f"{log}.log").open("ab") as out:
            proc = subprocess.Popen(
                argv,
                env={**os.environ, **env},
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        self.procs.append(proc)
        return proc

    def healthy(self, server: subprocess.Popen[bytes]) -> bool:
        """Whether `server` (logging to server.log) answers /healthz; its log's tail if it
        exited."""
        import httpx

        if server.poll() is not None:
            tail = (self.tmp / "server.log").read_text(errors="replace")[-2000:]
            raise RuntimeError(f"colony server exited with {server.returncode}:\n{tail}")
        try:
            return self.client.get("/healthz", timeout=1).is_success
        except httpx.TransportError:
            return False

    def get(self, path: str) -> Any:
        response = self.client.get(path)
        assert response.is_success, response.text
        return response.json()

    def close(self) -> None:
        self.client.close()
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
                proc.kill()
        for proc in self.procs:
            proc.wait(timeout=30)


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
    from server.runs.dispatch import DispatchSettings

    return DispatchSettings(listen=(f"tcp/127.0.0.1:{port}",), **overrides)


def fake_components(genomes: np.ndarray, trials: int = 1) -> np.ndarray:
    """(n, trials, 4) Eq 12 components that depend on each genome alone, within what any
    trial's physics allows (offsets under 1 cm, stuck 0 or 1), so the scheduler accepts them."""
    u = (np.sin(genomes[:, :3]) + 1.0) / 2.0
    far = 0.01 * u[:, 0]
    one = np.stack([far, far * u[:, 1], far, (u[:, 2] > 0.5).astype(np.float64)], axis=1)
    return np.repeat(one[:, None, :], trials, axis=1)


def fake_fitness(genomes: np.ndarray) -> np.ndarray:
    """A deterministic function of each genome alone, as the real fitness is: Eq 12 (default
    weights) of `fake_components`."""
    from evorobotics.fitness import mean_fitness
    from schemas.run import FitnessWeights

    return mean_fitness(fake_components(genomes), FitnessWeights())


def plausible_forgery(config: RunConfig, components: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a careful forger claims instead of (..., trials, 4) real components: every trial's
    stuck flag flipped and the fitness Eq 12 of that, all within physics, so only a spot-check
    (a re-evaluation) can tell it from the truth."""
    from evorobotics.fitness import mean_fitness

    forged = np.array(components, dtype=np.float64)
    forged[..., 3] = 1.0 - forged[..., 3]
    shape = forged.shape
    fitness = mean_fitness(forged.reshape(-1, *shape[-2:]), config.fitness).reshape(shape[:-2])
    return fitness, forged


def fake_evaluator(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A worker's Evaluator, fast: `fake_fitness`, its components, and descriptors in [0, 1]
    that depend on each genome alone."""
    descriptors = (np.sin(genomes[:, :4]) + 1.0) / 2.0
    components = fake_components(genomes, config.trials)
    return fake_fitness(genomes), components, descriptors


def reference(
    config: RunConfig,
    evaluator: Callable[
        [RunConfig, int, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]
    ] = fake_evaluator,
) -> list[Told]:
    """The run undisturbed, each generation evaluated whole by `evaluator`."""
    from evorobotics.evolution import RunLoop

    loop = RunLoop(config)
    told = []
    while not loop.done:
        told.append(loop.tell(*evaluator(config, loop.generation, loop.ask())))
    return told


def same_generations(written: list[Written], expected: list[Told]) -> None:
    """Bit for bit: generation numbers, genomes and fitness, in order; only the last is
    marked as its run's last."""
    assert [w.told.generation for w in written] == [t.generation for t in expected]
    for w, t in zip(written, expected, strict=True):
        assert w.told.genomes.tobytes() == t.genomes.tobytes()
        assert w.told.fitness.tobytes() == t.fitness.tobytes()
    assert [w.last for w in written] == [False] * (len(written) - 1) + [True]


class Clock:
    """A fake monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def make_scheduler(policy: Policy | None = None) -> tuple[Scheduler, Clock]:
    """A scheduler on a fake clock (its wall clock 1000 s ahead of it)."""
    from server.runs.policy import Policy
    from server.runs.scheduler import Scheduler

    clock = Clock()
    return Scheduler(policy or Policy(), clock=clock, wall=lambda: 1000.0 + clock.t), clock


def evolved_champion(config: RunConfig, run_id: int) -> ControllerDocument:
    """`colony evolve`'s champion of `config` (`evolve(...).best`), named as the server names
    its run `run_id`'s."""
    from evorobotics.evolution import evolve

    best = evolve(config, threads=1).best
    return replace(best, provenance={**best.provenance, "run": run_id})


def router_config(port: int) -> zenoh.Config:
    """A zenoh router on 127.0.0.1:`port` only: no peers to connect, multicast scouting off."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def client_config(port: int) -> zenoh.Config:
    """A zenoh client of the router on 127.0.0.1:`port`, multicast scouting off."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


_TOKENS: dict[int, dict[str, Any]] = {}
"""id of a `zenoh_client` session -> the worker tokens `as_worker` declared on it."""


@contextmanager
def zenoh_client(port: int) -> Iterator[zenoh.Session]:
    """A client session of the router on 127.0.0.1:`port`, closed on exit."""
    import zenoh

    session = zenoh.open(client_config(port))
    _TOKENS[id(session)] = {}
    try:
        yield session
    finally:
        _TOKENS.pop(id(session))
        session.close()  # type: ignore[no-untyped-call]


def as_worker(session: zenoh.Session, name: str) -> None:
    """Declare the worker `name`'s liveliness token on a `zenoh_client` session, once, as a
    worker does before it asks for jobs: the server leases only to names with a token."""
    from schemas.wire import worker_key

    tokens = _TOKENS[id(session)]
    if name not in tokens:
        tokens[name] = session.liveliness().declare_token(worker_key(name))


def gone_worker(session: zenoh.Session, name: str) -> None:
    """Undeclare the token `as_worker` declared for `name` (the worker leaves)."""
    _TOKENS[id(session)].pop(name).undeclare()


@contextmanager
def worker_thread(port: int, name: str, evaluator: Evaluator) -> Iterator[WorkerStats]:
    """A real worker (its own client session) in a thread; stopped and joined on exit. The
    stats are filled in when it returns."""
    from worker.main import WorkerSettings, WorkerStats, run_worker

    stop = threading.Event()
    stats = WorkerStats()
    settings = WorkerSettings(
        connect=(f"tcp/127.0.0.1:{port}",), name=name, backoff_max_s=0.2, request_timeout_s=5.0
    )

    def body() -> None:
        got = run_worker(settings, stop, evaluator=evaluator)
        stats.jobs_done, stats.errors = got.jobs_done, got.errors

    thread = threading.Thread(target=body, name=f"worker-{name}")
    thread.start()
    try:
        yield stats
    finally:
        stop.set()
        thread.join(timeout=WAIT)
    assert not thread.is_alive()


# ------------------------------------------------------------------------------------ servers


@contextmanager
def uvicorn_running(app: FastAPI, port: int) -> Iterator[threading.Thread]:
    """`app` under a real uvicorn on 127.0.0.1:`port` until exit; the thread it runs in."""
    import uvicorn

    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + SERVER_START_S
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            thread.join(0.05)
        yield thread
    finally:
        server.should_exit = True
        thread.join(timeout=30)


@contextmanager
def serving(settings: Settings) -> Iterator[tuple[str, FastAPI]]:
    """The app under a real uvicorn on `settings.port`; its base URL and the app."""
    from server.app import create_app

    app = create_app(settings)
    with uvicorn_running(app, settings.port):
        yield f"http://127.0.0.1:{settings.port}", app


@dataclass
class Served:
    url: str
    app: FastAPI


@contextmanager
def serve(tmp: Path, app: FastAPI | None = None) -> Iterator[Served]:
    """create_app (or `app`) under a real uvicorn on a free port, stopped on exit."""
    from server.app import create_app
    from server.core.settings import Settings

    port = free_port()
    app = app or create_app(
        Settings(db_url=f"sqlite:///{tmp / 'colony.db'}", port=port, executors=1, zenoh=False)
    )
    with uvicorn_running(app, port) as thread:
        yield Served(f"http://127.0.0.1:{port}", app)
    assert not thread.is_alive(), "uvicorn did not stop"


def completed_run(url: str, config: dict[str, Any]) -> int:
    """Start a run of `config` on the server at `url` and wait until it completes; its id."""
    import httpx

    with httpx.Client(base_url=url, timeout=30) as client:
        run_id: int = client.post("/api/runs", json=config).json()["id"]
        assert eventually(
            lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed", 120
        )
    return run_id


# ---------------------------------------------------------------------------- the REST API


def wait_status(client: httpx.Client, run_id: int, done: set[str]) -> dict[str, Any]:
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        run: dict[str, Any] = client.get(f"/api/runs/{run_id}").json()
        if run["status"] in done:
            return run
        threading.Event().wait(0.05)
    raise TimeoutError(f"run {run_id} did not reach {done}")


def check_small_run(base_url: str) -> None:
    """A SMALL run through the REST API at `base_url` completes and its history, ranking and
    best controller are `evolve`'s, bit for bit."""
    import httpx

    from evorobotics.document import controller_sha256
    from evorobotics.evolution import evolve

    with httpx.Client(base_url=base_url, timeout=30) as client:
        created = client.post("/api/runs", json=SMALL)
        assert created.status_code == 201
        run_id = created.json()["id"]
        run = wait_status(client, run_id, {"completed", "failed"})
        assert run["status"] == "completed", run["error"]
        assert run["generation"] == 5 and run["evaluations"] == 60
        assert run["started_at"] and run["finished_at"]
        history = client.get(f"/api/runs/{run_id}/generations").json()
        assert [g["generation"] for g in history] == list(range(5))
        assert all(g["worst"] <= g["mean"] <= g["best"] for g in history)
        best = client.get(f"/api/runs/{run_id}/best").json()
        assert run["best_fitness"] == history[-1]["best"]
        ranked = client.get(f"/api/runs/{run_id}/individuals").json()
        champion = ranked["individuals"][best["validation"]["training_rank"]]  # one identity
        assert (champion["sha256"], champion["fitness"]) == (best["sha256"], best["fitness"])
        assert ranked["generation"] == 4
        assert [i["rank"] for i in ranked["individuals"]] == list(range(12))
        first = client.get(f"/api/runs/{run_id}/individuals", params={"generation": 0}).json()
        assert all(i["parent"] is None for i in first["individuals"])
        stored = client.get(f"/api/controllers/{best['sha256']}")
        assert stored.status_code == 200 and stored.json()["sha256"] == best["sha256"]
    local = evolve(RunConfig(**SMALL))
    assert best["sha256"] == local.best.sha256
    assert best["weights"] == local.best.to_dict()["weights"]
    assert local.state.ranked is not None  # the store keeps a copy's bytes at its origin only
    spec = RunConfig(**SMALL).network_spec
    assert [i["sha256"] for i in ranked["individuals"]] == [
        controller_sha256(spec, genome) for genome in local.state.ranked
    ]


# --------------------------------------------------------------------------- the run manager


def evaluated(manager: RunManager, worker: str) -> Result | None:
    """`worker` leases a job and evaluates it (not yet settled); None when none is leasable."""
    from server.runs.evaluation import run_job

    job = manager.scheduler.lease(worker)
    return None if job is None else run_job(job, worker)


def drain(manager: RunManager, worker: str = "w") -> None:
    """Evaluate, settle and write jobs until none is leasable."""
    while (result := evaluated(manager, worker)) is not None:
        assert manager.scheduler.settle(result).accepted
        manager.flush()


# ---------------------------------------------------------------------------- robot controllers


def constant_drive(left: float, right: float, spec: NetworkSpec = REACTIVE) -> ControllerDocument:
    """A controller that ignores its whiskers: output biases give these wheel commands."""
    from evorobotics.document import ControllerDocument
    from evorobotics.layout import layout

    w = np.zeros((1, spec.weight_count))
    lay = layout(spec)
    for block in lay.blocks:
        if block.m == spec.layers and block.t == 0 and block.s == 0:
            view = lay.view(w, block)
            for k, motor in enumerate((left, right)):
                y = (motor + 1.0) / 2.0
                view[0, k, -1] = math.log(y / (1.0 - y))
    return ControllerDocument(spec, w[0], provenance={"test": f"drive {left} {right}"})


def random_controller(seed: int, spec: NetworkSpec = REACTIVE) -> ControllerDocument:
    """Weights uniform in [-1, 1) from `seed`."""
    from evorobotics.document import ControllerDocument

    rng = np.random.default_rng(seed)
    return ControllerDocument(spec, rng.uniform(-1, 1, spec.weight_count))


def save(state_dir: Path, doc: ControllerDocument) -> None:
    """Install `doc` as the controller an agent in `state_dir` starts with."""
    state_dir.mkdir(parents=True, exist_ok=True)
    (state_dir / "controller.json").write_text(doc.to_json())


class FixedBody:
    """Physics that stays put and shows preset whiskers: isolates the link from the simulator."""

    dt = 0.1

    def __init__(self) -> None:
        self.bits: tuple[bool, ...] = (True, False, True, False, False)

    def step(self, left: float, right: float) -> None:
        pass

    def whiskers(self) -> tuple[bool, ...]:
        return self.bits


# --------------------------------------------------------------------------------- robot agents


def offline_settings(robot: str, state_dir: Path, **kwargs: object) -> AgentSettings:
    """An agent whose server never answers (a free port nobody listens on)."""
    from robot_agent.agent import AgentSettings

    return AgentSettings(
        robot_id=robot,
        connect=(f"tcp/127.0.0.1:{free_port()}",),
        state_dir=state_dir,
        backoff_max=0.5,
        **kwargs,  # type: ignore[arg-type]
    )


@dataclass
class Colony:
    url: str
    db_url: str
    run_id: int
    app: Any
    tmp: Path


@dataclass
class Link:
    router: zenoh.Session
    service: RobotService
    endpoint: str
    port: int


@contextmanager
def robot_link(
    colony: Colony,
    port: int | None = None,
    *,
    signer: Signer | None = None,
    settings: RobotSettings | None = None,
) -> Iterator[Link]:
    """A router session and a RobotService on the app's database, installed in the app, reading
    archives through the app's run manager; it signs with `signer` if given."""
    import zenoh

    from server.core.db import make_engine
    from server.robots.service import RobotService
    from server.robots.settings import RobotSettings

    port = port or free_port()
    engine = make_engine(colony.db_url)
    router = zenoh.open(router_config(port))
    try:
        settings = settings or RobotSettings(push_timeout=5.0)
        archives = colony.app.state.manager.archive
        rank = colony.app.state.manager.scheduler.rank
        service = RobotService(router, engine, settings, signer, archives, rank).start()
        colony.app.state.robots = service
        try:
            yield Link(router, service, f"tcp/127.0.0.1:{port}", port)
        finally:
            service.close()
            colony.app.state.robots = None
    finally:
        router.close()  # type: ignore[no-untyped-call]
        engine.dispose()


@contextmanager
def virtual_robot(
    robot: str, link: Link, state_dir: Path, seed: int = 0, *, tracker: bool = False, **kwargs: Any
) -> Iterator[tuple[Agent, BasicXEmulator]]:
    """An agent over a BasicX emulator pty (the paper's maze), connected to `link`'s router.
    `tracker`: the firmware has no pose request (a real BasicX) and an overhead tracker
    publishes the body's true poses from a session of its own."""
    import zenoh

    from robot_agent.agent import Agent, AgentSettings
    from robot_agent.driver import BasicXDriver
    from robot_agent.emulator import BasicXEmulator, FirmwareConfig
    from robot_agent.sim_body import SimBody
    from robot_agent.tracker import EmulatedTracker

    firmware = FirmwareConfig(pose_request=not tracker)
    with (
        BasicXEmulator(SimBody.create("paper", seed=seed), firmware) as emulator,
        ExitStack() as stack,
    ):
        if tracker:
            session = stack.enter_context(zenoh.open(client_config(link.port)))
            stack.enter_context(EmulatedTracker(session, robot, emulator))
        settings = AgentSettings(
            robot_id=robot,
            connect=(link.endpoint,),
            state_dir=state_dir,
            backoff_max=0.5,
            request_timeout=1.0,
            **kwargs,
        )
        with BasicXDriver.open(emulator.port_path) as driver, Agent(settings, driver) as agent:
            yield agent, emulator


def online(client: httpx.Client, robot: str) -> bool:
    response = client.get(f"/api/robots/{robot}")
    return response.status_code == 200 and bool(response.json()["online"])
