"""The robot agent daemon: a fixed-rate control loop over the BasicX link and a zenoh link thread.

Two threads per robot, so the network can never stall the wheels:

- control (real time, period = the simulator's dt): apply a pending controller at the step
  boundary, read the whiskers, `evorobotics.network.step` (batch 1, the simulator's own code),
  send the motor commands, record the sample, feed the stuck detector. Deadline-based: step k
  is due at start + k * period on the monotonic clock, so lateness never accumulates.
- link: opens the zenoh client session (retrying with backoff; a missing router is logged
  once, then at a falling rate), makes sure no other agent runs this robot (or stops the
  agent, naming the other's HOST:PID), declares the robot's liveliness token, takes pushes
  from the command subscriber, acknowledges them once applied, asks the server for a
  replacement when stuck, and delivers buffered trace batches until acknowledged.

The robot keeps running its controller without the network. Traces wait in a bounded buffer
(oldest dropped first, counted) and go out after reconnection. The last accepted controller is
written to the state directory so a restarted agent resumes with it. A stuck robot backs up and
turns (scripted escape) at once, while it asks the server; if a replacement arrives it takes
over after the escape, otherwise the current controller resumes from fresh state. A
replacement that runs `return_after_steps` steps unstuck hands the robot back to its home
controller (the last pushed).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import queue
import re
import secrets
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import zenoh

from evorobotics import network
from evorobotics.document import ControllerDocument
from evorobotics.errors import ControllerDocumentError
from robot_agent.errors import FirmwareError, SerialLinkError
from robot_agent.odometry import Odometry
from robot_agent.stuck import StuckConfig, StuckDetector
from robot_agent.verify import Verifier, pin_key, pinned_key
from schemas.answer import CONSOLIDATION, TARGET, one_answer
from schemas.robots import (
    ESCAPE,
    TRACKER_MAX_AGE_S,
    WHISKERS,
    AgentState,
    ControllerPush,
    PoseSource,
    PushAck,
    Replacement,
    RobotStatus,
    StopCommand,
    StuckRequest,
    TraceAck,
    TraceBatch,
    TrackerPose,
    ack_key,
    agent_key,
    alive_key,
    check_robot_id,
    clamp_poses,
    command_key,
    decode_message,
    encode_message,
    encode_trace,
    replace_key,
    traces_key,
    tracker_key,
)
from schemas.security import ZenohClientAuth
from schemas.wire import WireError
from schemas.world import World

log = logging.getLogger(__name__)


class RobotIO(Protocol):
    """What the control loop needs from the robot: `BasicXDriver` is the real one."""

    def whiskers(self) -> tuple[bool, ...]: ...

    def pose(self) -> tuple[float, float, float]:
        """The true pose; FirmwareError when the robot cannot tell (a real BasicX)."""
        ...

    def set_motors(self, left: float, right: float) -> None: ...

    def stop(self) -> None: ...

    def set_watchdog(self, seconds: float) -> None: ...


def default_state_dir(robot_id: str) -> Path:
    return Path.home() / ".evocolony" / f"agent-{check_robot_id(robot_id)}"


_AGENTS = itertools.count(1)
"""Agents made in this process (tests run several)."""


def _next_address() -> str:
    """HOST:PID of this process, and -N for its Nth agent after the first: the name of a new
    agent's `agent_key` token (one key chunk)."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "_", socket.gethostname()) or "host"
    n = next(_AGENTS)
    return f"{host}:{os.getpid()}" + (f"-{n}" if n > 1 else "")


