"""The zenoh wire between the server and simulation workers: key expressions, messages, codecs.

Defined once here and documented in docs/protocol.md. Every payload is one *frame*:

    b"EVC1" | u32 little-endian header length | JSON header | array bytes, concatenated

The header is a JSON object whose `arrays` entry lists `{name, dtype, shape}` in body order;
numpy arrays travel as raw little-endian C-order bytes, never pickle. Each message is one
pydantic model whose array fields ride in the frame's body (`encode`/`decode`), validated
whole on decode, so a receiver can log and drop a bad message and keep serving.

Hierarchy:
    WireError (ValueError)   a payload cannot be decoded or fails validation
    └── InvalidJobError      a job whose key parsed but whose content is unusable: the worker
                             reports an error result for `key` instead of running it
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from typing import Any, ClassVar, Literal, TypeVar

import numpy as np
import orjson
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.network import NetworkSpec
from schemas.run import RunConfig
from schemas.world import World

PROTOCOL = 16
"""Wire protocol version, sent in every job request and robot trace batch; the server idles
workers and refuses robots' traces of other versions."""

KEY_JOB_NEXT = "evocolony/jobs/next/*"
"""Queryable (server): a worker's `get` on `next_key(name)` asks for its next job; the reply is
a job or idle."""
KEY_JOB_RESULT = "evocolony/jobs/result/*"
"""Queryable (server): a worker's `get` on `result_key(name)` carries a result; the reply is an
Ack or the next job. The worker's name in the key lets zenoh's access control bind it to the
worker's credentials (docs/security.md); the server refuses a message naming another worker."""
KEY_WORKERS = "evocolony/workers/*"
"""Liveliness key expression matching every worker's token."""
ERROR_MAX = 65536
"""Longest error message a result carries (`Result` cuts longer ones)."""
SPAN_BATCH_MAX = 64
"""Most generations one Result carries (a span sends several at once)."""

MAGIC = b"EVC1"
_HEADER = struct.Struct("<4sI")
MAX_HEADER = 1 << 20
"""A header longer than this (1 MiB) is malformed: configs are a few kilobytes."""
ALLOWED_DTYPES = frozenset({"<f8", "<f4", "<i8", "<i4", "|u1", "|b1"})
"""Plain numeric dtypes only: object arrays would need pickle."""
_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,128}$")
"""Worker names: one key-expression chunk, no wildcards or separators."""
_DIGEST = re.compile("^[0-9a-f]{8}$")
"""A `genome_digest`: CRC-32 in lowercase hex."""


class WireError(ValueError):
    """A payload cannot be decoded or fails validation."""


class InvalidJobError(WireError):
    """A job whose identity parsed but whose content cannot be evaluated."""

    def __init__(self, key: JobKey, reason: str, ack: Ack | None = None) -> None:
        super().__init__(f"job {key.label()}: {reason}")
        self.key = key
        self.reason = reason
        self.ack = ack
        """Set when the job came as the reply to a result: that result's acknowledgement."""


def worker_key(name: str) -> str:
    """The liveliness key of the worker called `name`."""
    check_worker_name(name)
    return f"evocolony/workers/{name}"


def next_key(name: str) -> str:
    """Where the worker called `name` asks for jobs."""
    return f"evocolony/jobs/next/{check_worker_name(name)}"


def result_key(name: str) -> str:
    """Where the worker called `name` delivers results."""
    return f"evocolony/jobs/result/{check_worker_name(name)}"


def check_worker_name(name: str) -> str:
    """`name` if it is a valid worker name, else ValueError (it becomes a key chunk)."""
    if not NAME_PATTERN.match(name):
        raise ValueError(f"worker name {name!r} must match {NAME_PATTERN.pattern}")
    return name


def genome_digest(genomes: np.ndarray) -> str:
    """CRC-32 (8 hex digits) of genomes as float64 little-endian C-order bytes.

    A transport check, never an identity: a span's worker asks its generations itself, and the
    server compares this with the genomes it asked, so a worker whose GA differs (another
    version) cannot slip fitness for other genomes into a run.
    """
    data = np.ascontiguousarray(genomes, dtype="<f8")
    return f"{zlib.crc32(data.data):08x}"


