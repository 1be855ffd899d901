"""The zenoh wire between the server and robot agents: key expressions, messages, codecs.

Defined once here and documented in docs/robots.md (and docs/protocol.md's key table). Frames
are those of `schemas.wire` (`EVC1` prefix, JSON header, raw arrays), so one decoder checks every
length, dtype and shape. Motor commands travel as float64 raw bytes: the server's replay check
compares them bit for bit with what the same controller computes from the same whiskers.

| key | kind | declared by |
| --- | --- | --- |
| `evocolony/robots/{id}/alive` | liveliness token | agent |
| `evocolony/robots/{id}/agent/{host}:{pid}` | liveliness token (which process runs the robot) | agent |
| `evocolony/robots/{id}/command` | subscriber (pushes, stop) | agent |
| `evocolony/robots/{id}/ack` | publication (push acknowledgements) | agent |
| `evocolony/robots/{id}/traces` | queryable `*` (trace batches, acknowledged) | server |
| `evocolony/robots/{id}/replace` | queryable `*` (a stuck robot asks for a controller) | server |
| `evocolony/tracker/{id}` | publication (an overhead tracker's poses of robot `id`) | tracker |

Every key carries the robot id, so zenoh's access control can confine robot `id`'s credentials
to `evocolony/robots/{id}/**`; the server refuses a message whose robot differs from its key's.
Tracker poses sit outside that tree: a robot's credential cannot report where it is.

Traces go by `get` rather than `put` so the agent knows what arrived: a `put` while the router is
down is lost silently, an unacknowledged batch stays in the agent's bounded buffer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.security import MAX_ROBOT_MESSAGE, MAX_TRACE_BYTES, MAX_TRACE_SAMPLES
from schemas.wire import NAME_PATTERN, PROTOCOL, WireError, decode_frame, encode_frame
from schemas.world import GapRobot, World

KEY_ROBOTS_ALIVE = "evocolony/robots/*/alive"
"""Liveliness key expression matching every robot's token."""
KEY_TRACES = "evocolony/robots/*/traces"
"""Queryable (server): a `get` carries one TraceBatch; the reply is a TraceAck."""
KEY_REPLACE = "evocolony/robots/*/replace"
"""Queryable (server): a stuck robot's `get` carries a StuckRequest; the reply a Replacement."""
KEY_ACKS = "evocolony/robots/*/ack"
"""Key expression the server subscribes to for every robot's push acknowledgements."""
KEY_TRACKER = "evocolony/tracker/*"
"""Key expression the server subscribes to for an overhead tracker's TrackerPose of each robot."""
TRACKER_MAX_AGE_S = 0.5
"""A tracker pose describes a moment at most this much after it: a stored sample takes the
newest at or before it, the agent's stuck detector the newest it has, if no older."""

WHISKERS = 5
POSE_LIMIT = 1000.0
"""Metres: a pose coordinate beyond +/-POSE_LIMIT is clamped to it (no lab maze is a km wide)."""
PoseSource = Literal["sim", "tracker", "odometry"]
"""Where a sample's pose comes from: the emulated robot's simulator (its true pose), an overhead
tracker (`TrackerPose`, matched to the sample by the server), or odometry integrated by the
agent from its motor commands with the simulator's body model (a real EvBot without a tracker)."""
ESCAPE = -1
"""Controller index of a sample driven by the scripted escape or a stop, not by a controller."""


def check_robot_id(robot_id: str) -> str:
    """`robot_id` if it is a valid id (one key chunk), else ValueError."""
    if not NAME_PATTERN.match(robot_id):
        raise ValueError(f"robot id {robot_id!r} must match {NAME_PATTERN.pattern}")
    return robot_id


def alive_key(robot_id: str) -> str:
    return f"evocolony/robots/{check_robot_id(robot_id)}/alive"


def agent_key(robot_id: str, where: str = "*") -> str:
    """The token of the agent process that runs robot `robot_id`, `where` = HOST:PID: an agent
    declares it before anything else, and refuses to run when another agent's token is there
    (docs/robots.md). The default `*` matches every agent of the robot."""
    return f"evocolony/robots/{check_robot_id(robot_id)}/agent/{where}"


