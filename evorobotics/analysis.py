"""Temporal responses of an evolved controller (beyond the paper; see docs/analysis.md).

The paper (section 4) saw controllers produce "sequences of moves of up to five times in
duration before stabilizing" after a wall contact, and notes that a reactive controller can give
only 2^5 = 32 responses where one with memory of five steps could in principle give 2^25; it left
the responses "not fully characterized". `analyze` measures them for one controller:

- baseline: from a fresh state, zero whiskers for `warmup` steps; the tail of its motor commands
  is a fixed point, a limit cycle of period p, or unsteady;
- contacts: from the baseline state, one whisker (each in turn, then all together) touches for
  d = 1..3 steps, then zeros; the settling time is the number of steps after the last contact
  step until the wheel travel per step stays within a physical tolerance (mm per step) of the
  zero-input continuation (any phase of a limit cycle) for good; otherwise whether it settles
  on a new fixed point;
- distinct responses: every whisker history of length k = 1..history from the baseline state,
  in one batch, counting the distinct cells (of a stated size in mm per step) the last step's
  wheel travel falls in; and the effective memory, the fewest last steps that determine it;
- `wall_encounter`: where a recorded trial touches a wall (for the Fig 7 close-up).

Tolerances are wheel travel, not motor-command units: a command c moves a wheel
c * max_speed * dt metres per step (30 mm at c = 1 in the default world), so differences the
robot cannot act on do not count as unsettled or distinct.

Pure numpy over `network.step` (the robot's and simulator's compiled path): no I/O, no randomness.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from evorobotics.document import ControllerDocument
from evorobotics.network import motor_commands, reset, step
from evorobotics.sim import DEFAULT_WORLD
from evorobotics.thresholds import RESOLUTION_MM, TOLERANCE_MM
from schemas.network import NetworkSpec
from schemas.world import World

DURATIONS = (1, 2, 3)
"""Contact lengths d (steps with the whisker held) of every contact experiment."""

WARMUP = 200
"""Zero-whisker steps from a fresh state before the baseline is classified."""

PRE = 3
"""Baseline steps kept before the contact onset in every stored trace (for plots)."""

MAX_SEQUENCES = 2**20
"""Upper bound on whisker histories evaluated (32^4), so no call can exhaust memory."""

CHUNK_BYTES = 32 * 2**20
"""`network.step` copies the weights per row: the history batch is cut to this many bytes."""

BaselineKind = Literal["fixed", "cycle", "unsteady"]


@dataclass(frozen=True)
class Baseline:
    """The free-running (zero-whisker) behaviour the contacts are measured against."""

    kind: BaselineKind
    period: int | None
    """1 for a fixed point, p >= 2 for a limit cycle, None when unsteady."""
    motors: tuple[tuple[float, ...], ...]
    """One period of motor commands (the last warm-up step when unsteady)."""


@dataclass(frozen=True)
class ContactResponse:
    """One contact experiment: which inputs touched, for how long, and the motor trace."""

    label: str
    inputs: tuple[int, ...]
    duration: int
    settle_steps: int | None
    """Steps after the last contact step until back on the baseline for good; None if never."""
    new_steady_steps: int | None
    """When not back on the baseline: steps until a new fixed point for good; else None."""
    peak_deviation_mm_per_step: float
    """Largest |wheel travel - baseline| over the trace (max over both wheels)."""
    motors: tuple[tuple[float, ...], ...]
    """Motor commands for steps -PRE .. duration - 1 + max_steps relative to the onset."""


@dataclass(frozen=True)
class Analysis:
    """Everything `analyze` measured; `to_dict()` is JSON-ready (the dashboard shows it)."""

    sha256: str
    spec: dict[str, Any]
    history: int
    full_speed_mm_per_step: float
    """Wheel travel per step at command 1 (max_speed * dt): converts commands to mm per step."""
    tolerance_mm_per_step: float
    """Settling and baseline tolerance (max over both wheels)."""
    resolution_mm_per_step: float
    """Cell size of the distinct-response count."""
    max_steps: int
    warmup: int
    baseline: Baseline
    reference: tuple[tuple[float, ...], ...]
    """The zero-input continuation over the longest trace's steps (the plot's dashed line)."""
    trace_start: int
    """Step of the first trace entry relative to the contact onset (-PRE)."""
    contacts: tuple[ContactResponse, ...]
    max_settle_steps: int | None
    """Largest settle_steps over single-step single-input contacts; None if one never settles."""
    distinct: tuple[int, ...]
    """Distinct responses (cells of resolution_mm_per_step) to all histories of k = 1..history."""
    reactive_bound: int
    """2^inputs: the most responses a controller without memory can give for any k."""
    memory: int
    """Fewest last steps of whisker history that determine the response cell (<= history)."""
    memory_saturated: bool
    """memory == history: the controller may remember further back than was tested."""

    def to_dict(self) -> dict[str, Any]:
        """Plain dicts, lists, ints, floats, strings and None (json.dumps-ready)."""
        out: dict[str, Any] = _listed(asdict(self))
        return out


def _listed(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _listed(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_listed(v) for v in obj]
    return obj


def _rows(a: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(x) for x in row) for row in a)


def mm_per_step(world: World = DEFAULT_WORLD) -> float:
    """Wheel travel in mm per control step at command 1 (30 in the default world)."""
    return 1e3 * world.max_speed * world.dt


def _run(spec: NetworkSpec, w: np.ndarray, state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """Motor commands (steps, B, outputs) for inputs (steps, B, n) from state (B, size)."""
    steps, batch = inputs.shape[:2]
    motors = np.empty((steps, batch, spec.outputs))
    chunk = max(1, CHUNK_BYTES // (8 * w.shape[0]))
    for lo in range(0, batch, chunk):
        hi = min(batch, lo + chunk)
        weights = np.broadcast_to(w, (hi - lo, w.shape[0]))
        st = state[lo:hi]
        for k in range(steps):
            out, st = step(spec, weights, inputs[k, lo:hi], st)
            motors[k, lo:hi] = motor_commands(spec, out)
    return motors


def _after_state(
    spec: NetworkSpec, w: np.ndarray, state: np.ndarray, steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Motor commands (steps, outputs) and final state (1, size) of `steps` zero inputs."""
    motors = np.empty((steps, spec.outputs))
    zero = np.zeros((1, spec.inputs))
    weights = w[None, :]
    for k in range(steps):
        out, state = step(spec, weights, zero, state)
        motors[k] = motor_commands(spec, out)[0]
    return motors, state


