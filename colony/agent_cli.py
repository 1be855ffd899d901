"""`colony agent` (the EvBot daemon, or a virtual EvBot with --emulate) and `colony replay`."""

from __future__ import annotations

import contextlib
import math
import signal
import threading
from pathlib import Path
from types import FrameType
from typing import Annotated

import httpx
import typer

from colony.client import DEFAULT_SERVER, ServerOpt, TokenOpt, call_server
from colony.options import LogFormatOpt, LogLevelOpt, ZenohPasswordOpt, ZenohRootCaOpt, ZenohUserOpt


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
    """Run an EvBot: the pushed controller at 10 Hz, traces to the server, ask when stuck."""
    from dataclasses import replace

    import zenoh

    from evorobotics.sim import DEFAULT_WORLD
    from robot_agent.agent import Agent, AgentSettings
    from robot_agent.driver import BasicXDriver
    from robot_agent.emulator import BasicXEmulator, FirmwareConfig
    from robot_agent.errors import AgentError
    from robot_agent.sim_body import SimBody
    from robot_agent.tracker import EmulatedTracker
    from schemas.security import ZenohClientAuth
    from schemas.world import world_from_json
    from server.core.logs import as_format, configure

    try:
        configure(log_level, as_format(log_format), ids={"robot": robot_id})
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if (serial is None) == (not emulate):
        raise typer.BadParameter("give exactly one of --serial PORT or --emulate")
    if tracker and not emulate:
        raise typer.BadParameter("--tracker emulates a tracker of the --emulate body")
    if zenoh_user is not None and zenoh_user != robot_id:
        raise typer.BadParameter(
            f"the zenoh user {zenoh_user} may only act as robot {zenoh_user}, not {robot_id}"
        )
    try:
        auth = ZenohClientAuth(user=zenoh_user, password=zenoh_password, root_ca=zenoh_root_ca)
        probe = AgentSettings(robot_id=robot_id, state_dir=state_dir)
        key = _server_key(server_key, probe.state_path, server, insecure_no_verify)
        settings = AgentSettings(
            robot_id=robot_id,
            connect=tuple(connect),
            state_dir=state_dir,
            server_key=key,
            require_signature=not insecure_no_verify,
            auth=auth,
            start_pose=_pose(start_pose),
            return_after_steps=return_after,
        )
        tracker_auth = ZenohClientAuth(
            user=tracker_user, password=tracker_password, root_ca=zenoh_root_ca
        )
        emulator = (
            BasicXEmulator(
                SimBody.create(
                    maze,
                    seed=seed,
                    index=index,
                    world=DEFAULT_WORLD if world is None else world_from_json(world.read_bytes()),
                ),
                FirmwareConfig(pose_request=not tracker),
            ).start()
            if emulate
            else None
        )
    except (ValueError, OSError) as exc:
        raise typer.BadParameter(str(exc)) from exc
    stop = threading.Event()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    port = emulator.port_path if emulator else str(serial)
    try:
        with contextlib.ExitStack() as stack:
            if tracker and emulator is not None:  # its own session: the robot's may not say
                session = stack.enter_context(
                    zenoh.open(replace(settings, auth=tracker_auth).zenoh_config())
                )
                stack.enter_context(EmulatedTracker(session, robot_id, emulator))
            driver = stack.enter_context(BasicXDriver.open(port, baud))
            agent = stack.enter_context(Agent(settings, driver))
            typer.echo(f"agent {robot_id} on {port}, server {' '.join(connect)}")
            while not stop.wait(1.0):
                pass
            status = agent.status()
        typer.echo(
            f"agent {robot_id}: {status.steps} steps, {agent.delivered} samples delivered, "
            f"{status.stuck_events} stuck events"
        )
    except (AgentError, OSError, zenoh.ZError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    finally:
        if emulator is not None:
            with contextlib.suppress(RuntimeError):
                emulator.stop()


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
        response.raise_for_status()
    except httpx.HTTPError as exc:
        typer.echo(
            f"warning: no server key pinned and none fetched from {server} ({exc}): every "
            "push is refused until the agent restarts with --server-key FILE",
            err=True,
        )
        return None
    load_public_key(response.content)
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
    """`X,Y,HEADING` as three finite floats; ValueError naming the option otherwise."""
    parts = text.split(",")
    try:
        x, y, theta = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--start-pose must be X,Y,HEADING (3 numbers), got {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, theta)):
        raise ValueError(f"--start-pose must be finite, got {text!r}")
    return x, y, theta
