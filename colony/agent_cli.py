"""`colony agent` (the EvBot daemon, or a virtual EvBot with --emulate) and `colony replay`."""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, NoReturn

import httpx
import typer

from colony.client import DEFAULT_SERVER, ServerOpt, TokenOpt, base_url_hint, call_server
from colony.options import LogFormatOpt, LogLevelOpt, ZenohPasswordOpt, ZenohRootCaOpt, ZenohUserOpt

if TYPE_CHECKING:
    from robot_agent.agent import AgentSettings
    from robot_agent.sim_body import SimBody
    from schemas.security import ZenohClientAuth


def agent_command(
    robot_id: Annotated[
        str,
        typer.Option(
            "--robot-id", envvar="COLONY_ROBOT_ID", help="this robot's id (a zenoh key chunk)"
        ),
    ],
    serial: Annotated[
        str | None,
        typer.Option(help="BasicX serial port or pyserial URL, e.g. /dev/ttyS0"),
    ] = None,
    connect: Annotated[
        list[str],
        typer.Option(
            "--connect",
            envvar="COLONY_CONNECT",
            help="zenoh endpoint of the server (or a lab zenohd), e.g. tcp/SERVER:7447",
        ),
    ] = ["tcp/127.0.0.1:7447"],  # noqa: B006 - typer reads the default, never mutates it
    state_dir: Annotated[
        Path | None,
        typer.Option(help="where the last accepted controller is kept [~/.evocolony/agent-ID]"),
    ] = None,
    emulate: Annotated[
        bool, typer.Option("--emulate", help="run a virtual EvBot (BasicX emulator on a pty)")
    ] = False,
    maze: Annotated[str, typer.Option(help="--emulate: maze name, gen:SIZE:SEED or path")] = (
        "paper"
    ),
    seed: Annotated[int, typer.Option(help="--emulate: seed of the start pose and gap")] = 0,
    index: Annotated[int, typer.Option(help="--emulate: robot index within the seed")] = 0,
    world: Annotated[
        Path | None,
        typer.Option(
            help="--emulate: the body's world, a JSON world or a run's config.json / best.json"
        ),
    ] = None,
    gap: Annotated[
        bool,
        typer.Option(
            "--gap/--no-gap",
            help="--emulate: the body's whiskers and wheels drawn from the world's reality gap "
            "(by --seed and --index), or exactly the world's whisker_range and motor_gain",
        ),
    ] = True,
    tracker: Annotated[
        bool,
        typer.Option(
            "--tracker",
            help="--emulate: the firmware has no pose request, as a real BasicX, and an "
            "emulated overhead tracker publishes the body's true poses on evocolony/tracker/ID",
        ),
    ] = False,
    tracker_user: Annotated[
        str | None,
        typer.Option(envvar="COLONY_TRACKER_USER", help="--tracker: the tracker's zenoh user"),
    ] = None,
    tracker_password: Annotated[
        str | None,
        typer.Option(envvar="COLONY_TRACKER_PASSWORD", help="its password (prefer the env var)"),
    ] = None,
    baud: Annotated[int, typer.Option(help="serial baud rate")] = 115_200,
    return_after: Annotated[
        int,
        typer.Option(
            help="steps a replacement runs unstuck before the robot goes back to its pushed "
            "controller (0: never)"
        ),
    ] = 300,
    start_pose: Annotated[
        str,
        typer.Option(
            help="--serial: where odometry starts in the lab maze, X,Y,HEADING (m, m, rad)"
        ),
    ] = "0,0,0",
    server_key: Annotated[
        Path | None,
        typer.Option(
            envvar="COLONY_SERVER_PUBLIC_KEY",
            help="the server's public key (PEM, GET /api/server-key); pinned",
        ),
    ] = None,
    server: Annotated[
        str, typer.Option("--server", help="without --server-key or a pinned key: fetch it here")
    ] = DEFAULT_SERVER,
    insecure_no_verify: Annotated[
        bool, typer.Option("--insecure-no-verify", help="accept unsigned pushes (testing only)")
    ] = False,
    zenoh_user: ZenohUserOpt = None,
    zenoh_password: ZenohPasswordOpt = None,
    zenoh_root_ca: ZenohRootCaOpt = None,
    log_level: LogLevelOpt = "INFO",
    log_format: LogFormatOpt = "text",
) -> None:
    """Run an EvBot: the pushed controller at 10 Hz, traces to the server, ask when stuck.

    Every flag is checked before anything is fetched, pinned or started: a bad one is one line
    naming it, exit status 2. Another agent already running this robot id: exit status 1."""
    import zenoh

    from robot_agent.agent import Agent
    from robot_agent.driver import BasicXDriver
    from robot_agent.emulator import BasicXEmulator, FirmwareConfig
    from robot_agent.errors import AgentError
    from robot_agent.tracker import EmulatedTracker

    flags = _checked(
        robot_id=robot_id,
        serial=serial,
        connect=connect,
        state_dir=state_dir,
        emulate=emulate,
        maze=maze,
        seed=seed,
        index=index,
        world=world,
        gap=gap,
        tracker=tracker,
        tracker_user=tracker_user,
        tracker_password=tracker_password,
        baud=baud,
        return_after=return_after,
        start_pose=start_pose,
        server_key=server_key,
        insecure_no_verify=insecure_no_verify,
        zenoh_user=zenoh_user,
        zenoh_password=zenoh_password,
        zenoh_root_ca=zenoh_root_ca,
        log_level=log_level,
        log_format=log_format,
    )
    stop = threading.Event()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        with contextlib.ExitStack() as stack:
            emulator = None
            if flags.body is not None:
                firmware = FirmwareConfig(pose_request=not tracker)
                emulator = stack.enter_context(BasicXEmulator(flags.body, firmware))
            port = emulator.port_path if emulator else str(serial)
            try:
                driver = stack.enter_context(BasicXDriver.open(port, baud))
            except (OSError, ValueError) as exc:
                if emulator is not None:
                    raise
                _refuse("--serial", f"cannot open {port}: {exc}")
            settings = replace(
                flags.settings,
                server_key=_server_key(
                    server_key, flags.settings.state_path, server, insecure_no_verify
                ),
            )
            if tracker and emulator is not None:  # its own session: the robot's may not say
                try:
                    session = stack.enter_context(
                        zenoh.open(replace(settings, auth=flags.tracker_auth).zenoh_config())
                    )
                except zenoh.ZError as exc:
                    typer.echo(
                        f"error: --tracker: the emulated tracker cannot reach the router at "
                        f"{' or '.join(connect)}: {_zenoh_reason(exc)}",
                        err=True,
                    )
                    raise typer.Exit(1) from None
                stack.enter_context(EmulatedTracker(session, robot_id, emulator))
            agent = stack.enter_context(Agent(settings, driver))
            typer.echo(f"agent {robot_id} on {port}, server {' '.join(connect)}")
            while not stop.wait(0.2) and agent.other_agent is None:
                pass
            status = agent.status()
    except (AgentError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None
    if agent.other_agent is not None:
        typer.echo(
            f"error: --robot-id {robot_id}: another agent runs this robot, at "
            f"{agent.other_agent} (HOST:PID): stop it, or give this one another --robot-id",
            err=True,
        )
        raise typer.Exit(1)
    typer.echo(
        f"agent {robot_id}: {status.steps} steps, {agent.delivered} samples delivered, "
        f"{status.stuck_events} stuck events"
    )


@dataclass(frozen=True)
class _Flags:
    """`colony agent`'s flags, checked."""

    settings: AgentSettings
    """Without the server key: it is fetched (trust on first use) once every flag is good."""
    tracker_auth: ZenohClientAuth
    body: SimBody | None
    """The --emulate robot's body, in its maze and world."""


def _refuse(flag: str, problem: object) -> NoReturn:
    """A bad flag: one line naming it and the problem, exit status 2 (a usage error)."""
    typer.echo(f"error: {flag}: {problem}", err=True)
    raise typer.Exit(2)


def _zenoh_reason(exc: Exception) -> str:
    """zenoh's error text without where in zenoh's Rust sources it was raised."""
    return re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc)).strip()