def classify_baseline(motors: np.ndarray, tol: float) -> Baseline:
    """Fixed point, limit cycle or unsteady, from the last half of a zero-input trace.

    Period p (smallest, 1 <= p <= len/4) when every command of the last half is within `tol`
    of the one p steps earlier; p = 1 is a fixed point.
    """
    n = motors.shape[0]
    if n < 4:
        raise ValueError(f"need at least 4 warm-up steps to classify a baseline, got {n}")
    tail = n // 2
    for p in range(1, tail // 2 + 1):
        gap = np.abs(motors[n - tail :] - motors[n - tail - p : n - p])
        if float(gap.max()) <= tol:
            kind: BaselineKind = "fixed" if p == 1 else "cycle"
            return Baseline(kind, p, _rows(motors[n - p :]))
    return Baseline("unsteady", None, _rows(motors[n - 1 :]))


def _held_from(ok: np.ndarray, limit: int) -> int | None:
    """Smallest j <= limit with ok[j:] all true, or None."""
    bad = np.flatnonzero(~ok)
    j = 0 if bad.size == 0 else int(bad[-1]) + 1
    return j if j <= limit else None


def _contacts(
    spec: NetworkSpec,
    w: np.ndarray,
    state: np.ndarray,
    baseline: Baseline,
    tol: float,
    horizon: int,
    mm: float,
) -> tuple[tuple[ContactResponse, ...], np.ndarray]:
    """Every contact experiment in one batch, and the zero-input reference trace.

    `tol` is in command units; `mm` converts a command to mm per step for the peak deviation.
    """
    n = spec.inputs
    patterns: list[tuple[str, tuple[int, ...]]] = [(f"whisker {i}", (i,)) for i in range(n)]
    if n > 1:
        patterns.append(("all", tuple(range(n))))
    cases = [(label, idx, d) for d in DURATIONS for label, idx in patterns]
    phases = baseline.period if baseline.kind == "cycle" and baseline.period else 1
    # enough steps for the longest contact, a horizon of 2 * max_steps after it, and phases
    total = PRE + max(DURATIONS) + 2 * horizon + phases
    inputs = np.zeros((total, len(cases) + 1, n))
    for row, (_, idx, d) in enumerate(cases, start=1):
        inputs[PRE : PRE + d, row, list(idx)] = 1.0
    states = np.repeat(state, len(cases) + 1, axis=0)
    motors = _run(spec, w, states, inputs)
    control = motors[:, 0]
    out = []
    for row, (label, idx, d) in enumerate(cases, start=1):
        end = PRE + d - 1  # last contact step
        span = PRE + max(DURATIONS) + 2 * horizon - end  # j = 0 .. span - 1
        trace = motors[end : end + span, row]
        settle: int | None = None
        for q in range(phases):
            ref = control[end + q : end + q + span]
            held = _held_from(np.abs(trace - ref).max(axis=1) <= tol, horizon)
            if held is not None and (settle is None or held < settle):
                settle = held
        new_steady = None
        if settle is None:
            new_steady = _held_from(np.abs(trace - trace[-1]).max(axis=1) <= tol, horizon)
        shown = motors[: end + horizon + 1, row]
        out.append(
            ContactResponse(
                label=label,
                inputs=idx,
                duration=d,
                settle_steps=settle,
                new_steady_steps=new_steady,
                peak_deviation_mm_per_step=mm
                * float(np.abs(shown - control[: shown.shape[0]]).max()),
                motors=_rows(shown),
            )
        )
    reference = control[: PRE + max(DURATIONS) + horizon]
    return tuple(out), reference


def _histories(n: int, k: int) -> np.ndarray:
    """All 2^(n k) input sequences: (k, B, n); row b's step j carries digit j of b (base 2^n,
    most significant first), input i of a step being bit i of its digit."""
    per_step = 2**n
    b = np.arange(per_step**k, dtype=np.int64)
    digits = np.stack([(b // per_step ** (k - 1 - j)) % per_step for j in range(k)])
    bits = (digits[:, :, None] >> np.arange(n, dtype=np.int64)) & 1
    return bits.astype(np.float64)


def _keys(motors: np.ndarray, cell: float) -> np.ndarray:
    """Cell index per wheel: [k cell, (k + 1) cell) is cell k, so a cell of an integer multiple
    of `cell` is a union of these and the distinct count can only fall as cells grow."""
    return np.floor(motors / cell).astype(np.int64)


def _memory(keys: np.ndarray, n: int, history: int) -> int:
    """Fewest last steps whose inputs determine the response (keys ordered as `_histories`)."""
    b = np.arange(keys.shape[0], dtype=np.int64)
    for k in range(history + 1):
        cls = b % (2**n) ** k
        groups = np.unique(cls).size
        if np.unique(np.column_stack([cls, keys]), axis=0).shape[0] == groups:
            return k
    return history


def distinct_responses(
    spec: NetworkSpec, weights: np.ndarray, state: np.ndarray, history: int, cell: float
) -> tuple[tuple[int, ...], int]:
    """Distinct response cells for k = 1..history from `state` (1, size), and memory.

    `cell` is the cell size in command units (> 0): the last step's commands of every history
    are binned per wheel and the occupied cells counted.
    """
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be finite and > 0, got {cell}")
    counts = []
    keys = np.empty((0, spec.outputs), dtype=np.int64)
    for k in range(1, history + 1):
        seqs = _histories(spec.inputs, k)
        states = np.repeat(state, seqs.shape[1], axis=0)
        keys = _keys(_run(spec, weights, states, seqs)[-1], cell)
        counts.append(int(np.unique(keys, axis=0).shape[0]))
    return tuple(counts), _memory(keys, spec.inputs, history)


def analyze(
    doc: ControllerDocument,
    *,
    history: int = 3,
    tolerance_mm: float = TOLERANCE_MM,
    resolution_mm: float = RESOLUTION_MM,
    max_steps: int = 50,
    warmup: int = WARMUP,
    world: World | None = None,
) -> Analysis:
    """Baseline, contact settling times and distinct responses of one controller.

    `tolerance_mm` and `resolution_mm` are wheel travel in mm per step in `world`: by default
    the world the document says it was evolved in, else `evorobotics.sim.DEFAULT_WORLD`.
    """
    spec = doc.spec
    if history < 1:
        raise ValueError(f"history must be >= 1, got {history}")
    if (2**spec.inputs) ** history > MAX_SEQUENCES:
        raise ValueError(
            f"history {history} with {spec.inputs} inputs means {(2**spec.inputs) ** history} "
            f"sequences; the limit is {MAX_SEQUENCES}"
        )
    if not (np.isfinite(tolerance_mm) and tolerance_mm >= 0):
        raise ValueError(f"tolerance_mm must be finite and >= 0, got {tolerance_mm}")
    if not (np.isfinite(resolution_mm) and resolution_mm > 0):
        raise ValueError(f"resolution_mm must be finite and > 0, got {resolution_mm}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if warmup < 4:
        raise ValueError(f"warmup must be >= 4, got {warmup}")
    mm = mm_per_step(world or doc.world or DEFAULT_WORLD)
    tol = tolerance_mm / mm
    w = np.ascontiguousarray(doc.weights, dtype=np.float64)
    warm_motors, state = _after_state(spec, w, reset(spec, 1), warmup)
    baseline = classify_baseline(warm_motors, tol)
    contacts, reference = _contacts(spec, w, state, baseline, tol, max_steps, mm)
    singles = [c.settle_steps for c in contacts if c.duration == 1 and len(c.inputs) == 1]
    max_settle = None if any(s is None for s in singles) else max(s or 0 for s in singles)
    distinct, memory = distinct_responses(spec, w, state, history, resolution_mm / mm)
    return Analysis(
        sha256=doc.sha256,
        spec=spec.model_dump(mode="json"),
        history=history,
        full_speed_mm_per_step=mm,
        tolerance_mm_per_step=float(tolerance_mm),
        resolution_mm_per_step=float(resolution_mm),
        max_steps=max_steps,
        warmup=warmup,
        baseline=baseline,
        reference=_rows(reference),
        trace_start=-PRE,
        contacts=contacts,
        max_settle_steps=max_settle,
        distinct=distinct,
        reactive_bound=2**spec.inputs,
        memory=memory,
        memory_saturated=memory == history,
    )


@dataclass(frozen=True)
class Encounter:
    """Steps of one wall encounter in a recorded trial (indices into its whiskers/motors)."""

    start: int
    """First step shown: up to `lead` steps before the onset."""
    onset: int
    """First step with a whisker touching, after at least one step with none."""
    release: int
    """First step after the onset with no whisker touching."""
    stop: int
    """One past the last step shown: `after` steps past the release, or the trial's end."""
    backward: tuple[int, ...]
    """Steps in start..stop-1 whose mean wheel command is < 0 (the robot reverses)."""


def wall_encounter(
    whiskers: np.ndarray, motors: np.ndarray, *, lead: int = 4, after: int = 8
) -> Encounter | None:
    """The first wall encounter with a backward move in a recorded trial, else the first one.

    `whiskers` (steps, n) bits and `motors` (steps, 2) commands of one robot
    (`record_path`). None when no whisker ever touches after a free step.
    """
    touch = np.asarray(np.asarray(whiskers).reshape(len(whiskers), -1).any(axis=1))
    back = np.asarray(np.asarray(motors).mean(axis=1) < 0)
    if touch.shape != back.shape:
        raise ValueError(f"whiskers and motors differ in steps: {touch.shape} vs {back.shape}")
    n = touch.shape[0]
    found: list[Encounter] = []
    for onset in np.flatnonzero(touch[1:] & ~touch[:-1]) + 1:
        free = np.flatnonzero(~touch[onset:])
        release = n if free.size == 0 else int(onset + free[0])
        start, stop = max(0, int(onset) - lead), min(n, release + after)
        steps = tuple(int(k) for k in np.flatnonzero(back[start:stop]) + start)
        found.append(Encounter(start, int(onset), release, stop, steps))
        if any(k >= onset for k in steps):
            return found[-1]
    return found[0] if found else None