@dataclass(frozen=True)
class AgentSettings:
    """Identity, server endpoints and timing of one agent; defaults suit a lab EvBot."""

    robot_id: str
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    state_dir: Path | None = None
    """Where the last accepted controller is kept (default ~/.evocolony/agent-ID)."""
    period: float = World().dt
    """Control period: the simulator's step, so the controller sees the same time base."""
    batch_steps: int = 10
    """Samples per trace batch in normal operation (one batch a second)."""
    max_batch: int = 600
    """Samples per batch while a backlog drains after a reconnection."""
    buffer_samples: int = 36_000
    """Trace samples kept while the server is unreachable (one hour at 10 Hz)."""
    request_timeout: float = 2.0
    """Timeout of each `get` (traces, replacement request)."""
    backoff_initial: float = 0.1
    backoff_max: float = 2.0
    watchdog: float = 0.5
    """Firmware watchdog set at start: a dead agent's motors stop within this time."""
    escape_back_steps: int = 8
    escape_turn_steps: int = 6
    escape_speed: float = 0.6
    return_after_steps: int = 300
    """A replacement that has run this many steps without getting stuck hands the robot back to
    its home controller (the last one pushed, or the saved one at start): the situation that
    stuck the home one is over (30 s). 0: a replacement stays."""
    stuck: StuckConfig = field(default_factory=StuckConfig)
    multicast_scouting: bool = False
    server_key: bytes | None = None
    """The server's Ed25519 public key (PEM), pinned in the state dir; with a key given or
    pinned, unsigned, tampered and replayed commands are refused (docs/security.md)."""
    require_signature: bool = False
    """Refuse every command while no server key is given or pinned (what `colony agent` sets)."""
    auth: ZenohClientAuth = field(default_factory=ZenohClientAuth)
    """zenoh user/password and TLS root CA."""
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where odometry starts (x m, y m, heading rad in the lab maze's frame): a real EvBot's
    traces carry the pose integrated from here; an emulated robot reports its true pose."""

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        if not self.connect:
            raise ValueError("an agent needs at least one connect endpoint")
        for name in ("period", "request_timeout", "backoff_initial", "backoff_max", "watchdog"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("batch_steps", "max_batch", "buffer_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.escape_back_steps < 0 or self.escape_turn_steps < 0:
            raise ValueError("escape steps must be >= 0")
        if self.return_after_steps < 0:
            raise ValueError(f"return_after_steps must be >= 0, got {self.return_after_steps}")
        if not 0 < self.escape_speed <= 1:
            raise ValueError(f"escape_speed must be in (0, 1], got {self.escape_speed}")
        if len(self.start_pose) != 3 or not np.isfinite(self.start_pose).all():
            raise ValueError(f"start_pose must be 3 finite numbers, got {self.start_pose}")

    @property
    def state_path(self) -> Path:
        return self.state_dir or default_state_dir(self.robot_id)

    def zenoh_config(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        conf.insert_json5(
            "scouting/multicast/enabled", "true" if self.multicast_scouting else "false"
        )
        # no 16 MiB shared-memory pool per agent (zenoh's default; see server.runs.dispatch)
        conf.insert_json5("transport/shared_memory/enabled", "false")
        for key, value in self.auth.entries():
            conf.insert_json5(key, value)
        return conf


def validate_document(text: str, sha256: str | None = None) -> ControllerDocument:
    """A document an EvBot can run (5 inputs, 2 outputs, finite, sha256 intact), else ValueError."""
    try:
        doc = ControllerDocument.from_json(text)
    except ControllerDocumentError as exc:
        raise ValueError(str(exc)) from None
    if doc.spec.inputs != WHISKERS or doc.spec.outputs != 2:
        raise ValueError(
            f"an EvBot needs {WHISKERS} inputs and 2 outputs, got {doc.spec.inputs} and "
            f"{doc.spec.outputs}"
        )
    if sha256 is not None and doc.sha256 != sha256:
        raise ValueError(f"push names sha256 {sha256} but the document hashes to {doc.sha256}")
    return doc


@dataclass
class _Pending:
    """A change the control loop makes at its next step boundary."""

    document: ControllerDocument | None
    """None: stop."""
    push_id: str | None
    """Acknowledge this push once applied (None: a replacement, nobody waits)."""


@dataclass(frozen=True)
class _Sample:
    step: int
    whiskers: tuple[int, ...]
    motors: tuple[float, float]
    sha256: str | None
    fresh: bool
    at: float
    """Unix seconds when the whiskers were read."""
    pose: tuple[float, float, float]


class _Backoff:
    def __init__(self, initial: float, maximum: float) -> None:
        self._initial, self._max = initial, maximum
        self._delay = initial

    def next(self) -> float:
        delay = self._delay
        self._delay = min(self._delay * 2, self._max)
        return delay

    def reset(self) -> None:
        self._delay = self._initial


NO_ROUTER_REPORT_S = 5.0
"""Seconds without a router before the first reminder; each later one waits twice as long."""


class _Outage:
    """The log of a missing router, calm: the first failed attempt, then a reminder after 5 s,
    10 s, 20 s... (a falling rate), each naming the router's address; zenoh's own error text
    (long, the same every time) at DEBUG only."""

    def __init__(self, robot: str, routers: tuple[str, ...]) -> None:
        self._robot, self._routers = robot, " or ".join(routers)
        self._since: float | None = None
        self._attempts = 0
        self._remind = NO_ROUTER_REPORT_S

    def failed(self, exc: Exception) -> None:
        now = time.monotonic()
        self._attempts += 1
        log.debug("robot %s: %s", self._robot, exc)
        if self._since is None:
            self._since = now
            log.warning(
                "robot %s: no router at %s; retrying (next report in %.0f s, then less and "
                "less often); the robot drives on and keeps its traces",
                self._robot,
                self._routers,
                self._remind,
            )
        elif now - self._since >= self._remind:
            log.info(
                "robot %s: still no router at %s after %.0f s (%d attempts)",
                self._robot,
                self._routers,
                now - self._since,
                self._attempts,
            )
            self._remind *= 2

    def connected(self) -> None:
        if self._since is not None:
            log.info(
                "robot %s: connected to the router at %s after %.0f s",
                self._robot,
                self._routers,
                time.monotonic() - self._since,
            )
        self._since, self._attempts, self._remind = None, 0, NO_ROUTER_REPORT_S


class Agent:
    """One EvBot's daemon between `start()` and `stop()` (or `with`)."""

    def __init__(
        self,
        settings: AgentSettings,
        robot: RobotIO,
        *,
        open_session: Callable[[], zenoh.Session] | None = None,
    ) -> None:
        self.settings = settings
        self.robot = robot
        self._open_session = open_session or (lambda: zenoh.open(settings.zenoh_config()))
        self._lock = threading.RLock()  # predicates of `wait_for` may read the properties
        self.changed = threading.Condition(self._lock)
        """Notified after every control step; wait on it with `wait_for`."""
        self._halt = threading.Event()
        self._wake = threading.Event()
        self._threads: list[threading.Thread] = []
        self._outbox: queue.SimpleQueue[PushAck | StuckRequest | ControllerDocument] = (
            queue.SimpleQueue()
        )
        self._buffer: deque[_Sample] = deque()
        self._pending: _Pending | None = None
        self._after_escape: ControllerDocument | None = None
        self._doc: ControllerDocument | None = None
        self._home: ControllerDocument | None = None
        """The controller the robot returns to after a replacement has done its job."""
        self._ran = 0
        """Steps the current controller has run since it was installed."""
        self._weights = np.empty((1, 0))
        self._net_state = np.empty((1, 0))
        self._fresh = False
        self._state: AgentState = "idle"
        self._escape: list[tuple[float, float]] = []
        self._detector = StuckDetector(settings.stuck, World(dt=settings.period))
        self._lateness: deque[float] = deque(maxlen=1000)
        self._tracked: tuple[float, tuple[float, float]] | None = None
        """An overhead tracker's newest (time, position) of this robot: the stuck detector's
        view from outside (`evocolony/tracker/{id}`, docs/robots.md)."""
        self.pose_source: PoseSource | None = None
        """sim: the robot reports its pose (the emulator); odometry: it cannot (a real BasicX),
        so `_odometry` integrates the motor commands. None until the first step asks."""
        self._odometry = Odometry(settings.start_pose, World(dt=settings.period))
        self._last_at = 0.0
        self.steps = 0
        self.stuck_events = 0
        self.serial_errors = 0
        self.serial_ok = True
        self.dropped = 0
        self.connected = threading.Event()
        """Set while the zenoh session is open."""
        self.delivered = 0
        """Trace samples the server acknowledged."""
        self.address = _next_address()
        """HOST:PID (-N after the first agent of a process), its `agent_key` token's name."""
        self.other_agent: str | None = None
        """HOST:PID of another agent found running this robot; this one then stopped itself
        (notified on `changed`)."""
        self.boot = self._next_boot()
        if settings.server_key is not None:
            pin_key(settings.state_path, settings.server_key)
        pem = pinned_key(settings.state_path)
        self.verifier = Verifier(pem, settings.robot_id, settings.state_path) if pem else None
        """None: no server key given or pinned, commands are taken unsigned (library use)."""
        if self.verifier is None:
            log.warning(
                "robot %s: no server key: commands are %s",
                settings.robot_id,
                "all refused" if settings.require_signature else "not verified",
            )
        saved = self._load_saved()
        if saved is not None:
            self._install(saved)
            self._home = saved

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Agent:
        if self._threads:
            raise RuntimeError("agent already started")
        with contextlib.suppress(SerialLinkError):
            self.robot.set_watchdog(self.settings.watchdog)
        for name, target in (("control", self._control_loop), ("link", self._link_loop)):
            thread = threading.Thread(
                target=target, name=f"agent-{name}-{self.settings.robot_id}", daemon=True
            )
            thread.start()
            self._threads.append(thread)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop both threads, the motors and the session (idempotent)."""
        self._halt.set()
        self._wake.set()
        for thread in self._threads:
            thread.join(timeout)
            if thread.is_alive():
                raise RuntimeError(f"{thread.name} did not stop")
        self._drain_outbox(None)  # persist a controller applied in the last steps
        with contextlib.suppress(SerialLinkError):
            self.robot.stop()

    def __enter__(self) -> Agent:
        return self.start() if not self._threads else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ observation

    @property
    def controller(self) -> ControllerDocument | None:
        with self._lock:
            return self._doc

    @property
    def state(self) -> AgentState:
        with self._lock:
            return self._state

    def buffered(self) -> int:
        with self._lock:
            return len(self._buffer)

    def lateness(self) -> list[float]:
        """Seconds each recent step started after its deadline (the loop's jitter)."""
        with self._lock:
            return list(self._lateness)

    def status(self) -> RobotStatus:
        with self._lock:
            return self._status()

    def _status(self) -> RobotStatus:
        late = sorted(self._lateness)
        p99 = late[min(len(late) - 1, int(0.99 * len(late)))] * 1000 if late else None
        return RobotStatus(
            state=self._state,
            steps=self.steps,
            sha256=self._doc.sha256 if self._doc else None,
            serial_ok=self.serial_ok,
            serial_errors=self.serial_errors,
            resends=getattr(getattr(self.robot, "stats", None), "resends", 0),
            dropped=self.dropped,
            stuck_events=self.stuck_events,
            jitter_p99_ms=p99,
        )

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until `predicate()` (checked after each step, lock held); False on timeout."""
        with self.changed:
            return self.changed.wait_for(predicate, timeout)

    # ------------------------------------------------------------------ control loop

    def _control_loop(self) -> None:
        period = self.settings.period
        due = time.monotonic()
        while not self._halt.is_set():
            now = time.monotonic()
            if now < due:
                self._halt.wait(due - now)
                if self._halt.is_set():
                    break
                now = time.monotonic()
            late = now - due
            try:
                self._step(late)
            except Exception:  # a bug must not leave the wheels on their last command
                log.exception("robot %s: control step failed; motors off", self.settings.robot_id)
                with contextlib.suppress(SerialLinkError):
                    self.robot.stop()
            due += period
            if time.monotonic() - due > period:  # overran a whole period: resynchronise
                due = time.monotonic()

    def _step(self, late: float) -> None:
        with self._lock:
            self._lateness.append(late)
            self._apply_pending()
        try:
            bits = tuple(int(b) for b in self.robot.whiskers())
            # wall-clock time, never stepping back within the traces (a clock set back by NTP)
            at = self._last_at = max(time.time(), self._last_at)
            pose = self._pose()
        except SerialLinkError as exc:
            self._serial_failed(exc)
            return
        with self._lock:
            motors, sha, fresh = self._decide(bits)
        try:
            self.robot.set_motors(motors[0], motors[1])
            ok = True
        except SerialLinkError as exc:
            self._serial_failed(exc)
            ok = False
        if ok and self.pose_source == "odometry":
            self._odometry.advance(*motors)
        with self._lock:
            self.serial_ok = ok
            sample = _Sample(self.steps, bits, motors, sha, fresh, at, pose)
            if len(self._buffer) >= self.settings.buffer_samples:
                self._buffer.popleft()
                self.dropped += 1
            self._buffer.append(sample)
            self.steps += 1
            self._ran += sha is not None
            if self._returns_home():
                assert self._home is not None
                log.info(
                    "robot %s: replacement %s ran %d steps unstuck; back to %s",
                    self.settings.robot_id,
                    sha and sha[:12],
                    self._ran,
                    self._home.sha256[:12],
                )
                self._install(self._home)
                self._outbox.put(self._home)  # persisted by the link thread
                self._wake.set()
            elif sha is not None and self._state == "running":
                tracked = self._tracked
                fresh_pose = (
                    tracked[1] if tracked is not None and at - tracked[0] <= TRACKER_MAX_AGE_S
                    else None
                )  # fmt: skip
                reason = self._detector.update([b == 1 for b in bits], motors, fresh_pose)
                if reason is not None:
                    self.stuck_events += 1
                    self._begin_escape()
                    self._outbox.put(
                        StuckRequest(
                            robot=self.settings.robot_id,
                            sha256=sha,
                            reason=str(reason),
                            step=sample.step,
                            nonce=secrets.token_hex(16),
                        )
                    )
                    self._wake.set()
            self.changed.notify_all()
        if len(self._buffer) >= self.settings.batch_steps:
            self._wake.set()

    def _returns_home(self) -> bool:
        """Whether a replacement has run long enough unstuck to hand the robot back (lock held)."""
        after = self.settings.return_after_steps
        return (
            after > 0
            and self._state == "running"
            and self._home is not None
            and self._doc is not None
            and self._doc.sha256 != self._home.sha256
            and self._ran >= after
        )

    def _pose(self) -> tuple[float, float, float]:
        """The robot's pose as it senses: its own (emulator) or odometry's, for good once the
        firmware refused the `P` request (a real BasicX has none)."""
        if self.pose_source != "odometry":
            try:
                pose = self.robot.pose()
            except FirmwareError:
                log.info("robot %s: no pose from the firmware: odometry", self.settings.robot_id)
                self.pose_source = "odometry"
            else:
                self.pose_source = "sim"
                return pose
        return self._odometry.pose

    def _serial_failed(self, exc: SerialLinkError) -> None:
        log.warning("robot %s: serial link: %s", self.settings.robot_id, exc)
        with self._lock:
            self.serial_ok = False
            self.serial_errors += 1
            self.changed.notify_all()

    def _decide(self, bits: tuple[int, ...]) -> tuple[tuple[float, float], str | None, bool]:
        """This step's motor commands, the controller that made them (None) and freshness."""
        if self._state == "escaping":
            motors = self._escape.pop(0)
            if not self._escape:
                self._end_escape()
            return motors, None, False
        if self._state != "running" or self._doc is None:
            return (0.0, 0.0), None, False
        inputs = np.array([bits], dtype=np.float64)
        out, self._net_state = network.step(self._doc.spec, self._weights, inputs, self._net_state)
        m = network.motor_commands(self._doc.spec, out)[0]
        fresh, self._fresh = self._fresh, False
        return (float(m[0]), float(m[1])), self._doc.sha256, fresh

    def _apply_pending(self) -> None:
        pending, self._pending = self._pending, None
        if pending is None:
            return
        if pending.document is None:
            self._state = "stopped"
            self._escape = []
            self._after_escape = None
        else:
            self._install(pending.document)
            self._home = pending.document
            self._outbox.put(pending.document)  # persisted by the link thread
        if pending.push_id is not None:
            self._outbox.put(
                PushAck(
                    robot=self.settings.robot_id,
                    push_id=pending.push_id,
                    accepted=True,
                    sha256=self._doc.sha256 if self._doc else None,
                )
            )
            self._wake.set()

    def _install(self, doc: ControllerDocument) -> None:
        """Run `doc` from fresh state (lock held, or before the threads start)."""
        self._doc = doc
        self._weights = np.ascontiguousarray(doc.weights[np.newaxis, :])
        self._net_state = network.reset(doc.spec, 1)
        self._fresh = True
        self._ran = 0
        self._state = "running"
        self._escape = []
        self._after_escape = None
        self._detector.reset()

    def _begin_escape(self) -> None:
        s = self.settings
        back = [(-s.escape_speed, -s.escape_speed)] * s.escape_back_steps
        turn = [(s.escape_speed, -s.escape_speed)] * s.escape_turn_steps
        self._escape = back + turn
        self._state = "escaping"
        if not self._escape:
            self._end_escape()

    def _end_escape(self) -> None:
        doc, replaced = self._after_escape or self._doc, self._after_escape is not None
        if doc is not None:
            self._install(doc)
            if replaced:
                self._outbox.put(doc)  # persisted by the link thread

    # ------------------------------------------------------------------ link thread

    def _link_loop(self) -> None:
        backoff = _Backoff(self.settings.backoff_initial, self.settings.backoff_max)
        outage = _Outage(self.settings.robot_id, self.settings.connect)
        while not self._halt.is_set():
            try:
                session = self._open_session()
            except zenoh.ZError as exc:
                outage.failed(exc)
                self._serve_offline(backoff.next())
                continue
            outage.connected()
            backoff.reset()
            try:
                self._serve(session)
            finally:
                self.connected.clear()
                session.close()  # type: ignore[no-untyped-call]

    def _serve_offline(self, delay: float) -> None:
        """Without a session: persist applied controllers; stuck requests go unanswered."""
        deadline = time.monotonic() + delay
        while not self._halt.is_set() and time.monotonic() < deadline:
            self._drain_outbox(None)
            self._wake.wait(min(0.05, max(0.0, deadline - time.monotonic())))
            self._wake.clear()

    def _serve(self, session: zenoh.Session) -> None:
        """Claim the robot (`agent_key`) and serve it, unless another agent has claimed it."""
        claim = session.liveliness().declare_token(agent_key(self.settings.robot_id, self.address))
        try:
            other = self._other_agent(session)
            if other is None:
                self._serve_robot(session)
            else:
                self._stand_down(other)
        finally:
            claim.undeclare()  # type: ignore[no-untyped-call]

    def _other_agent(self, session: zenoh.Session) -> str | None:
        """HOST:PID of another agent whose token claims this robot, or None. Each agent
        declares its own token before it looks, so of two agents starting together at most one
        runs (perhaps neither: then start one again)."""
        mine = agent_key(self.settings.robot_id, self.address)
        replies = session.liveliness().get(
            agent_key(self.settings.robot_id), timeout=self.settings.request_timeout
        )
        for reply in replies:
            if reply.ok is not None and str(reply.ok.key_expr) != mine:
                return str(reply.ok.key_expr).rsplit("/", 1)[1]
        return None

    def _stand_down(self, other: str) -> None:
        """Another agent runs this robot: stop both threads (motors off on `stop`); the owner
        reads `other_agent` and says so (`colony agent` in one line)."""
        with self._lock:
            self.other_agent = other
            self._halt.set()
            self.changed.notify_all()

    def _serve_robot(self, session: zenoh.Session) -> None:
        """The robot's side of the link while the session lasts (`_serve`)."""
        robot = self.settings.robot_id
        inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()

        def on_command(sample: zenoh.Sample) -> None:
            inbox.put(sample.payload.to_bytes())
            self._wake.set()

        def on_pose(sample: zenoh.Sample) -> None:  # an overhead tracker's, if the lab has one
            try:
                pose = decode_message(sample.payload.to_bytes())
            except WireError:
                return  # the server counts bad poses; the detector only misses one
            if isinstance(pose, TrackerPose) and pose.robot == robot:
                with self._lock:
                    if self._tracked is None or pose.at > self._tracked[0]:
                        self._tracked = (pose.at, (pose.x, pose.y))

        token = session.liveliness().declare_token(alive_key(robot))
        subscriber = session.declare_subscriber(command_key(robot), on_command)
        poses = session.declare_subscriber(tracker_key(robot), on_pose)
        self.connected.set()
        backoff = _Backoff(self.settings.backoff_initial, self.settings.backoff_max)
        retry_at = 0.0
        flush_every = self.settings.batch_steps * self.settings.period
        flushed = time.monotonic()
        try:
            while not self._halt.is_set():
                while True:
                    try:
                        self._command(session, inbox.get_nowait())
                    except queue.Empty:
                        break
                self._drain_outbox(session)
                now = time.monotonic()
                # a full batch, or whatever is there once a batch's time has passed
                due = self.buffered() >= self.settings.batch_steps or now - flushed >= flush_every
                if due and now >= retry_at:
                    flushed = now
                    if self._deliver(session):
                        backoff.reset()
                        retry_at = 0.0
                    else:
                        retry_at = time.monotonic() + backoff.next()
                self._wake.wait(self.settings.period)
                self._wake.clear()
        finally:
            poses.undeclare()  # type: ignore[no-untyped-call]
            subscriber.undeclare()  # type: ignore[no-untyped-call]
            token.undeclare()  # type: ignore[no-untyped-call]

    def _command(self, session: zenoh.Session, payload: bytes) -> None:
        robot = self.settings.robot_id
        try:
            message = decode_message(payload)
        except WireError as exc:
            log.warning("robot %s: dropping malformed command: %s", robot, exc)
            return
        if isinstance(message, StopCommand | ControllerPush):
            document = message.document if isinstance(message, ControllerPush) else None
            refused = self._verify(message.kind, message.push_id, message, document)
            if refused is not None:
                log.warning(
                    "robot %s: refusing %s %s: %s", robot, message.kind, message.push_id, refused
                )
                current = self.controller
                self._publish_ack(
                    session,
                    PushAck(
                        robot=robot,
                        push_id=message.push_id,
                        accepted=False,
                        sha256=current.sha256 if current else None,
                        reason=refused,
                    ),
                )
                return
        if isinstance(message, StopCommand):
            with self._lock:
                self._pending = _Pending(None, message.push_id)
            return
        if not isinstance(message, ControllerPush):
            log.warning("robot %s: unexpected %s on the command key", robot, message.kind)
            return
        try:
            doc = validate_document(message.document, message.sha256)
        except ValueError as exc:
            log.warning("robot %s: rejecting push %s: %s", robot, message.push_id, exc)
            current = self.controller
            self._publish_ack(
                session,
                PushAck(
                    robot=robot,
                    push_id=message.push_id,
                    accepted=False,
                    sha256=current.sha256 if current else None,
                    reason=str(exc)[:500],
                ),
            )
            return
        with self._lock:
            self._pending = _Pending(doc, message.push_id)

    def _verify(
        self,
        kind: str,
        push_id: str,
        message: ControllerPush | StopCommand | Replacement,
        document: str | None,
    ) -> str | None:
        """Why a command is refused (unsigned, bad signature, replayed), or None to accept it."""
        if self.verifier is None:
            if self.settings.require_signature:
                return "no server key pinned on this robot: restart it with --server-key FILE"
            return None
        return self.verifier.check(
            kind=kind,
            push_id=push_id,
            seq=message.seq,
            signature=message.signature,
            document=document,
        )

    def _drain_outbox(self, session: zenoh.Session | None) -> None:
        while True:
            try:
                item = self._outbox.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, ControllerDocument):
                self._save(item)
            elif session is None:
                continue  # offline: acks have nobody waiting, stuck requests nobody to answer
            elif isinstance(item, PushAck):
                self._publish_ack(session, item)
            else:
                self._ask_replacement(session, item)

    def _publish_ack(self, session: zenoh.Session, ack: PushAck) -> None:
        session.put(
            ack_key(self.settings.robot_id),
            encode_message(ack),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def _ask_replacement(self, session: zenoh.Session, request: StuckRequest) -> None:
        reply = _ask(
            session,
            replace_key(request.robot),
            encode_message(request),
            self.settings.request_timeout,
        )
        if reply is None:
            log.info("robot %s: no server for a replacement; escaping", request.robot)
            return
        try:
            message = decode_message(reply)
            if not isinstance(message, Replacement):
                raise WireError(f"expected a replacement, got {message.kind}")
            if message.robot != request.robot:
                raise ValueError(f"it names robot {message.robot}")
            if message.document is None:
                log.info("robot %s: no replacement: %s", request.robot, message.reason)
                return
            # signed over this request's nonce: an answer to another request is refused
            refused = self._verify("replacement", request.nonce, message, message.document)
            if refused is not None:
                raise ValueError(refused)
            doc = validate_document(message.document)
        except ValueError as exc:
            log.warning("robot %s: refusing the replacement: %s", request.robot, exc)
            return
        with self._lock:
            if self._state == "escaping":
                self._after_escape = doc
            else:
                self._pending = _Pending(doc, None)

    def _deliver(self, session: zenoh.Session) -> bool:
        """Send the oldest buffered samples; False if the server did not acknowledge."""
        with self._lock:
            if not self._buffer:
                return True
            limit = self.settings.max_batch
            samples = list(itertools.islice(self._buffer, limit))
            status = self._status()
            source = self.pose_source or "odometry"  # known before the first sample is taken
        batch = _batch(self.settings.robot_id, self.boot, samples, status, source)
        reply = _ask(
            session, traces_key(batch.robot), encode_trace(batch), self.settings.request_timeout
        )
        if reply is None:
            return False
        try:
            ack = decode_message(reply)
        except WireError as exc:
            log.warning("robot %s: malformed trace ack: %s", self.settings.robot_id, exc)
            return False
        if not isinstance(ack, TraceAck) or ack.last < batch.last:
            return False
        with self._lock:
            while self._buffer and self._buffer[0].step <= ack.last:
                self._buffer.popleft()
                self.delivered += 1
        return True

    # ------------------------------------------------------------------ state directory

    def _next_boot(self) -> int:
        """Count agent starts in the state dir: (boot, step) identifies a sample for ever."""
        path = self.settings.state_path / "boot"
        try:
            boot = int(path.read_text()) + 1
        except (OSError, ValueError):
            boot = 0
        _write_atomic(path, str(boot))
        return boot

    def _load_saved(self) -> ControllerDocument | None:
        path = self.settings.state_path / "controller.json"
        try:
            return validate_document(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            log.warning("robot %s: ignoring saved controller: %s", self.settings.robot_id, exc)
            return None

    def _save(self, doc: ControllerDocument) -> None:
        _write_atomic(self.settings.state_path / "controller.json", doc.to_json())


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _batch(
    robot: str, boot: int, samples: list[_Sample], status: RobotStatus, source: PoseSource
) -> TraceBatch:
    shas = list(dict.fromkeys(s.sha256 for s in samples if s.sha256 is not None))
    index = {sha: i for i, sha in enumerate(shas)}
    return TraceBatch(
        robot=robot,
        boot=boot,
        controllers=tuple(shas),
        status=status,
        steps=np.array([s.step for s in samples], dtype=np.int64),
        whiskers=np.array([s.whiskers for s in samples], dtype=np.uint8).reshape(-1, WHISKERS),
        motors=np.array([s.motors for s in samples], dtype=np.float64).reshape(-1, 2),
        controller=np.array(
            [ESCAPE if s.sha256 is None else index[s.sha256] for s in samples], dtype=np.int32
        ),
        fresh=np.array([s.fresh for s in samples], dtype=np.bool_),
        times=np.array([s.at for s in samples], dtype=np.float64),
        poses=clamp_poses(np.array([s.pose for s in samples], dtype=np.float64)),
        pose_source=source,
    )


def _ask(session: zenoh.Session, key: str, payload: bytes, timeout: float) -> bytes | None:
    """The server's successful reply's payload, or None (no server, timeout, error reply, or
    more than one answerer)."""
    replies = session.get(
        key, payload=payload, timeout=timeout, target=TARGET, consolidation=CONSOLIDATION
    )
    return one_answer(replies, key, log)