def encode_frame(header: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> bytes:
    """One frame: the JSON header (with an `arrays` index added) then each array's raw bytes.

    The header goes through orjson (a tenth of the json module's time, paid by every message):
    its integers must fit 64 bits, and it never holds NaN (orjson writes null)."""
    if "arrays" in header:
        raise ValueError("header key 'arrays' is reserved for the array index")
    index: list[dict[str, Any]] = []
    bodies: list[bytes] = []
    for name, array in (arrays or {}).items():
        le = array
        if array.dtype.str not in ALLOWED_DTYPES:  # big-endian, or not allowed at all
            le = np.asarray(array, dtype=array.dtype.newbyteorder("<"))
        if le.dtype.str not in ALLOWED_DTYPES:
            raise ValueError(f"array {name!r} has dtype {array.dtype}; allowed {ALLOWED_DTYPES}")
        index.append({"name": name, "dtype": le.dtype.str, "shape": list(le.shape)})
        bodies.append(le.tobytes())
    head = orjson.dumps({**header, "arrays": index})
    return b"".join([_HEADER.pack(MAGIC, len(head)), head, *bodies])


def decode_frame(payload: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Header and arrays of a frame; WireError on a bad magic, length, dtype or shape."""
    if len(payload) < _HEADER.size:
        raise WireError(
            f"frame of {len(payload)} bytes is shorter than its {_HEADER.size}-byte prefix"
        )
    magic, size = _HEADER.unpack_from(payload)
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if size > MAX_HEADER or _HEADER.size + size > len(payload):
        raise WireError(f"header length {size} exceeds the frame of {len(payload)} bytes")
    try:
        header = orjson.loads(payload[_HEADER.size : _HEADER.size + size])
    except orjson.JSONDecodeError as exc:
        raise WireError(f"header is not JSON: {exc}") from exc
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
        raise WireError("header must be a JSON object with an 'arrays' list")
    arrays: dict[str, np.ndarray] = {}
    offset = _HEADER.size + size
    for entry in header.pop("arrays"):
        name, dtype, shape = _array_entry(entry)
        count = math.prod(shape)
        nbytes = count * dtype.itemsize
        if offset + nbytes > len(payload):
            raise WireError(f"array {name!r} needs {nbytes} bytes; the frame is too short")
        flat = np.frombuffer(payload, dtype=dtype, count=count, offset=offset)
        arrays[name] = flat.reshape(shape).copy()
        offset += nbytes
    if offset != len(payload):
        raise WireError(f"{len(payload) - offset} trailing bytes after the last array")
    return header, arrays


def _array_entry(entry: object) -> tuple[str, np.dtype[Any], tuple[int, ...]]:
    if not isinstance(entry, dict):
        raise WireError("array index entries must be objects")
    name, dtype, shape = entry.get("name"), entry.get("dtype"), entry.get("shape")
    if not (isinstance(name, str) and isinstance(dtype, str) and isinstance(shape, list)) or (
        dtype not in _DTYPES  # a str by then: a list or dict is unhashable
    ):
        raise WireError(f"bad array index entry {entry!r}")
    if len(shape) > 8:
        raise WireError(f"array {name!r} has {len(shape)} dimensions; at most 8")
    if not all(type(n) is int and 0 <= n < 2**31 for n in shape):  # not bool, a subclass
        raise WireError(f"bad shape {shape!r} for array {name!r}")
    return name, _DTYPES[dtype], tuple(shape)


_M = TypeVar("_M", bound="_Message")


class _Message(BaseModel):
    """A wire message: its `ARRAYS` fields travel as the frame's arrays, the rest as JSON."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)
    ARRAYS: ClassVar[tuple[str, ...]] = ()


def encode(message: _Message) -> bytes:
    """One message as a frame; a Job's GA state goes as `state.*` arrays."""
    header = message.model_dump(mode="json", exclude=set(message.ARRAYS))
    arrays: dict[str, np.ndarray] = {}
    for name in message.ARRAYS:
        value = getattr(message, name)
        if isinstance(value, dict):
            arrays |= {f"{name}.{key}": array for key, array in value.items()}
        elif value is not None:
            arrays[name] = value
    return encode_frame(header, arrays)


def decode(payload: bytes, model: type[_M]) -> _M:
    """A validated `model` from a frame; WireError if the frame or the message is bad."""
    header, arrays = decode_frame(payload)
    return _validate(model, header, arrays)


def _validate(model: type[_M], header: dict[str, Any], arrays: dict[str, np.ndarray]) -> _M:
    fields: dict[str, Any] = dict(header)
    for name, array in arrays.items():
        group, dot, key = name.partition(".")
        if group not in model.ARRAYS or group in header:
            raise WireError(f"{model.__name__}: unexpected array {name!r}")
        held = fields.setdefault(group, {} if dot else array)
        if not (key and isinstance(held, dict)) if dot else held is not array:
            raise WireError(f"{model.__name__}: array {name!r} clashes with another")
        if isinstance(held, dict):
            held[key] = array
    try:
        return model.model_validate(fields)
    except ValidationError as exc:
        raise WireError(f"{model.__name__}: {_first_line(exc)}") from exc


def _first_line(exc: ValidationError) -> str:
    errors = exc.errors()
    where = ".".join(str(part) for part in errors[0]["loc"]) if errors else ""
    return f"{where}: {errors[0]['msg']}" if errors else str(exc)


Stage = Literal["train", "validate", "test", "explore", "robustness", "rank"]
"""What a job simulates: individuals of a generation (`train`); once a run's last generation
is told, slices of its champion's choice: candidates on the validation set (`validate`,
`evorobotics.evolution.validate`) and the pick's held-out test poses (`test`,
`evorobotics.evolution.held_out_trials`); trials of a controller's report (REPORT_STAGES); or
a run's candidates ranked in a robot's world (`rank`, `evorobotics.evolution.rank_in_world`):
validate's rows of another config."""
ReportStage = Literal["explore", "robustness"]
REPORT_STAGES: tuple[ReportStage, ...] = ("explore", "robustness")
"""A controller's reports, whoever asked (a study, the REST API): an exploration report's
poses (`explore`, `evorobotics.explore.exploration_trials`) or a robustness map's trials
(`robustness`, `evorobotics.robustness.map_trials`)."""
ASKED_STAGES: tuple[Stage, ...] = (*REPORT_STAGES, "rank")
"""Work the server asks for itself, of no run in flight: the reports, and the rankings its
replacement policies and pushes choose from (`rank`)."""
REPORT_ROBOT_STEPS = 20_000_000
"""Most robot-steps of one report (its trials x steps): a report job's trials are drawn whole
before its slice is cut, so this bounds what one job can ask of a worker."""
MAP_CELLS = 49
"""Cells of a robustness map (7 whisker ranges x 7 gain ratios, `evorobotics.robustness`)."""


def rank_candidates(config: RunConfig) -> int:
    """Most rows of a ranking (`rank`) whose config is `config`: its `validation.candidates`
    fittest training ranks and as many archive elites."""
    return 2 * config.validation.candidates


def report_trials(stage: Stage, poses: int) -> int:
    """Trials of a report of `poses` poses: one per pose, or per pose and map cell."""
    return MAP_CELLS * poses if stage == "robustness" else poses


class ReportSpec(BaseModel):
    """A report's size besides its job's config (the controller's network and world, the
    report's maze and seed): `colony evaluate`'s poses, steps and reality gap."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    poses: int = Field(ge=1, le=REPORT_ROBOT_STEPS)
    steps: int = Field(ge=1, le=100_000)
    reality_gap: bool = Field(False, description="draw each trial's robot from the world's gap")


def report_config(network: NetworkSpec, world: World, maze: str, seed: int) -> RunConfig:
    """A report job's config: the controller's network and world with the report's maze and
    seed (the rest is RunConfig's default and unused; a colony world's gap robots need its
    'colony' gap)."""
    gap = "colony" if world.gap_robots else "off"
    return RunConfig(network=network, world=world, maze=maze, seed=seed, reality_gap=gap)


class JobKey(BaseModel):
    """Identity of one evaluation job: results are idempotent under it."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    run_id: int = Field(ge=0, lt=2**63)
    generation: int = Field(ge=0, lt=2**63)
    index: int = Field(ge=0, lt=2**63)
    """Each fits a signed 64-bit integer (the database's, and every JSON header's)."""
    stage: Stage = "train"
    """A champion stage's jobs carry the run's last generation."""

    @property
    def report(self) -> bool:
        """A report's or a ranking's job (ASKED_STAGES): `run_id` is then its number
        (`server.runs.jobs.Report`, `Rank`) and `generation` 0."""
        return self.stage in ASKED_STAGES

    def label(self) -> str:
        if self.stage == "rank":
            return f"ranking {self.run_id} job {self.index}"
        if self.report:
            return f"report {self.run_id} {self.stage} job {self.index}"
        stage = "" if self.stage == "train" else f" {self.stage}"
        return f"run {self.run_id} gen {self.generation}{stage} job {self.index}"

    def at(self, generation: int) -> JobKey:
        """The same job of another generation (a span's generations are one job each)."""
        return JobKey(run_id=self.run_id, generation=generation, index=self.index, stage=self.stage)


EXPLORE_COLUMNS = 7
"""An exploration trial's row: stuck step (-1: never), confined, largest offset by step
min(40, H) and by H, coverage, curve length and net offset of the first min(40, H) steps
(`evorobotics.explore.TRIAL_COLUMNS`)."""


def score_columns(stage: Stage) -> int:
    """Columns of a stage's `Result.scores`: validate's and rank's (score, stuck, roaming),
    test's (roaming, stuck, offset) in the nominal world then in the test gap's, explore's
    EXPLORE_COLUMNS, robustness's (roaming, stuck)."""
    if stage == "train":
        raise ValueError("a training job's result carries fitness, not scores")
    columns = {"validate": 3, "rank": 3, "test": 6, "explore": EXPLORE_COLUMNS, "robustness": 2}
    return columns[stage]


def _worker_name(value: str) -> str:
    return check_worker_name(value)


class JobRequest(_Message):
    """Worker -> server on KEY_JOB_NEXT: who asks, and how fast it last ran."""

    kind: Literal["next"] = "next"
    protocol: int = PROTOCOL
    worker: str
    host: str = Field("", max_length=255)
    robot_steps_per_s: float | None = Field(None, ge=0.0, allow_inf_nan=False)
    """Measured on its last job; the server clamps it (schemas.security bounds)."""
    threads: int = Field(1, ge=1, le=256)
    """Threads it evaluates a job on: several workers on one host with more than one share
    its cores, so the server does not slice a generation between them."""

    _name = field_validator("worker")(_worker_name)


class Idle(_Message):
    """Server -> worker on KEY_JOB_NEXT: no job within the long-poll; ask again."""

    kind: Literal["idle"] = "idle"
    reason: str = Field("", max_length=ERROR_MAX)


class Ack(_Message):
    """Server -> worker on KEY_JOB_RESULT: stop retrying; `accepted` False means dropped."""

    kind: Literal["ack"] = "ack"
    key: JobKey
    accepted: bool
    reason: str = Field("", max_length=ERROR_MAX)


class Job(_Message):
    """One evaluation job: individuals start..stop of a generation, with their genomes; with
    `span` > 1 the whole generation, evolved `span` generations on by the worker itself from
    `state` (the GA state before this generation's `tell`). A champion stage's job (`key.stage`)
    is validation candidates start..stop, or test poses start..stop of the one genome; a
    report's job, trials start..stop of its `report` of the one genome (`config`:
    `report_config`); a ranking's, candidates start..stop on the validation set of its
    `config` (`evorobotics.evolution.ranking_config`)."""

    ARRAYS: ClassVar[tuple[str, ...]] = ("genomes", "state", "checks")
    kind: Literal["job"] = "job"
    key: JobKey
    start: int = Field(ge=0)
    stop: int = Field(ge=1)
    lease_s: float = Field(60.0, gt=0.0, allow_inf_nan=False)
    config: RunConfig
    span: int = Field(1, ge=1)
    ack: Ack | None = None
    """Set when the job answers a result that asked for the next job: that result's Ack."""
    report: ReportSpec | None = None
    """A report's job's (REPORT_STAGES), and only theirs."""
    genomes: np.ndarray
    """(stop - start, n_weights) float64."""
    state: dict[str, np.ndarray] | None = None
    checks: np.ndarray | None = None
    """(c, n_weights) float64: individuals of another job of the generation, evaluated after
    the slice's and sent with them (`Result.checks`): that job's spot-check, by another
    worker (a training job's of a generation cut into several)."""

    @model_validator(mode="after")
    def _check(self) -> Job:
        if (self.report is not None) != (self.key.stage in REPORT_STAGES):
            raise ValueError("a report's job, and only a report's, brings its report")
        if self.key.stage != "train":
            return self._check_stage()
        config, genomes = self.config, self.genomes
        if not 0 <= self.start < self.stop <= config.population:
            raise ValueError(
                f"slice {self.start}:{self.stop} outside population {config.population}"
            )
        shape = (self.stop - self.start, config.network_spec.weight_count)
        if genomes.shape != shape or genomes.dtype != np.float64:
            raise ValueError(f"genomes are {genomes.dtype}{genomes.shape}, expected float64{shape}")
        if not np.isfinite(genomes).all():
            raise ValueError("genomes contain NaN or infinity")
        checks = self.checks
        if checks is not None and (
            checks.dtype != np.float64
            or checks.ndim != 2
            or not 1 <= len(checks) <= config.population
            or checks.shape[1] != shape[1]
            or not np.isfinite(checks).all()
            or self.span > 1
        ):
            raise ValueError(f"checks must be finite float64 (1..population, {shape[1]}), no span")
        if (self.span > 1) != (self.state is not None):
            raise ValueError("a span, and only a span, brings the GA state")
        if self.span > 1 and (self.start, self.stop) != (0, config.population):
            raise ValueError(f"a span needs the whole population, got {self.start}:{self.stop}")
        if self.key.generation + self.span > config.generations:
            raise ValueError(
                f"span of {self.span} from generation {self.key.generation} "
                f"passes {config.generations}"
            )
        return self

    def evaluated(self) -> np.ndarray:
        """The genomes a training job's worker evaluates, in its result's order: its slice,
        then its `checks`."""
        return self.genomes if self.checks is None else np.concatenate([self.genomes, self.checks])

    def _check_stage(self) -> Job:
        config, genomes, v = self.config, self.genomes, self.config.validation
        validate = self.key.stage in ("validate", "rank")
        if self.span != 1 or self.state is not None or self.checks is not None:
            raise ValueError(f"a {self.key.stage} job is no span and brings no checks")
        if self.report is not None:
            most = self._check_report(self.report)
        elif self.key.stage == "rank":
            most = self._check_rank()
        elif self.key.generation != config.generations - 1:
            raise ValueError(f"a {self.key.stage} job is of the last generation")
        else:
            most = v.candidates if validate and v.poses else v.test_poses if not validate else 0
        if not 0 <= self.start < self.stop <= most:
            raise ValueError(f"{self.key.stage} slice {self.start}:{self.stop} outside {most}")
        shape = (self.stop - self.start if validate else 1, config.network_spec.weight_count)
        if genomes.shape != shape or genomes.dtype != np.float64:
            raise ValueError(f"genomes are {genomes.dtype}{genomes.shape}, expected float64{shape}")
        if not np.isfinite(genomes).all():
            raise ValueError("genomes contain NaN or infinity")
        return self

    def _check_rank(self) -> int:
        """The most candidates of a ranking's job, once it checks out."""
        if self.key.generation != 0:
            raise ValueError(f"a ranking's job is of generation 0, got {self.key.generation}")
        if self.config.gap or not self.config.validation.poses:
            raise ValueError("a ranking validates without a reality gap, on validation poses")
        return rank_candidates(self.config)

    def _check_report(self, report: ReportSpec) -> int:
        """The trials of a report's job, once it checks out."""
        stage = self.key.stage
        if self.key.generation != 0:
            raise ValueError(f"a report's job is of generation 0, got {self.key.generation}")
        trials = report_trials(stage, report.poses)
        if trials * report.steps > REPORT_ROBOT_STEPS:
            raise ValueError(
                f"a report of {trials} trials x {report.steps} steps exceeds "
                f"{REPORT_ROBOT_STEPS} robot-steps"
            )
        if stage == "robustness" and report.reality_gap:
            raise ValueError("a robustness map sets the gap per cell: no reality_gap")
        return trials


class Result(_Message):
    """Worker -> server on KEY_JOB_RESULT: fitness, components and behaviour descriptors of
    `k` consecutive generations of one job's slice (k = 1 but for a span), or an error."""

    ARRAYS: ClassVar[tuple[str, ...]] = ("fitness", "components", "descriptors", "scores")
    kind: Literal["result"] = "result"
    key: JobKey
    """The job of the first generation; generation i of the result is `key.at(g + i)`."""
    worker: str
    start: int | None = Field(None, ge=0)
    stop: int | None = Field(None, ge=1)
    """The evaluated slice; None only for an error about a job whose slice did not parse."""
    robot_steps_per_s: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    seconds: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    error: str | None = None
    want_next: bool = False
    """Answer with the worker's next job (carrying the Ack) if one is ready now."""
    checks: int = Field(0, ge=0, le=10_000)
    """Rows after the slice's: the job's `checks`, evaluated (k = 1)."""
    digests: tuple[str, ...] = Field((), max_length=SPAN_BATCH_MAX)
    """`genome_digest` of each generation's genomes: a span's, which the worker asked itself."""
    fitness: np.ndarray | None = None
    """(k, stop - start + checks) float64."""
    components: np.ndarray | None = None
    """(k, stop - start + checks, trials, 4) float64."""
    descriptors: np.ndarray | None = None
    """(k, stop - start + checks, 4) float64 (`evorobotics.evaluate.DESCRIPTORS`). Only dtypes and
    shapes are checked here: whether the values can be true is a claim the scheduler judges
    (`evorobotics.evaluate.implausible`), so a false one counts against its credential."""
    scores: np.ndarray | None = None
    """A stage's (a champion's, a report's or a ranking's): (stop - start, `score_columns`)
    float64, in place of the others."""

    _name = field_validator("worker")(_worker_name)

    @field_validator("error")
    @classmethod
    def _cut(cls, value: str | None) -> str | None:
        """Any exception's text, as valid UTF-8 of at most ERROR_MAX characters."""
        if value is None:
            return None
        value = value.encode("utf-8", "replace").decode("utf-8")
        return value if len(value) <= ERROR_MAX else value[: ERROR_MAX - 1] + "\u2026"

    @model_validator(mode="after")
    def _check(self) -> Result:
        if (self.start is None) != (self.stop is None) or (
            self.start is not None and self.stop is not None and self.start >= self.stop
        ):
            raise ValueError(f"bad slice {self.start}:{self.stop}")
        if not all(_DIGEST.match(d) for d in self.digests):
            raise ValueError("digests must be 8 lowercase hex digits (CRC-32)")
        if self.error is not None:
            if (
                self.fitness is not None
                or self.components is not None
                or self.descriptors is not None
                or self.scores is not None
                or self.digests
            ):
                raise ValueError("an error result carries no fitness")
            return self
        if self.key.stage != "train":
            if self.checks:
                raise ValueError(f"a {self.key.stage} result carries no checks")
            return self._check_scores()
        if self.scores is not None:
            raise ValueError("a training result carries no scores")
        fitness, components, descriptors = self.fitness, self.components, self.descriptors
        if (
            fitness is None
            or components is None
            or descriptors is None
            or self.start is None
            or self.stop is None
        ):
            raise ValueError("a result needs its slice, fitness, components and descriptors")
        k, n = len(fitness) if fitness.ndim else 0, self.stop - self.start + self.checks
        if self.checks and (k != 1 or self.digests):
            raise ValueError("a result with checks is of one generation, no span")
        if fitness.dtype != np.float64 or fitness.ndim != 2 or not 1 <= k <= SPAN_BATCH_MAX:
            raise ValueError(f"fitness must be float64 (k <= {SPAN_BATCH_MAX}, n)")
        if fitness.shape[1] != n:
            raise ValueError(f"fitness {fitness.shape} must be for the slice and checks: {n}")
        if components.dtype != np.float64 or components.ndim != 4 or components.shape[:2] != (k, n):
            raise ValueError(f"components {components.shape} do not match fitness {fitness.shape}")
        if descriptors.dtype != np.float64 or descriptors.shape != (k, n, 4):
            raise ValueError(f"descriptors {descriptors.shape} must be float64 ({k}, {n}, 4)")
        if self.digests and len(self.digests) != k:
            raise ValueError(f"{len(self.digests)} digests for {k} generations")
        return self

    def _check_scores(self) -> Result:
        scores, stage = self.scores, self.key.stage
        if self.fitness is not None or self.components is not None or self.descriptors is not None:
            raise ValueError(f"a {stage} result carries scores only")
        if scores is None or self.start is None or self.stop is None or self.digests:
            raise ValueError(f"a {stage} result needs its slice and scores")
        shape = (self.stop - self.start, score_columns(stage))
        if scores.dtype != np.float64 or scores.shape != shape:
            raise ValueError(f"scores {scores.dtype}{scores.shape} must be float64{shape}")
        if not np.isfinite(scores).all():
            raise ValueError("scores must be finite")
        if stage == "explore":
            return self._check_exploration(scores)
        if stage == "robustness":
            if ((scores != 0.0) & (scores != 1.0)).any() or (scores.sum(axis=1) > 1.0).any():
                raise ValueError("a map's trial roams or sticks or neither: 0 or 1, not both")
            return self
        fractions = scores[:, 1:] if stage in ("validate", "rank") else scores[:, :4]
        if not ((fractions >= 0.0) & (fractions <= 1.0)).all():
            raise ValueError("stuck and roaming must lie in [0, 1]")
        if stage == "test" and ((fractions != 0.0) & (fractions != 1.0)).any():
            raise ValueError("a test trial roams or not and sticks or not: 0 or 1")
        if stage == "test" and not ((scores[:, 4:] >= 0.0) & (scores[:, 4:] <= 1e6)).all():
            raise ValueError("a test trial's offset must lie in [0, 1e6] m")
        return self

    def _check_exploration(self, scores: np.ndarray) -> Result:
        """Bounds any exploration trial keeps, whatever its steps (the scheduler checks
        those that depend on them: `evorobotics.reports.implausible`)."""
        stuck, confined, near, far, coverage, curve, net = scores.T
        if not ((stuck == np.round(stuck)) & ((stuck == -1.0) | (stuck >= 1.0))).all():
            raise ValueError("an exploration trial's stuck step is -1 or a step >= 1")
        if ((confined != 0.0) & (confined != 1.0)).any():
            raise ValueError("an exploration trial is confined or not: 0 or 1")
        if not ((net >= 0.0) & (net <= near) & (near <= far) & (far <= 1e6)).all():
            raise ValueError(
                "an exploration trial's offsets need 0 <= net <= by 40 <= max <= 1e6 m"
            )
        if not ((curve >= 0.0) & (curve <= 1e6)).all():
            raise ValueError("an exploration trial's curve length must lie in [0, 1e6] m")
        if not ((coverage == np.round(coverage)) & (coverage >= 1.0)).all():
            raise ValueError("an exploration trial covers a whole number of cells, at least 1")
        return self

    @property
    def generations(self) -> int:
        return 1 if self.fitness is None else len(self.fitness)


def decode_job(payload: bytes, ack: Ack | None = None) -> Job:
    """A validated job; InvalidJobError (carrying the key) if only its content is bad."""
    header, arrays = decode_frame(payload)
    try:
        return _validate(Job, header, arrays)
    except WireError as exc:
        try:
            key = JobKey.model_validate(header.get("key"))
        except ValidationError:
            raise exc from None
        raise InvalidJobError(key, str(exc), ack) from exc


def decode_next_reply(payload: bytes) -> Job | Idle:
    """The server's answer on KEY_JOB_NEXT: a job (possibly InvalidJobError) or idle."""
    if decode_frame(payload)[0].get("kind") == "idle":
        return decode(payload, Idle)
    return decode_job(payload)


def decode_result_reply(payload: bytes) -> tuple[Ack, Job | None]:
    """The server's answer on KEY_JOB_RESULT: the Ack, and the next job if it sent one.

    A next job whose content is invalid raises InvalidJobError carrying the Ack (the result
    was settled either way).
    """
    header = decode_frame(payload)[0]
    if header.get("kind") != "job":
        return decode(payload, Ack), None
    try:
        ack = Ack.model_validate(header.get("ack"))
    except ValidationError as exc:
        raise WireError(f"Ack: {_first_line(exc)}") from exc
    return ack, decode_job(payload, ack)


class WorkerStatus(BaseModel):
    """One row of GET /api/workers."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    host: str
    state: Literal["idle", "busy", "gone"]
    jobs_done: int
    evaluations: int = Field(0, description="controllers whose fitness the server took from it")
    late: int = Field(0, description="evaluations it sent too late or twice (dropped)")
    robot_steps_per_s: float | None
    last_seen: float = Field(description="Unix time the server last heard from the worker")