def traces_key(robot_id: str) -> str:
    return f"evocolony/robots/{check_robot_id(robot_id)}/traces"


def replace_key(robot_id: str) -> str:
    return f"evocolony/robots/{check_robot_id(robot_id)}/replace"


def command_key(robot_id: str) -> str:
    return f"evocolony/robots/{check_robot_id(robot_id)}/command"


def ack_key(robot_id: str) -> str:
    return f"evocolony/robots/{check_robot_id(robot_id)}/ack"


def tracker_key(robot_id: str) -> str:
    """Where an overhead tracker publishes the robot's poses (its own role, not the robot's)."""
    return f"evocolony/tracker/{check_robot_id(robot_id)}"


ROBOT_KEY_KINDS = frozenset({"alive", "command", "ack", "traces", "replace"})


def robot_from_key(key: str) -> str:
    """The robot id of a robot's key (`evocolony/robots/{id}/{kind}`); ValueError otherwise."""
    parts = key.split("/")
    if len(parts) == 4 and parts[:2] == ["evocolony", "robots"] and parts[3] in ROBOT_KEY_KINDS:
        return check_robot_id(parts[2])
    raise ValueError(f"{key!r} is not a robot key")


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
"""A controller's sha256: exactly 64 lowercase hex digits, nothing larger travels or is stored."""
Reason = Annotated[str, Field(max_length=256)]
"""A one-line reason from a peer: bounded, so no message grows the log or the database."""


class _RobotMessage(_Model):
    robot: str

    @field_validator("robot")
    @classmethod
    def _check_robot(cls, value: str) -> str:
        return check_robot_id(value)


class ControllerPush(_Model):
    """Server -> agent on command_key: run this controller document (validated by the agent)."""

    kind: Literal["push"] = "push"
    push_id: str = Field(min_length=1, max_length=64)
    sha256: Sha256
    document: str = Field(description="controller document JSON (evorobotics.document)")
    seq: int = Field(0, ge=0, description="server sequence number; agents refuse seq <= last")
    signature: str = Field(
        "",
        max_length=128,
        description="Ed25519 hex over schemas.security.signed_bytes; '' unsigned",
    )


class StopCommand(_Model):
    """Server -> agent on command_key: stop the motors and idle until the next push."""

    kind: Literal["stop"] = "stop"
    push_id: str = Field(min_length=1, max_length=64)
    seq: int = Field(0, ge=0, description="server sequence number; agents refuse seq <= last")
    signature: str = Field(
        "",
        max_length=128,
        description="Ed25519 hex over schemas.security.signed_bytes; '' unsigned",
    )


class PushAck(_RobotMessage):
    """Agent -> server on ack_key: a push or stop applied (accepted) or refused (reason)."""

    kind: Literal["ack"] = "ack"
    push_id: str = Field(min_length=1, max_length=64)
    accepted: bool
    sha256: Sha256 | None = Field(description="the controller the robot runs after this message")
    reason: Reason = ""


AgentState = Literal["running", "escaping", "stopped", "idle"]
"""idle: no controller yet; stopped: by the operator until the next push."""


class RobotStatus(_Model):
    """The agent's state, sent with every trace batch."""

    state: AgentState
    steps: int = Field(ge=0, lt=2**62, description="control steps run since the agent started")
    sha256: Sha256 | None = Field(description="controller in force")
    serial_ok: bool = Field(description="the BasicX answered the last step's requests")
    serial_errors: int = Field(0, ge=0)
    resends: int = Field(0, ge=0)
    dropped: int = Field(0, ge=0, description="trace samples dropped from a full buffer")
    stuck_events: int = Field(0, ge=0)
    jitter_p99_ms: float | None = Field(None, ge=0.0, allow_inf_nan=False)