def _checked(
    *,
    robot_id: str,
    serial: str | None,
    connect: list[str],
    state_dir: Path | None,
    emulate: bool,
    maze: str,
    seed: int,
    index: int,
    world: Path | None,
    gap: bool,
    tracker: bool,
    tracker_user: str | None,
    tracker_password: str | None,
    baud: int,
    return_after: int,
    start_pose: str,
    server_key: Path | None,
    insecure_no_verify: bool,
    zenoh_user: str | None,
    zenoh_password: str | None,
    zenoh_root_ca: Path | None,
    log_level: str,
    log_format: str,
) -> _Flags:
    """Every flag of `colony agent` checked, and the logs configured; `_refuse` on the first
    bad one. Nothing is fetched, pinned or started here (the state dir is created)."""
    import zenoh
    from pydantic import ValidationError

    from colony.run_inputs import validation_message
    from evorobotics.errors import EvoError
    from evorobotics.sim import DEFAULT_WORLD
    from robot_agent.agent import AgentSettings
    from robot_agent.sim_body import SimBody
    from robot_agent.verify import load_public_key
    from schemas.robots import check_robot_id
    from schemas.security import ZenohClientAuth
    from schemas.world import world_from_json
    from server.core.logs import as_format, configure

    try:
        check_robot_id(robot_id)
    except ValueError as exc:
        _refuse("--robot-id", exc)
    try:
        fmt = as_format(log_format)
    except ValueError as exc:
        _refuse("--log-format", exc)
    try:
        configure(log_level, fmt, ids={"robot": robot_id})
    except ValueError as exc:
        _refuse("--log-level", exc)
    if (serial is None) == (not emulate):
        _refuse("--serial/--emulate", "give exactly one: --serial PORT (an EvBot) or --emulate")
    if tracker and not emulate:
        _refuse("--tracker", "it emulates a tracker of the --emulate body")
    if zenoh_user is not None and zenoh_user != robot_id:
        _refuse("--zenoh-user", f"the zenoh user {zenoh_user} may only act as robot {zenoh_user}")
    for endpoint in connect:
        protocol, slash, address = endpoint.partition("/")
        if not (protocol and slash and address):
            _refuse("--connect", f"{endpoint!r} is not PROTOCOL/ADDRESS, e.g. tcp/SERVER:7447")
    for flag, path in (("--zenoh-root-ca", zenoh_root_ca), ("--server-key", server_key)):
        if path is not None and not path.is_file():
            _refuse(f"{flag} {path}", "no such file")
    try:
        auth = ZenohClientAuth(user=zenoh_user, password=zenoh_password, root_ca=zenoh_root_ca)
    except ValueError as exc:
        _refuse("--zenoh-user/--zenoh-password", exc)
    try:
        tracker_auth = ZenohClientAuth(
            user=tracker_user, password=tracker_password, root_ca=zenoh_root_ca
        )
    except ValueError as exc:
        _refuse("--tracker-user/--tracker-password", exc)
    try:
        pose = _pose(start_pose)
    except ValueError as exc:
        _refuse("--start-pose", exc)
    for flag, value, low in (("--return-after", return_after, 0), ("--baud", baud, 1)):
        if value < low:
            _refuse(flag, f"must be >= {low}, got {value}")
    settings = AgentSettings(
        robot_id=robot_id,
        connect=tuple(connect),
        state_dir=state_dir,
        require_signature=not insecure_no_verify,
        auth=auth,
        start_pose=pose,
        return_after_steps=return_after,
    )
    try:
        settings.zenoh_config()
    except zenoh.ZError as exc:
        _refuse("--connect", _zenoh_reason(exc))
    state = settings.state_path
    try:
        state.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _refuse("--state-dir", f"cannot create {state}: {exc.strerror}")
    if not os.access(state, os.W_OK):
        _refuse("--state-dir", f"cannot write in {state}")
    if server_key is not None:
        try:
            load_public_key(server_key.read_bytes())
        except (OSError, ValueError) as exc:
            _refuse(f"--server-key {server_key}", exc)
    body = None
    if emulate:
        for flag, value in (("--seed", seed), ("--index", index)):
            if value < 0:
                _refuse(flag, f"must be >= 0, got {value}")
        body_world = DEFAULT_WORLD
        if world is not None:
            try:
                body_world = world_from_json(world.read_bytes())
            except OSError as exc:
                _refuse(f"--world {world}", f"cannot read it: {exc.strerror}")
            except ValidationError as exc:
                _refuse(f"--world {world}", validation_message(exc))
            except ValueError as exc:
                _refuse(f"--world {world}", exc)
        try:
            body = SimBody.create(maze, seed=seed, index=index, gap=gap, world=body_world)
        except (EvoError, ValueError, OSError) as exc:
            _refuse(f"--maze {maze}", exc)
    return _Flags(settings, tracker_auth, body)


