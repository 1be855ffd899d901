"""The zenoh wire between the server and simulation workers: key expressions, messages, codecs.

Defined once here and documented in docs/protocol.md. Control messages are JSON; numpy arrays
travel as raw little-endian C-order bytes with dtype and shape beside them, never pickle.

Every payload is one *frame*:

    b"EVC1" | u32 little-endian header length | JSON header | array bytes, concatenated

The header is a JSON object whose `arrays` entry lists `{name, dtype, shape}` in body order.
Decoders check every length, dtype and shape and raise `WireError` on anything malformed, so a
receiver can log and drop a bad message and keep serving.

Hierarchy:
    WireError (ValueError)   a payload cannot be decoded or fails validation
    └── InvalidJobError           a job whose key parsed but whose content is unusable: the worker
                             reports an error result for `key` instead of running it
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import numpy as np
import orjson
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
)

from schemas.run import RunConfig

PROTOCOL = 9
"""Wire protocol version, sent in every job request; the server idles other versions.

2: a result may ask for the next job (`want_next`); the server then answers with that job,
carrying the acknowledgement, instead of a bare Ack (one round trip per job instead of two).
3: requests and results name the jobs the worker still has in hand (`holding`), so a worker
may hold one prefetched job and deliver a result while it evaluates the next.
4: a job says whether others were still pending when it was leased (`more`); without them a
prefetch could only come back idle, so the worker does not send one.
5: a job of a whole generation may be a span (`span` > 1, with the GA state): the worker
evolves that many generations itself and sends their results as it goes, several consecutive
generations per message (`SpanResults`), each with the digest of the genomes it evaluated;
each accepted generation moves the lease to the next.
6: the digests are CRC-32 instead of sha256 (a third of the cost, every generation).
7: a span may go to a team (`team`, `member`, `team_id`): idle workers split each of its
generations, exchange their slices' fitness on `evocolony/teams/NAME` (`TeamMessage`) and each
tells and asks itself; only the team's leader (member 0) holds the lease and sends results.
8: a team whose members share their leader's machine (the `machine` of their requests) may be
`shared`: they split each generation in chunks through a file in shared memory instead
(`worker.shared`), no messages.
9: requests and results are numbered (`seq`) and name the worker's earlier ones whose replies
it has not read yet (`awaiting`): the jobs those replies carry keep their leases, so a worker
may send a result asking for the next job before it reads the reply to its previous request
(two requests in flight instead of one).
"""

KEY_JOB_NEXT = "evocolony/jobs/next"
"""Queryable (server): a worker's `get` asks for its next job; reply is a job or idle."""
KEY_JOB_RESULT = "evocolony/jobs/result"
"""Queryable (server): a worker's `get` carries a result; reply is an acknowledgement."""
KEY_WORKERS = "evocolony/workers/*"
"""Liveliness key expression matching every worker's token."""
TEAM_MAX = 64
"""Most workers in one team."""
ERROR_MAX = 65536
"""Longest error message a result carries (`Result` cuts longer ones)."""
HOLDING_MAX = 16
"""Most jobs a request or result names as held, and most earlier requests it names as
awaited."""

MAGIC = b"EVC1"
_HEADER = struct.Struct("<4sI")
MAX_HEADER = 1 << 20
"""A header longer than this (1 MiB) is malformed: configs are a few kilobytes."""
ALLOWED_DTYPES = frozenset({"<f8", "<f4", "<i8", "<i4", "|u1", "|b1"})
"""Plain numeric dtypes only: object arrays would need pickle."""
_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,128}$")
"""Worker names: one key-expression chunk, no wildcards or separators."""
_DIGEST = "^[0-9a-f]{8}$"
"""A `genome_digest`: CRC-32 in lowercase hex."""
_TEAM_ID = "^[0-9a-f]{16}$"
"""A team's identity: 16 lowercase hex digits the server draws per team."""


class WireError(ValueError):
    """A payload cannot be decoded or fails validation."""


class InvalidJobError(WireError):
    """A job whose identity parsed but whose content cannot be evaluated."""

    def __init__(self, key: JobKey, reason: str) -> None:
        super().__init__(f"job {key.label()}: {reason}")
        self.key = key
        self.reason = reason
        self.ack: Ack | None = None
        """Set when the job came as the reply to a result: that result's acknowledgement."""


def worker_key(name: str) -> str:
    """The liveliness key of the worker called `name`."""
    check_worker_name(name)
    return f"evocolony/workers/{name}"