class TraceHeader(_RobotMessage):
    kind: Literal["trace"] = "trace"
    protocol: int = Field(PROTOCOL, description="schemas.wire.PROTOCOL of the agent")
    pose_source: PoseSource
    boot: int = Field(ge=0, lt=2**31, description="agent start count: (boot, step) names a sample")
    controllers: list[Sha256] = Field(
        max_length=MAX_TRACE_SAMPLES, description="sha256 of each controller index in the batch"
    )
    status: RobotStatus


@dataclass(frozen=True)
class TraceBatch:
    """Consecutive control samples of one robot during one agent start (`boot`).

    steps (n,) int64 (one more per sample: the agent sends consecutive samples), whiskers (n, 5)
    uint8, motors (n, 2) float64 in [-1, 1] exactly as the controller computed them (before the
    wire's 1/1000 quantisation), controller (n,) int32 index into
    `controllers` or ESCAPE, fresh (n,) bool: the controller's state was reset before this step,
    times (n,) float64 Unix seconds when the whiskers were read (non-decreasing), poses (n, 3)
    float64 x, y (metres, within +/-POSE_LIMIT) and heading (radians, in [-pi, pi]) then, from
    `pose_source`.
    """

    robot: str
    boot: int
    controllers: tuple[str, ...]
    status: RobotStatus
    steps: np.ndarray
    whiskers: np.ndarray
    motors: np.ndarray
    controller: np.ndarray
    fresh: np.ndarray
    times: np.ndarray
    poses: np.ndarray
    pose_source: PoseSource

    def __post_init__(self) -> None:
        check_robot_id(self.robot)
        n = self.steps.shape[0] if self.steps.ndim == 1 else -1
        expected = {
            "steps": ((n,), np.int64),
            "whiskers": ((n, WHISKERS), np.uint8),
            "motors": ((n, 2), np.float64),
            "controller": ((n,), np.int32),
            "fresh": ((n,), np.bool_),
            "times": ((n,), np.float64),
            "poses": ((n, 3), np.float64),
        }
        for name, (shape, dtype) in expected.items():
            value: np.ndarray = getattr(self, name)
            if value.shape != shape or value.dtype != dtype:
                raise WireError(
                    f"trace {name} must be {np.dtype(dtype)} {shape}, got {value.dtype} "
                    f"{value.shape}"
                )
        if n < 1:
            raise WireError("a trace batch holds at least one sample")
        if np.any(np.diff(self.steps) <= 0):
            raise WireError("trace steps must increase")
        if np.any(self.whiskers > 1):
            raise WireError("whisker bits must be 0 or 1")
        if not np.isfinite(self.motors).all() or np.any(np.abs(self.motors) > 1.0):
            raise WireError("motor commands must be finite and within [-1, 1]")
        bad = (self.controller < ESCAPE) | (self.controller >= len(self.controllers))
        if np.any(bad):
            raise WireError("controller index out of range")
        if not np.isfinite(self.times).all() or np.any(self.times < 0):
            raise WireError("sample times must be finite Unix seconds")
        if np.any(np.diff(self.times) < 0):
            raise WireError("sample times must not decrease")
        if not np.isfinite(self.poses).all():
            raise WireError("poses must be finite")
        if np.any(np.abs(self.poses[:, :2]) > POSE_LIMIT) or np.any(
            np.abs(self.poses[:, 2]) > np.pi
        ):
            raise WireError(f"pose x, y must lie within +/-{POSE_LIMIT} m and heading in [-pi, pi]")

    @property
    def first(self) -> int:
        return int(self.steps[0])

    @property
    def last(self) -> int:
        return int(self.steps[-1])


def clamp_poses(poses: np.ndarray) -> np.ndarray:
    """Finite poses brought into range: x, y clamped to +/-POSE_LIMIT, a heading beyond pi
    wrapped into [-pi, pi] (a peer's odometry may wind up many turns); values in range are
    kept bit for bit, non-finite ones stay (and are refused)."""
    out = np.array(poses, dtype=np.float64).reshape(-1, 3)
    xy = out[:, :2]
    out[:, :2] = np.where(np.isfinite(xy), np.clip(xy, -POSE_LIMIT, POSE_LIMIT), xy)
    wound = np.abs(out[:, 2]) > np.pi
    out[wound, 2] = np.arctan2(np.sin(out[wound, 2]), np.cos(out[wound, 2]))
    return out