def _server_key(path: Path | None, state_dir: Path, server: str, insecure: bool) -> bytes | None:
    """The key to pin: --server-key, else the pinned one (None: the agent loads it), else
    fetched once from the server (trust on first use); None if that fails too."""
    from robot_agent.verify import load_public_key, pinned_key

    if path is not None:
        return path.read_bytes()
    if insecure or pinned_key(state_dir) is not None:
        return None
    try:
        response = httpx.get(f"{server.rstrip('/')}/api/server-key", timeout=10.0)
        if response.is_error:
            why = f"{response.status_code} {response.reason_phrase}"
            raise ValueError(why + base_url_hint(server, response.status_code))
        load_public_key(response.content)
    except (httpx.HTTPError, ValueError) as exc:
        typer.echo(
            f"warning: no server key pinned and none fetched from {server} ({exc}): every "
            "push is refused until the agent restarts with --server-key FILE",
            err=True,
        )
        return None
    typer.echo(f"pinned the server key fetched from {server} in {state_dir}")
    return response.content


def replay_command(
    ctx: typer.Context,
    robot: Annotated[str, typer.Argument(help="robot id")],
    server: ServerOpt = DEFAULT_SERVER,
    token: TokenOpt = None,
) -> None:
    """Sim-to-real check: replay the robot's stored whiskers through its controllers.

    Exit status 0 when every checked motor command is bit-identical, 1 otherwise.
    """
    report = call_server(ctx, server, token, "GET", f"/api/robots/{robot}/replay")
    verdict = "identical" if report["identical"] else "NOT identical"
    typer.echo(
        f"robot {robot}: {verdict}: {report['checked']} samples checked in "
        f"{report['segments']} segments, {report['mismatches']} mismatches, "
        f"{report['skipped']} skipped"
    )
    if report["first_mismatch"]:
        typer.echo(f"first mismatch: {report['first_mismatch']}")
    if not report["identical"]:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add `agent` and `replay` to the root CLI."""
    app.command(name="agent")(agent_command)
    app.command(name="replay")(replay_command)


def _pose(text: str) -> tuple[float, float, float]:
    """`X,Y,HEADING` as three finite floats; ValueError otherwise."""
    parts = text.split(",")
    try:
        x, y, theta = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"must be X,Y,HEADING (3 numbers), got {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, theta)):
        raise ValueError(f"must be finite, got {text!r}")
    return x, y, theta