def team_key(name: str) -> str:
    """The key on which the worker called `name` receives its teams' messages."""
    check_worker_name(name)
    return f"evocolony/teams/{name}"


def team_cuts(population: int, size: int) -> list[int]:
    """Bounds of the `size` contiguous, near-equal slices of a team: member i evaluates
    individuals cuts[i]..cuts[i + 1]."""
    if not 1 <= size <= population:
        raise ValueError(f"a team of {size} cannot split a population of {population}")
    return [population * i // size for i in range(size + 1)]


def check_worker_name(name: str) -> str:
    """`name` if it is a valid worker name, else ValueError (it becomes a key chunk)."""
    if not NAME_PATTERN.match(name):
        raise ValueError(f"worker name {name!r} must match {NAME_PATTERN.pattern}")
    return name


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


_M = TypeVar("_M", bound=BaseModel)


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class JobKey(_Model):
    """Identity of one evaluation job: results are idempotent under it."""

    run_id: int = Field(ge=0)
    generation: int = Field(ge=0)
    index: int = Field(ge=0)

    def label(self) -> str:
        return f"run {self.run_id} gen {self.generation} job {self.index}"


def check_numbers(seq: int, awaiting: tuple[int, ...]) -> tuple[int, ...]:
    """`awaiting` unless it fails to name earlier requests than `seq` (ValueError): numbers
    from 1, ascending, each once, and none for an unnumbered request (`seq` 0)."""
    if seq < 0 or any(not 0 < a < b for a, b in zip(awaiting, (*awaiting[1:], seq), strict=False)):
        raise ValueError(f"request {seq} cannot await {list(awaiting)}")
    return awaiting


class JobRequest(_Model):
    """Worker -> server on KEY_JOB_NEXT: who asks, and how fast it last ran."""

    kind: Literal["next"] = "next"
    protocol: int = PROTOCOL
    worker: str
    host: str = Field("", max_length=255)
    machine: str = Field("", max_length=255)
    """What shares memory with the worker (protocol 8; empty: no shared teams): workers of
    the same `machine` may split a span in shared memory."""
    robot_steps_per_s: float | None = Field(None, ge=0.0, allow_inf_nan=False)
    holding: tuple[JobKey, ...] = Field((), max_length=HOLDING_MAX)
    """Jobs the worker has in hand: non-empty makes this a prefetch (answered at once, never
    held); any other lease of the worker lost its reply and is released, but for those of
    `awaiting`."""
    seq: int = Field(0, ge=0)
    """This request's number among its worker's (protocol 9; 0: unnumbered)."""
    awaiting: tuple[int, ...] = Field((), max_length=HOLDING_MAX)
    """Numbers of the worker's earlier requests whose replies it has not read yet: a job one
    of them carries is in flight, its lease kept, and this request is a prefetch."""

    @field_validator("worker")
    @classmethod
    def _check_name(cls, value: str) -> str:
        return check_worker_name(value)

    @field_validator("awaiting")
    @classmethod
    def _check_awaiting(cls, value: tuple[int, ...], info: ValidationInfo) -> tuple[int, ...]:
        return check_numbers(info.data.get("seq", 0), value)


class Idle(_Model):
    """Server -> worker on KEY_JOB_NEXT: no job within the long-poll; ask again."""

    kind: Literal["idle"] = "idle"
    reason: str = ""


class Ack(_Model):
    """Server -> worker on KEY_JOB_RESULT: stop retrying; `accepted` False means dropped."""

    kind: Literal["ack"] = "ack"
    key: JobKey
    accepted: bool
    reason: str = ""


class JobHeader(_Model):
    """The JSON part of a job; the genomes travel as the frame's `genomes` array."""

    kind: Literal["job"] = "job"
    key: JobKey
    start: int = Field(ge=0)
    stop: int = Field(ge=1)
    lease_s: float = Field(gt=0.0, allow_inf_nan=False)
    more: bool = True
    """When leased, jobs were pending and every other live worker held one: a prefetch may
    get a job."""
    config: RunConfig
    ack: Ack | None = None
    """Set when the job answers a result that asked for the next job: that result's Ack."""
    span: int = Field(1, ge=1)
    """Generations the worker evolves from this one (protocol 5); above 1 the frame also
    carries the GA state the generation's `tell` starts from, as `state.*` arrays."""
    team: tuple[str, ...] = Field((), max_length=TEAM_MAX)
    """The workers splitting the span's generations, leader first (protocol 7)."""
    member: int = Field(0, ge=0)
    """This worker's place in `team`: it evaluates slice `member` of `team_cuts`."""
    team_id: str = Field("", pattern=f"^$|{_TEAM_ID}")
    shared: bool = False
    """The team splits generations in shared memory: its members share a machine (protocol 8)."""


@dataclass(frozen=True)
class Job:
    """One evaluation job: individuals start..stop of a generation, with their genomes."""

    key: JobKey
    start: int
    stop: int
    config: RunConfig
    genomes: np.ndarray
    lease_s: float = 60.0
    more: bool = True
    """A prefetch may get another job (protocol 4; see JobHeader.more)."""
    span: int = 1
    """Generations to evolve from this one (protocol 5; see JobHeader.span)."""
    state: dict[str, np.ndarray] | None = None
    """The GA state (`GAState.to_arrays`) before this generation's `tell`; only with a span."""
    team: tuple[str, ...] = ()
    """The workers splitting a span, leader first (protocol 7; see JobHeader.team)."""
    member: int = 0
    team_id: str = ""
    shared: bool = False
    """The team works in shared memory (protocol 8; see JobHeader.shared)."""

    def __post_init__(self) -> None:
        check_job(self.key, self.start, self.stop, self.config, self.genomes)
        if self.span > 1 or self.state is not None:
            check_span(self.key, self.start, self.stop, self.config, self.span, self.state)
        if self.team or self.member or self.team_id or self.shared:
            check_team(self.key, self.config, self.span, self.team, self.member, self.team_id)

    def leased(self, lease_s: float, more: bool) -> Job:
        """This job as sent under a lease: only `lease_s` and `more` differ, so it is not
        validated again (the server sends every job this way; its genomes were checked once)."""
        if not (lease_s > 0.0 and math.isfinite(lease_s)):
            raise ValueError(f"lease_s must be a finite number > 0, got {lease_s}")
        return _altered(self, lease_s=lease_s, more=more)

    @property
    def robot_steps(self) -> int:
        """Robot-steps this job simulates: individuals x trials x steps."""
        return (self.stop - self.start) * self.config.trials * self.config.steps


_T = TypeVar("_T")


def _altered(item: _T, **changes: Any) -> _T:
    """A copy of the frozen dataclass `item` with `changes`, not validated again (a sixth of
    `dataclasses.replace`'s time, two thirds of `copy.copy`'s): for fields that need no check."""
    altered = object.__new__(type(item))
    altered.__dict__.update(item.__dict__, **changes)
    return altered


def check_job(key: JobKey, start: int, stop: int, config: RunConfig, genomes: np.ndarray) -> None:
    """InvalidJobError unless the slice lies in the population and genomes fit it and are finite."""
    if not 0 <= start < stop <= config.population:
        raise InvalidJobError(key, f"slice {start}:{stop} outside population {config.population}")
    shape = (stop - start, config.network_spec.weight_count)
    if genomes.shape != shape:
        raise InvalidJobError(key, f"genomes have shape {genomes.shape}, expected {shape}")
    if genomes.dtype != np.float64:
        raise InvalidJobError(key, f"genomes have dtype {genomes.dtype}, expected float64")
    if not np.isfinite(genomes).all():
        raise InvalidJobError(key, "genomes contain NaN or infinity")


def check_span(
    key: JobKey,
    start: int,
    stop: int,
    config: RunConfig,
    span: int,
    state: dict[str, np.ndarray] | None,
) -> None:
    """InvalidJobError unless a span covers the whole population, stays within the run's
    generations and brings the GA state (validated by `GAState.from_arrays` where it is used)."""
    if span < 1:
        raise InvalidJobError(key, f"span {span} must be >= 1")
    if (start, stop) != (0, config.population):
        raise InvalidJobError(key, f"a span needs the whole population, got slice {start}:{stop}")
    if key.generation + span > config.generations:
        raise InvalidJobError(
            key, f"span of {span} from generation {key.generation} passes {config.generations}"
        )
    if not state:
        raise InvalidJobError(key, "a span needs the GA state")


def check_team(
    key: JobKey, config: RunConfig, span: int, team: tuple[str, ...], member: int, team_id: str
) -> None:
    """InvalidJobError unless a team splits a span among 2 or more distinct, valid workers,
    at most one per individual, and names this worker's place in it and the team."""
    if span < 2:
        raise InvalidJobError(key, "a team needs a span")
    if not 2 <= len(team) <= min(TEAM_MAX, config.population):
        raise InvalidJobError(key, f"a team of {len(team)} for a population of {config.population}")
    if len(set(team)) != len(team) or not all(NAME_PATTERN.match(name) for name in team):
        raise InvalidJobError(key, f"team members {team} must be distinct worker names")
    if not 0 <= member < len(team):
        raise InvalidJobError(key, f"member {member} of a team of {len(team)}")
    if not re.match(_TEAM_ID, team_id):
        raise InvalidJobError(key, f"team id {team_id!r} must be 16 lowercase hex digits")


def genome_digest(genomes: np.ndarray) -> str:
    """CRC-32 (8 hex digits) of a generation's genomes as float64 little-endian C-order bytes.

    A span's worker asks its generations itself; the server compares this digest with the
    genomes it asked, so a worker whose GA differs (another version) cannot slip fitness for
    other genomes into a run. It guards against a mismatch, not an adversary (workers are
    trusted with the fitness anyway), and CRC-32 sees every single-bit change and every
    reordering of rows at a third of sha256's cost, paid every generation on both sides.
    """
    data = np.ascontiguousarray(genomes, dtype="<f8")
    return f"{zlib.crc32(data.data):08x}"


def encode_job(job: Job, ack: Ack | None = None) -> bytes:
    """A job frame; `ack` acknowledges the result whose reply this job is (protocol 2)."""
    header = {
        "kind": "job",
        "key": _key_json(job.key),
        "start": job.start,
        "stop": job.stop,
        "lease_s": job.lease_s,
        "more": job.more,
        "config": _config_json(job.config),
    }
    if ack is not None:
        header["ack"] = {
            "kind": "ack",
            "key": _key_json(ack.key),
            "accepted": ack.accepted,
            "reason": ack.reason,
        }
    arrays = {"genomes": job.genomes}
    if job.span > 1 and job.state is not None:
        header["span"] = job.span
        arrays |= {f"state.{name}": value for name, value in job.state.items()}
    if job.team:
        header |= {"team": list(job.team), "member": job.member, "team_id": job.team_id}
        header["shared"] = job.shared
    return encode_frame(header, arrays)


_CONFIG_JSON: dict[int, tuple[RunConfig, dict[str, Any]]] = {}
_CONFIGS: dict[bytes, RunConfig] = {}
_CACHE_SIZE = 64
"""Configs repeat job after job: serialise and parse each one once (bounded caches)."""


def _config_json(config: RunConfig) -> dict[str, Any]:
    cached = _CONFIG_JSON.get(id(config))
    if cached is not None and cached[0] is config:
        return cached[1]
    if len(_CONFIG_JSON) >= _CACHE_SIZE:
        _CONFIG_JSON.clear()
    data: dict[str, Any] = config.model_dump(mode="json")
    _CONFIG_JSON[id(config)] = (config, data)
    return data


def _parse_config(data: object) -> RunConfig:
    """A RunConfig from its JSON object, parsed once per distinct config; ValueError if it is
    not one (pydantic's ValidationError is a ValueError)."""
    try:
        text = orjson.dumps(data, option=orjson.OPT_SORT_KEYS)
    except orjson.JSONEncodeError as exc:  # nested deeper than orjson goes
        raise ValueError(f"config: {exc}") from exc
    config = _CONFIGS.get(text)
    if config is None:
        config = RunConfig.model_validate(data)
        if len(_CONFIGS) >= _CACHE_SIZE:
            _CONFIGS.clear()
        _CONFIGS[text] = config
    return config


def decode_job(payload: bytes) -> Job:
    """A validated job; InvalidJobError (carrying the key) if only its content is bad."""
    return _job_from(*decode_frame(payload))


def _job_from(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> Job:
    if header.get("kind") != "job":
        raise WireError(f"expected a job, got kind {header.get('kind')!r}")
    try:  # the key once, with the rest: a bad one is found below, for the error
        parsed = JobHeader.model_validate({**header, "config": _parse_config(header.get("config"))})
    except ValueError as exc:
        try:
            key = JobKey.model_validate(header.get("key"))
        except ValidationError as key_exc:
            raise WireError(f"job key: {key_exc}") from key_exc
        raise InvalidJobError(key, str(exc)) from exc
    key = parsed.key
    genomes = arrays.pop("genomes", None)
    if genomes is None or (parsed.span == 1 and arrays):
        raise InvalidJobError(key, f"expected the array 'genomes' only, got {sorted(arrays)}")
    state = {name.removeprefix("state."): value for name, value in arrays.items()}
    if len(state) != len(arrays):
        raise InvalidJobError(key, f"unexpected arrays {sorted(arrays)} in a span")
    return Job(
        key=key,
        start=parsed.start,
        stop=parsed.stop,
        config=parsed.config,
        genomes=genomes,
        lease_s=parsed.lease_s,
        more=parsed.more,
        span=parsed.span,
        state=state if parsed.span > 1 else None,
        team=parsed.team,
        member=parsed.member,
        team_id=parsed.team_id,
        shared=parsed.shared,
    )


class ResultHeader(_Model):
    """The JSON part of a result; fitness and components travel as arrays."""

    kind: Literal["result"] = "result"
    key: JobKey
    worker: str
    robot_steps_per_s: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    seconds: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    error: str | None = Field(None, max_length=ERROR_MAX)
    want_next: bool = False
    """Answer with the worker's next job (carrying the Ack) if one is ready now."""
    holding: tuple[JobKey, ...] = Field((), max_length=HOLDING_MAX)
    """Other jobs the worker has in hand (a prefetched one): their leases are kept."""
    seq: int = Field(0, ge=0)
    awaiting: tuple[int, ...] = Field((), max_length=HOLDING_MAX)
    """As in `JobRequest` (protocol 9)."""
    start: int | None = Field(None, ge=0)
    stop: int | None = Field(None, ge=1)
    """The evaluated slice (protocol 4): a key names one slice only within a server's life
    (the cut follows the workers), so a result for another slice is late."""
    digest: str | None = Field(None, pattern=_DIGEST)
    """`genome_digest` of the genomes evaluated: set by a span's worker (protocol 5)."""

    @field_validator("worker")
    @classmethod
    def _check_name(cls, value: str) -> str:
        return check_worker_name(value)

    @field_validator("awaiting")
    @classmethod
    def _check_awaiting(cls, value: tuple[int, ...], info: ValidationInfo) -> tuple[int, ...]:
        return check_numbers(info.data.get("seq", 0), value)


@dataclass(frozen=True)
class Result:
    """A worker's answer to a job: fitness (n,) and components (n, trials, k), or an error."""

    key: JobKey
    worker: str
    fitness: np.ndarray | None = None
    components: np.ndarray | None = None
    robot_steps_per_s: float = 0.0
    seconds: float = 0.0
    error: str | None = None
    want_next: bool = False
    holding: tuple[JobKey, ...] = ()
    seq: int = 0
    awaiting: tuple[int, ...] = ()
    start: int | None = None
    stop: int | None = None
    """The job's slice; None only for an error about a job whose slice did not parse."""
    digest: str | None = None
    """`genome_digest` of the evaluated genomes (a span's generations)."""

    def __post_init__(self) -> None:
        check_worker_name(self.worker)
        if not (0.0 <= self.robot_steps_per_s < math.inf and 0.0 <= self.seconds < math.inf):
            raise WireError(
                f"result {self.key.label()}: speed {self.robot_steps_per_s} and seconds "
                f"{self.seconds} must be finite and >= 0"
            )
        if self.error is not None:  # any exception's text: valid UTF-8, at most ERROR_MAX
            error = self.error.encode("utf-8", "replace").decode("utf-8")
            if len(error) > ERROR_MAX:
                error = error[: ERROR_MAX - 1] + "\u2026"
            object.__setattr__(self, "error", error)
        if self.digest is not None and not re.match(_DIGEST, self.digest):
            raise WireError(f"result {self.key.label()}: digest {self.digest!r} is not CRC-32 hex")
        _check_asking(self.key, self.holding, self.seq, self.awaiting)
        if (self.start is None) != (self.stop is None) or (
            self.start is not None and self.stop is not None and not 0 <= self.start < self.stop
        ):
            raise WireError(f"result {self.key.label()}: bad slice {self.start}:{self.stop}")
        if self.error is None:
            if self.fitness is None or self.fitness.ndim != 1:
                raise WireError(f"result {self.key.label()} needs a 1-D fitness array")
            if self.fitness.dtype != np.float64 or not np.isfinite(self.fitness).all():
                raise WireError(f"result {self.key.label()}: fitness must be finite float64")
            if self.components is not None and (
                self.components.ndim < 1 or self.components.shape[0] != self.fitness.shape[0]
            ):
                raise WireError(f"result {self.key.label()}: components do not match fitness")
            if self.start is None or self.stop is None:
                raise WireError(f"result {self.key.label()} needs its slice (start, stop)")
            if self.fitness.shape[0] != self.stop - self.start:
                raise WireError(f"result {self.key.label()}: fitness does not match its slice")

    def asking(
        self,
        want_next: bool,
        holding: tuple[JobKey, ...],
        seq: int = 0,
        awaiting: tuple[int, ...] = (),
    ) -> Result:
        """This result as delivered: only what it asks and names differs, so it is not
        validated again (a worker sends every result this way; its arrays were checked once)."""
        _check_asking(self.key, holding, seq, awaiting)
        return _altered(self, want_next=want_next, holding=holding, seq=seq, awaiting=awaiting)


def _check_asking(
    key: JobKey, holding: tuple[JobKey, ...], seq: int, awaiting: tuple[int, ...]
) -> None:
    if len(holding) > HOLDING_MAX or len(awaiting) > HOLDING_MAX:
        raise WireError(
            f"result {key.label()} holds {len(holding)} jobs and awaits {len(awaiting)} "
            f"requests; at most {HOLDING_MAX} each"
        )
    try:
        check_numbers(seq, awaiting)
    except ValueError as exc:
        raise WireError(f"result {key.label()}: {exc}") from exc


def encode_result(result: Result) -> bytes:
    """A result frame. Its header is written directly, not through `ResultHeader`: `Result`
    checked its content when it was built, and the server validates every header it reads."""
    header = {
        "kind": "result",
        "key": _key_json(result.key),
        "worker": result.worker,
        "robot_steps_per_s": float(result.robot_steps_per_s),
        "seconds": float(result.seconds),
        "error": result.error,
        "want_next": bool(result.want_next),
        "holding": [_key_json(key) for key in result.holding],
        "seq": int(result.seq),
        "awaiting": [int(number) for number in result.awaiting],
        "start": None if result.start is None else int(result.start),
        "stop": None if result.stop is None else int(result.stop),
        "digest": result.digest,
    }
    arrays: dict[str, np.ndarray] = {}
    if result.fitness is not None:
        arrays["fitness"] = result.fitness
    if result.components is not None:
        arrays["components"] = result.components
    return encode_frame(header, arrays)


def _key_json(key: JobKey) -> dict[str, int]:
    """`key.model_dump(mode="json")` at a fifth of the cost (every message names keys)."""
    return {"run_id": key.run_id, "generation": key.generation, "index": key.index}


def decode_result(payload: bytes) -> Result:
    return _result_from(*decode_frame(payload))


def _result_from(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> Result:
    try:
        parsed = ResultHeader.model_validate(header)
    except ValidationError as exc:
        raise WireError(f"result header: {exc}") from exc
    if not set(arrays) <= {"fitness", "components"}:
        raise WireError(f"unexpected arrays {sorted(arrays)} in a result")
    return Result(
        key=parsed.key,
        worker=parsed.worker,
        fitness=arrays.get("fitness"),
        components=arrays.get("components"),
        robot_steps_per_s=parsed.robot_steps_per_s,
        seconds=parsed.seconds,
        error=parsed.error,
        want_next=parsed.want_next,
        holding=parsed.holding,
        seq=parsed.seq,
        awaiting=parsed.awaiting,
        start=parsed.start,
        stop=parsed.stop,
        digest=parsed.digest,
    )


SPAN_BATCH_MAX = 64
"""Most generations one SpanResults message carries."""


class SpanResultsHeader(_Model):
    """The JSON part of consecutive generations' results of one span (protocol 5)."""

    kind: Literal["span-results"] = "span-results"
    key: JobKey
    """The first generation's job; the others follow it generation by generation."""
    worker: str
    robot_steps_per_s: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    seconds: float = Field(0.0, ge=0.0, allow_inf_nan=False)
    digests: tuple[str, ...] = Field(min_length=1, max_length=SPAN_BATCH_MAX)
    """`genome_digest` of each generation's genomes, in order."""

    @field_validator("worker")
    @classmethod
    def _check_name(cls, value: str) -> str:
        return check_worker_name(value)

    @field_validator("digests")
    @classmethod
    def _check_digests(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        if not all(re.match(_DIGEST, d) for d in value):
            raise ValueError("digests must be 64 lowercase hex characters")
        return value


def encode_span_results(results: list[Result]) -> bytes:
    """Consecutive generations' whole-population results of a span, in one frame: fitness
    (k, n) and components (k, n, trials, 4) stacked, one digest each."""
    first = results[0]
    if not 1 <= len(results) <= SPAN_BATCH_MAX:
        raise ValueError(f"{len(results)} results; a message carries 1 to {SPAN_BATCH_MAX}")
    for i, result in enumerate(results):
        expected = first.key.model_copy(update={"generation": first.key.generation + i})
        if result.key != expected or result.fitness is None or result.components is None:
            raise ValueError(f"result {i} is not generation {expected.generation}'s, evaluated")
        if result.digest is None or result.worker != first.worker:
            raise ValueError(f"result {i} lacks its digest or comes from another worker")
    header = SpanResultsHeader(
        key=first.key,
        worker=first.worker,
        robot_steps_per_s=results[-1].robot_steps_per_s,
        seconds=sum(r.seconds for r in results),
        digests=tuple(r.digest or "" for r in results),
    )
    arrays = {
        "fitness": np.stack([r.fitness for r in results if r.fitness is not None]),
        "components": np.stack([r.components for r in results if r.components is not None]),
    }
    return encode_frame(header.model_dump(mode="json"), arrays)


def decode_results(payload: bytes) -> list[Result]:
    """A result, or a span's consecutive generations as one Result each (WireError if bad)."""
    header, arrays = decode_frame(payload)
    if header.get("kind") != "span-results":
        return [_result_from(header, arrays)]
    try:
        parsed = SpanResultsHeader.model_validate(header)
    except ValidationError as exc:
        raise WireError(f"span results header: {exc}") from exc
    fitness, components = arrays.get("fitness"), arrays.get("components")
    k = len(parsed.digests)
    if set(arrays) != {"fitness", "components"} or fitness is None or components is None:
        raise WireError(f"span results need fitness and components, got {sorted(arrays)}")
    if fitness.ndim != 2 or fitness.shape[0] != k or components.shape[:2] != fitness.shape:
        raise WireError(
            f"span results of {k} generations with fitness {fitness.shape} and "
            f"components {components.shape}"
        )
    n = fitness.shape[1]
    if n < 1:
        raise WireError("span results of an empty population")
    return [
        Result(
            key=parsed.key.model_copy(update={"generation": parsed.key.generation + i}),
            worker=parsed.worker,
            fitness=fitness[i],
            components=components[i],
            robot_steps_per_s=parsed.robot_steps_per_s,
            seconds=parsed.seconds / k,
            start=0,
            stop=n,
            digest=digest,
        )
        for i, digest in enumerate(parsed.digests)
    ]


class TeamHeader(_Model):
    """The JSON part of a team message; fitness and components travel as arrays."""

    kind: Literal["team"] = "team"
    team_id: str = Field(pattern=_TEAM_ID)
    generation: int = Field(ge=0)
    member: int = Field(ge=0, lt=TEAM_MAX)
    """The sender's place in the team."""
    ranges: tuple[tuple[int, int], ...] = Field((), max_length=TEAM_MAX)
    """The [start, stop) slices whose fitness follows, concatenated in this order."""
    digest: str | None = Field(None, pattern=_DIGEST)
    """`genome_digest` of the whole generation the sender asked (with fitness)."""
    over: bool = False
    """The sender leaves the team (the leader: the span ends for everyone)."""


@dataclass(frozen=True)
class TeamMessage:
    """Worker -> worker on `team_key`: fitness of slices of one generation of a team span
    (protocol 7), so every member tells and asks the same generation; or leaving (`over`).

    Members send fitness and components to the leader, fitness alone to the other members;
    the leader also sends the slices it evaluated for a member that fell silent.
    """

    team_id: str
    generation: int
    member: int
    ranges: tuple[tuple[int, int], ...] = ()
    fitness: np.ndarray | None = None
    components: np.ndarray | None = None
    digest: str | None = None
    """`genome_digest` of the generation the sender asked: members whose GA differs (another
    version) would evaluate other genomes, so their fitness must not count."""
    over: bool = False

    def __post_init__(self) -> None:
        where = f"team message of generation {self.generation} from member {self.member}"
        previous = 0
        for start, stop in self.ranges:
            if not previous <= start < stop:
                raise WireError(f"{where}: ranges {self.ranges} must be ascending and disjoint")
            previous = stop
        count = sum(stop - start for start, stop in self.ranges)
        if self.over and (self.ranges or self.fitness is not None):
            raise WireError(f"{where}: leaving carries no fitness")
        if self.fitness is None:
            if count or self.components is not None or self.digest is not None:
                raise WireError(f"{where}: ranges or a digest without fitness")
            return
        if self.digest is None or not re.match(_DIGEST, self.digest):
            raise WireError(f"{where}: fitness without the digest of its genomes")
        if self.fitness.shape != (count,) or self.fitness.dtype != np.float64:
            raise WireError(f"{where}: fitness {self.fitness.shape} for {count} individuals")
        if not np.isfinite(self.fitness).all():
            raise WireError(f"{where}: fitness must be finite")
        if self.components is not None and (
            self.components.ndim != 3 or self.components.shape[0] != count
        ):
            raise WireError(f"{where}: components {self.components.shape} for {count}")


def encode_team_message(message: TeamMessage) -> bytes:
    """A team message as a frame (validated when the message was built)."""
    header = TeamHeader(
        team_id=message.team_id,
        generation=message.generation,
        member=message.member,
        ranges=message.ranges,
        digest=message.digest,
        over=message.over,
    )
    arrays: dict[str, np.ndarray] = {}
    if message.fitness is not None:
        arrays["fitness"] = message.fitness
    if message.components is not None:
        arrays["components"] = message.components
    return encode_frame(header.model_dump(mode="json"), arrays)


def decode_team_message(payload: bytes) -> TeamMessage:
    """A validated team message; WireError if malformed."""
    header, arrays = decode_frame(payload)
    parsed = _validate(header, TeamHeader)
    if not set(arrays) <= {"fitness", "components"}:
        raise WireError(f"unexpected arrays {sorted(arrays)} in a team message")
    return TeamMessage(
        team_id=parsed.team_id,
        generation=parsed.generation,
        member=parsed.member,
        ranges=parsed.ranges,
        fitness=arrays.get("fitness"),
        components=arrays.get("components"),
        digest=parsed.digest,
        over=parsed.over,
    )


def encode_message(message: JobRequest | Idle | Ack) -> bytes:
    """A control message as an array-less frame."""
    return encode_frame(message.model_dump(mode="json"))


def decode_request(payload: bytes) -> JobRequest:
    return _decode_model(payload, JobRequest)


def decode_ack(payload: bytes) -> Ack:
    return _decode_model(payload, Ack)


def decode_next_reply(payload: bytes) -> Job | Idle:
    """The server's answer on KEY_JOB_NEXT: a job (possibly InvalidJobError) or idle."""
    header, arrays = decode_frame(payload)
    if header.get("kind") == "idle":
        if arrays:
            raise WireError(f"Idle carries no arrays, got {sorted(arrays)}")
        return _validate(header, Idle)
    return _job_from(header, arrays)


def decode_result_reply(payload: bytes) -> tuple[Ack, Job | None]:
    """The server's answer on KEY_JOB_RESULT: the Ack, and the next job if it sent one.

    A next job whose content is invalid raises InvalidJobError after the Ack parsed; the
    caller gets the Ack from `exc.ack` (the result was settled either way).
    """
    header, arrays = decode_frame(payload)
    if header.get("kind") != "job":
        if arrays:
            raise WireError(f"Ack carries no arrays, got {sorted(arrays)}")
        return _validate(header, Ack), None
    ack = _validate(header.pop("ack", None), Ack)
    try:
        return ack, _job_from(header, arrays)
    except InvalidJobError as exc:
        exc.ack = ack
        raise


def _validate(data: object, model: type[_M]) -> _M:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise WireError(f"{model.__name__}: {exc}") from exc


def _decode_model(payload: bytes, model: type[_M]) -> _M:
    header, arrays = decode_frame(payload)
    if arrays:
        raise WireError(f"{model.__name__} carries no arrays, got {sorted(arrays)}")
    try:
        return model.model_validate(header)
    except ValidationError as exc:
        raise WireError(f"{model.__name__}: {exc}") from exc


class WorkerStatus(_Model):
    """One row of GET /api/workers."""

    name: str
    host: str
    state: Literal["idle", "busy", "gone"]
    jobs_done: int
    robot_steps_per_s: float | None
    last_seen: float = Field(description="Unix time the server last heard from the worker")