def encode_trace(batch: TraceBatch) -> bytes:
    header = TraceHeader(
        robot=batch.robot,
        boot=batch.boot,
        controllers=list(batch.controllers),
        status=batch.status,
        pose_source=batch.pose_source,
    )
    arrays = {
        "steps": batch.steps,
        "whiskers": batch.whiskers,
        "motors": batch.motors,
        "controller": batch.controller,
        "fresh": batch.fresh,
        "times": batch.times,
        "poses": batch.poses,
    }
    return encode_frame(header.model_dump(mode="json"), arrays)


def decode_trace(payload: bytes) -> TraceBatch:
    """A trace batch; WireError when malformed, of another protocol or over MAX_TRACE_BYTES /
    MAX_TRACE_SAMPLES. Finite poses out of range are clamped (`clamp_poses`)."""
    if len(payload) > MAX_TRACE_BYTES:
        raise WireError(f"trace batch of {len(payload)} bytes exceeds {MAX_TRACE_BYTES}")
    header, arrays = decode_frame(payload)
    try:
        parsed = TraceHeader.model_validate(header)
    except ValidationError as exc:
        raise WireError(f"trace header: {exc}") from exc
    if parsed.protocol != PROTOCOL:
        raise WireError(f"the agent speaks protocol {parsed.protocol}, the server {PROTOCOL}")
    names = {"steps", "whiskers", "motors", "controller", "fresh", "times", "poses"}
    if set(arrays) != names:
        raise WireError(f"trace arrays must be {sorted(names)}, got {sorted(arrays)}")
    if len(arrays["steps"]) > MAX_TRACE_SAMPLES:
        raise WireError(
            f"trace batch of {len(arrays['steps'])} samples exceeds {MAX_TRACE_SAMPLES}"
        )
    if arrays["poses"].ndim == 2 and arrays["poses"].shape[1:] == (3,):
        arrays["poses"] = clamp_poses(arrays["poses"])
    return TraceBatch(
        robot=parsed.robot,
        boot=parsed.boot,
        controllers=tuple(parsed.controllers),
        status=parsed.status,
        pose_source=parsed.pose_source,
        **{name: arrays[name] for name in names},
    )


class TraceAck(_RobotMessage):
    """Server -> agent, reply on KEY_TRACES: samples through step `last` are stored."""

    kind: Literal["trace-ack"] = "trace-ack"
    last: int


class StuckRequest(_RobotMessage):
    """Agent -> server on KEY_REPLACE: the robot is stuck with `sha256`; send another."""

    kind: Literal["stuck"] = "stuck"
    sha256: Sha256 | None
    reason: str = Field(max_length=64)
    step: int = Field(ge=0, lt=2**62)
    nonce: str = Field(
        pattern=r"^[0-9a-f]{32}$",
        description="fresh random hex of this request: the replacement is signed over it (as its "
        "push id), so it answers this request and no other",
    )


class Replacement(_RobotMessage):
    """Server -> agent, reply on KEY_REPLACE: a new document, or None with the reason; signed
    with the request's nonce as push id, so it answers that request only."""

    kind: Literal["replacement"] = "replacement"
    document: str | None
    reason: str = ""
    seq: int = Field(0, ge=0, description="server sequence number; agents refuse seq <= last")
    signature: str = Field(
        "",
        max_length=128,
        description="Ed25519 hex over schemas.security.signed_bytes; '' unsigned",
    )


class TrackerPose(_RobotMessage):
    """Tracker -> server on `tracker_key`: where the robot was at wall time `at` (Unix seconds,
    the clock the agents stamp their samples with: NTP-synchronised hosts)."""

    kind: Literal["pose"] = "pose"
    at: float = Field(gt=0, allow_inf_nan=False)
    x: float = Field(ge=-POSE_LIMIT, le=POSE_LIMIT, allow_inf_nan=False)
    y: float = Field(ge=-POSE_LIMIT, le=POSE_LIMIT, allow_inf_nan=False)
    theta: float = Field(ge=-math.pi, le=math.pi, allow_inf_nan=False)


RobotMessage = (
    ControllerPush | StopCommand | PushAck | TraceAck | StuckRequest | Replacement | TrackerPose
)
_KINDS: dict[str, type[_Model]] = {
    "push": ControllerPush,
    "stop": StopCommand,
    "ack": PushAck,
    "trace-ack": TraceAck,
    "stuck": StuckRequest,
    "replacement": Replacement,
    "pose": TrackerPose,
}


def encode_message(message: RobotMessage) -> bytes:
    """A control message as an array-less frame."""
    return encode_frame(message.model_dump(mode="json"))


def decode_message(payload: bytes) -> RobotMessage:
    """Any control message, by its `kind`; WireError when malformed or over MAX_ROBOT_MESSAGE."""
    if len(payload) > MAX_ROBOT_MESSAGE:
        raise WireError(f"robot message of {len(payload)} bytes exceeds {MAX_ROBOT_MESSAGE}")
    header, arrays = decode_frame(payload)
    if arrays:
        raise WireError(f"control messages carry no arrays, got {sorted(arrays)}")
    model = _KINDS.get(str(header.get("kind")))
    if model is None:
        raise WireError(f"unknown robot message kind {header.get('kind')!r}")
    try:
        message = model.model_validate(header)
    except ValidationError as exc:
        raise WireError(f"{model.__name__}: {exc}") from exc
    return message  # type: ignore[return-value]


# ---------------------------------------------------------------------------- REST bodies

ReplacementPolicy = Literal["off", "rank", "archive", "fit"]
"""What a stuck robot gets (docs/robots.md): `off` nothing (its scripted escape carries on and
its controller resumes), `rank` the next rank of the run its controller came from, `archive`
the elite of that run's archive (map-elites, cma-me, novelty) whose behaviour differs most from
the stuck controller's, `fit` the candidate of that run that roams most in the robot's
calibrated world."""
DEFAULT_REPLACEMENT: ReplacementPolicy = "rank"
PolicySource = Literal["robot", "colony"]
"""Where a robot's effective replacement policy comes from: its own setting or the colony's."""


class RobotOut(_Model):
    """One robot as GET /api/robots and GET /api/colony list it (the one robot view)."""

    id: str
    online: bool
    state: str
    controller_sha256: str | None
    steps: int = Field(description="the robot's step counter in its last report")
    stuck_events: int = Field(description="stuck requests the server received")
    last_seen: datetime | None = Field(
        description="when the server last heard from it (ISO 8601, UTC); null: never"
    )
    replacement: ReplacementPolicy = Field(description="the policy its stuck requests get")
    replacement_source: PolicySource = Field(
        description="robot: its own setting; colony: the server's COLONY_REPLACEMENT"
    )


class FieldWindow(_Model):
    """A robot's time and stuck events over a span of its retained traces."""

    robot_hours: float
    stuck_events: int
    stuck_per_hour: float | None = Field(description="null: no time in the span")


class RobotDetail(RobotOut):
    """GET /api/robots/{id}: the summary plus the controller's origin, whiskers, link and
    calibration."""

    controller_run: int | None
    controller_rank: int | None
    controller_generation: int | None
    whiskers: str = Field(description="last whisker bits, left to right")
    boot: int
    link: dict[str, object] = Field(description="zenoh link and the agent's last RobotStatus")
    calibration: RobotCalibration | None = Field(
        None, description="its stored fit (colony robot calibrate); null: not calibrated"
    )
    calibrated_at: datetime | None = None
    before_calibration: FieldWindow | None = Field(
        None, description="its retained traces and stuck events from before the fit was stored"
    )
    since_calibration: FieldWindow | None = Field(None, description="and from then on")


class PushBody(_Model):
    """POST /api/robots/{id}/controller: a stored controller, or a run's controller."""

    sha256: str | None = Field(
        None,
        pattern=r"^[0-9a-fA-F]{8,64}$",
        description="a stored controller's sha256, or an unambiguous prefix of 8+ hex digits",
    )
    run_id: int | None = Field(None, ge=0)
    rank: int | None = Field(
        None,
        ge=0,
        description="a training rank of the run's latest generation; omitted: the run's best "
        "(its validated champion once completed, else training rank 0)",
    )
    elite: int | None = Field(
        None,
        ge=0,
        le=10_000_000,
        description="an entry of the run's archive, in GET /api/runs/{id}/archive order "
        "(map-elites, cma-me, novelty)",
    )

    fit: bool = Field(
        False,
        description="the run's candidate (validated ranks and archive elites) that roams most "
        "in this robot's calibrated world",
    )

    @model_validator(mode="after")
    def _one_choice(self) -> PushBody:
        if (self.sha256 is None) == (self.run_id is None):
            raise ValueError("give exactly one of sha256 or run_id")
        if self.run_id is None and (self.rank is not None or self.elite is not None or self.fit):
            raise ValueError("rank, elite and fit choose within a run: give run_id")
        if (self.rank is not None) + (self.elite is not None) + self.fit > 1:
            raise ValueError("give at most one of rank, elite or fit")
        return self


class ReplacementBody(_Model):
    """PUT /api/robots/{id}/replacement: the robot's own policy, or null for the colony's."""

    policy: ReplacementPolicy | None = Field(
        description="off, rank, archive, fit, or null: follow the colony's setting"
    )


class StuckEventOut(_Model):
    """One stuck request in the field ledger, and what it was served."""

    id: int
    at: float = Field(description="Unix time the server received it")
    step: int = Field(description="the robot's step counter when it got stuck")
    reason: str = Field(description="the stuck detector's sign")
    controller_sha256: str | None = Field(description="the controller that got stuck")
    policy: ReplacementPolicy | None = Field(
        description="the policy in force for this robot then (null: recorded before policies)"
    )
    replacement_sha256: str | None = Field(description="what was sent; null: nothing")
    answer: str | None = Field(description="why: the rank sent, or why nothing was")
    steps_run: int | None = Field(
        description="steps of the robot's clock from this event to its next, when the robot "
        "was then running what this event left it with (the replacement, or with none its own "
        "controller); null while that runs, or when a push or an agent restart came between"
    )


class LedgerController(_Model):
    """A controller of the field ledger: how long the robot ran it after a stuck event left it
    with it, and how often it stuck."""

    sha256: str
    steps_run: int = Field(description="the `steps_run` of the events that left the robot with it")
    seconds_run: float = Field(description="steps_run x dt")
    stuck_events: int = Field(description="the events in which it was the controller that stuck")


class StuckEventsOut(_Model):
    robot: str
    events: list[StuckEventOut] = Field(description="newest last")
    controllers: list[LedgerController] = Field(
        default_factory=list, description="per controller of these events, longest run first"
    )


class PushOut(_Model):
    robot: str
    push_id: str
    sha256: str | None
    acknowledged: bool = Field(description="the robot answered within the timeout")
    accepted: bool = Field(description="the robot runs the pushed controller (or stopped)")
    reason: str = ""


class TraceSample(_Model):
    boot: int
    step: int
    whiskers: str
    motors: tuple[float, float]
    controller_sha256: str | None
    fresh: bool
    at: float | None = Field(description="Unix time the whiskers were read (null: not recorded)")
    pose: tuple[float, float, float] | None = Field(
        description="x, y (m), heading (rad) then (null: not recorded)"
    )
    pose_source: PoseSource | None = Field(
        description="sim: the emulator's true pose; tracker: an overhead tracker's (the newest "
        "at or before `at`); odometry: integrated from motor commands"
    )


class TracesOut(_Model):
    robot: str
    samples: list[TraceSample] = Field(description="newest last")


class MapMaze(_Model):
    """The maze the Colony page draws: `rows[0]` is the north edge, `#` a wall cell."""

    name: str
    width: float = Field(description="metres along x")
    height: float = Field(description="metres along y")
    cell_size: float = Field(description="metres per grid cell")
    rows: list[str] = Field(description="the grid, north row first: '#' wall, '.' free")


class MapStuck(_Model):
    """A stuck event where it happened (the pose of its step, when that sample is retained)."""

    id: int
    at: float = Field(description="Unix time the server received it")
    step: int
    reason: str
    x: float
    y: float


class MapRobot(_Model):
    """One robot on the map: where it is, where it went lately, where it got stuck."""

    id: str
    online: bool
    pose_source: PoseSource | None = Field(description="of its newest sample (null: no pose)")
    pose: tuple[float, float, float] | None = Field(description="newest x, y (m), heading (rad)")
    at: float | None = Field(description="Unix time of the newest pose")
    path: list[tuple[float, float]] = Field(description="recent x, y, oldest first")
    stuck: list[MapStuck] = Field(description="stuck events within the recent path")


class ColonyMapOut(_Model):
    """GET /api/colony/map."""

    maze: MapMaze
    robots: list[MapRobot]


class ReplayOut(_Model):
    """The sim-to-real check: same whiskers into the same controller, same motor commands."""

    robot: str
    identical: bool = Field(description="samples were checked and every one matched bit for bit")
    checked: int
    segments: int = Field(description="controller runs replayed from their fresh start")
    skipped: int = Field(description="samples not checkable: escape, stop, or start not retained")
    mismatches: int
    first_mismatch: dict[str, object] | None


class FieldStats(_Model):
    """Field performance of a controller over every robot that ran it."""

    sha256: str
    robot_hours: float
    stuck_events: int
    stuck_per_hour: float | None


Range = Annotated[float, Field(ge=0.0, le=0.25, allow_inf_nan=False)]
"""A whisker trigger distance, m (`evorobotics.calibrate.MAX_RANGE`)."""
Gain = Annotated[float, Field(gt=0.0, le=3.0, allow_inf_nan=False)]


class CalibrationUncertainty(_Model):
    whisker_range: tuple[Range, Range, Range, Range, Range]
    motor_gain: tuple[
        Annotated[float, Field(ge=0.0, le=3.0)], Annotated[float, Field(ge=0.0, le=3.0)]
    ]


class CalibrationResiduals(_Model):
    moving_steps: int = Field(ge=0, le=10**8)
    pose_rms_m: float = Field(ge=0.0, le=100.0, allow_inf_nan=False)
    whisker_disagreements: tuple[int, int, int, int, int] = Field(
        description="recorded bits per whisker the fitted range reads otherwise"
    )


class RobotCalibration(_Model):
    """A robot's physics fitted from its traces (`colony robot calibrate`, docs/robots.md):
    the body of `POST /api/robots/{id}/calibration`, `evorobotics.calibrate.Calibration`'s JSON."""

    whisker_range: tuple[Range, Range, Range, Range, Range] = Field(
        description="each whisker's trigger distance, left to right, m"
    )
    motor_gain: tuple[Gain, Gain] = Field(description="the wheels' gains [left, right]")
    uncertainty: CalibrationUncertainty
    samples: int = Field(ge=100, le=10**8)
    residuals: CalibrationResiduals
    bounded: tuple[Annotated[int, Field(ge=0, le=4)], ...] = Field(
        (),
        max_length=5,
        description="whiskers whose bit never changed: their range is only known to lie in "
        "range +- uncertainty",
    )

    def gap_robot(self, robot: str) -> GapRobot:
        """This fit as one robot of a colony gap (`reality_gap: "colony"`)."""
        return GapRobot(
            robot=robot,
            whisker_range=self.whisker_range,
            whisker_uncertainty=self.uncertainty.whisker_range,
            motor_gain=self.motor_gain,
            motor_gain_uncertainty=self.uncertainty.motor_gain,
        )

    def world(self, base: World) -> World:
        """`base` with this robot's whisker ranges and wheel gains."""
        return base.model_copy(
            update={"whisker_range": self.whisker_range, "motor_gain": self.motor_gain}
        )


class CalibrationOut(_Model):
    robot: str
    stored_at: datetime
    calibration: RobotCalibration
