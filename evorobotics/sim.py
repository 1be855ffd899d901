"""The maze simulator (paper section 2.2): differential-drive EvBots with five binary whiskers.

Every robot is independent (robots do not interact) and carries its own controller, a row of a
(batch, n_weights) weight array. One step of one robot, in this order:

1. sense: whisker k triggers (bit 1) iff a wall cell lies within the robot's trigger distance
   (nominal 50 mm) of its attachment point along its direction. Exact ray vs grid: slab test of
   the segment against every wall cell its bounding box touches (outside the grid is wall).
2. think: the controller maps the five bits to two wheel commands in [-1, 1]
   (`network.motor_commands`).
3. act: wheel speed = command * gain * max_speed; v = (vl + vr) / 2, w = (vr - vl) / wheel_base;
   midpoint integration over dt: heading' = heading + w dt, position += v dt (cos, sin)(heading
   + w dt / 2); heading wrapped to [-pi, pi).
4. collide: the body is the 165 x 127 mm rectangle centred on the pose (the wheel axle passes
   through its centre). If the moved body overlaps a wall cell (exact separating-axis test;
   touching is not overlap) the move is blocked and the pose stays unchanged. A robot blocked
   on `stuck_after` consecutive steps (default 1, our rule rather than a quote from the paper:
   stuck as soon as its body would enter a wall) is stuck: it stays immobile for the rest of
   the trial (its controller keeps running so recordings stay complete) and its trial scores
   stuck = 1.

Fitness terms (Eq 12) are accumulated on the way: curve_length sums the straight distance of
every accepted move, net_offset is the final distance from the start position, max_offset the
largest distance from the start position at any step. So is `cells`, the number of distinct
grid cells the centre visited (a behaviour descriptor, not a fitness term).

`simulate` is the canonical path: one numba kernel runs controller, physics and fitness for all
robots and steps. `simulate_watched` is the same kernel measuring, as the robots move, what a
long trial is judged on (confinement, coverage, offsets: `explore`), with nothing recorded. `simulate_reference` is the same science as vectorised numpy over the batch,
kept as the reference the tests compare against. `clear_of_walls` is the start-pose test
(body clear, no whisker touching) in compiled code, bit-identical to the numpy geometry.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, cast

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, types
from numba.core import cgutils
from numba.core.typing.templates import Signature
from numba.extending import intrinsic

from evorobotics import network
from evorobotics.maze import Maze
from schemas.network import NetworkSpec
from schemas.world import N_WHISKERS, World

TWO_PI = 2.0 * math.pi


DEFAULT_WORLD = World()
"""The default world: every function's `params` default."""


@dataclass(frozen=True)
class Gap:
    """A robot's physics per robot: wheel gains (B, 2) and whisker trigger distances in m,
    either fixed for the trial, (B, 5) one per whisker or (B,) shared by the five, or
    (B, steps, 5) one per step and whisker (`World.gap_model`)."""

    whisker_range: np.ndarray
    motor_gain: np.ndarray

    @classmethod
    def nominal(cls, batch: int, params: World = DEFAULT_WORLD) -> Gap:
        """No gap: every robot at the world's nominal whisker ranges and wheel gains."""
        return cls(
            np.tile(np.array(params.whisker_ranges), (batch, 1)),
            np.tile(np.array(params.motor_gain), (batch, 1)),
        )

    def tile(self, k: int) -> Gap:
        """The batch repeated k times, in order: each of k individuals meets the same draws."""
        reps = (k,) + (1,) * (self.whisker_range.ndim - 1)
        return Gap(np.tile(self.whisker_range, reps), np.tile(self.motor_gain, (k, 1)))


class _Trials:
    """What every batch of trials reports: Eq 12's terms and the step each robot stuck on."""

    curve_length: np.ndarray
    net_offset: np.ndarray
    max_offset: np.ndarray
    stuck_step: np.ndarray

    @property
    def stuck(self) -> np.ndarray:
        """(B,) bool: stuck by the end of the trial."""
        return self.stuck_step >= 0

    @property
    def components(self) -> np.ndarray:
        """(B, 4) in fitness.COMPONENTS order."""
        return np.stack(
            [self.curve_length, self.net_offset, self.max_offset, self.stuck.astype(np.float64)],
            axis=-1,
        )


@dataclass(frozen=True)
class SimResult(_Trials):
    """Final poses (B, 3), the Eq-12 terms (B,), and with record=True the per-step traces."""

    poses_final: np.ndarray
    curve_length: np.ndarray
    net_offset: np.ndarray
    max_offset: np.ndarray
    stuck_step: np.ndarray
    """(B,) int64: the step (1-based) on which the robot became stuck, -1 if it never did."""
    poses: np.ndarray | None = field(default=None)
    """(B, steps+1, 3) pose before each step and after the last."""
    whiskers: np.ndarray | None = field(default=None)
    """(B, steps, 5) uint8 bits sensed at the start of each step."""
    motors: np.ndarray | None = field(default=None)
    """(B, steps, 2) wheel commands in [-1, 1] the controller chose at each step."""
    cells: np.ndarray | None = field(default=None)
    """(B,) int64: distinct maze cells the robot's centre visited, its start cell included
    (a behaviour descriptor: `evaluate.DESCRIPTORS`). Always set by `simulate` and
    `simulate_reference`; None only in results built by hand."""


# ---------------------------------------------------------------- numpy geometry (reference)


def _wall_at(solid: np.ndarray, j: np.ndarray, i: np.ndarray) -> np.ndarray:
    """solid[j, i] with everything outside the grid a wall."""
    ny, nx = solid.shape
    inside = (j >= 0) & (j < ny) & (i >= 0) & (i < nx)
    return np.where(inside, solid[np.clip(j, 0, ny - 1), np.clip(i, 0, nx - 1)], True)


def body_hits_wall(maze: Maze, poses: np.ndarray, params: World = DEFAULT_WORLD) -> np.ndarray:
    """(B,) True where the body rectangle at `poses` (B, 3) overlaps a wall cell (SAT, exact)."""
    poses = np.asarray(poses, dtype=np.float64)
    cell = maze.cell_size
    h = cell / 2
    a, b = params.body_length / 2, params.body_width / 2
    k = math.ceil(2 * params.half_diagonal / cell) + 1
    x, y, th = poses[:, 0:1], poses[:, 1:2], poses[:, 2:3]
    c, s = np.cos(th), np.sin(th)
    ac, as_ = np.abs(c), np.abs(s)
    i0 = np.floor((x - params.half_diagonal) / cell).astype(np.int64)
    j0 = np.floor((y - params.half_diagonal) / cell).astype(np.int64)
    offs = np.arange(k)
    ii = (i0 + offs[None, :])[:, :, None]  # (B, k, 1)
    jj = (j0 + offs[None, :])[:, None, :]  # (B, 1, k)
    wall = _wall_at(maze.solid, jj, ii)  # (B, k, k)
    dx = ((ii + 0.5) * cell - x[:, :, None]) + 0.0 * jj
    dy = ((jj + 0.5) * cell - y[:, :, None]) + 0.0 * ii
    c3, s3, ac3, as3 = c[:, :, None], s[:, :, None], ac[:, :, None], as_[:, :, None]
    ox = np.abs(dx) < a * ac3 + b * as3 + h
    oy = np.abs(dy) < a * as3 + b * ac3 + h
    ou = np.abs(dx * c3 + dy * s3) < a + h * (ac3 + as3)
    ov = np.abs(dy * c3 - dx * s3) < b + h * (ac3 + as3)
    return np.asarray((wall & ox & oy & ou & ov).any(axis=(1, 2)))


def whisker_bits(
    maze: Maze,
    poses: np.ndarray,
    params: World = DEFAULT_WORLD,
    ranges: np.ndarray | None = None,
) -> np.ndarray:
    """(B, 5) uint8: 1 where a wall lies within range of a whisker's attachment point.

    `ranges` is the trigger distance per robot (B,) or per robot and whisker (B, 5); by default
    the world's nominal `whisker_ranges`.
    """
    poses = np.asarray(poses, dtype=np.float64)
    batch = poses.shape[0]
    r = (
        np.tile(np.array(params.whisker_ranges), (batch, 1))
        if ranges is None
        else np.asarray(ranges, float)
    )
    if r.ndim == 1:
        r = r[:, None]
    if r.shape not in ((batch, 1), (batch, N_WHISKERS)):
        raise ValueError(f"ranges must be ({batch},) or ({batch}, {N_WHISKERS}), got {r.shape}")
    cell = maze.cell_size
    x, y, th = poses[:, 0:1], poses[:, 1:2], poses[:, 2:3]
    c, s = np.cos(th), np.sin(th)
    wx, wy = np.array(params.whisker_x), np.array(params.whisker_y)
    px = x + c * wx - s * wy  # (B, 5)
    py = y + s * wx + c * wy
    ca, sa = np.cos(np.array(params.whisker_angle)), np.sin(np.array(params.whisker_angle))
    ux = c * ca - s * sa  # direction = heading rotated by the whisker angle
    uy = s * ca + c * sa
    r2 = r + 0.0 * px
    i0 = np.floor(np.minimum(px, px + r2 * ux) / cell).astype(np.int64)
    j0 = np.floor(np.minimum(py, py + r2 * uy) / cell).astype(np.int64)
    k = math.ceil(float(r.max(initial=0.0)) / cell) + 2
    offs = np.arange(k)
    ii = (i0[..., None] + offs)[..., :, None]  # (B, 5, k, 1)
    jj = (j0[..., None] + offs)[..., None, :]  # (B, 5, 1, k)
    wall = _wall_at(maze.solid, jj, ii)
    tx0, tx1 = _slab(ii * cell, (ii + 1) * cell, px[..., None, None], ux[..., None, None])
    ty0, ty1 = _slab(jj * cell, (jj + 1) * cell, py[..., None, None], uy[..., None, None])
    t_in = np.maximum(np.maximum(tx0, ty0), 0.0)
    t_out = np.minimum(tx1, ty1)
    hit = wall & (t_in <= t_out) & (t_in <= r2[..., None, None])
    return np.asarray(hit.any(axis=(2, 3)), dtype=np.uint8)


def _slab(
    lo: np.ndarray, hi: np.ndarray, p: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Parameter interval where p + t u lies in [lo, hi] on one axis (all t if parallel inside)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ta = (lo - p) / u
        tb = (hi - p) / u
    flat = np.abs(u) < 1e-12
    inside = (lo <= p) & (p <= hi)
    t0 = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    t1 = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return t0, t1


def move(poses: np.ndarray, motors: np.ndarray, gain: np.ndarray, params: World) -> np.ndarray:
    """(B, 3) poses after one unobstructed differential-drive step (midpoint integration)."""
    vl = motors[:, 0] * gain[:, 0] * params.max_speed
    vr = motors[:, 1] * gain[:, 1] * params.max_speed
    v = (vl + vr) * 0.5
    w = (vr - vl) / params.wheel_base
    th = poses[:, 2]
    mid = th + w * (params.dt * 0.5)
    out = np.empty_like(poses)
    out[:, 0] = poses[:, 0] + v * params.dt * np.cos(mid)
    out[:, 1] = poses[:, 1] + v * params.dt * np.sin(mid)
    out[:, 2] = _wrap(th + w * params.dt)
    return out


def _wrap(th: np.ndarray) -> np.ndarray:
    return np.asarray(th - TWO_PI * np.floor((th + math.pi) / TWO_PI))


# ---------------------------------------------------------------- shared argument checks


def _kernel_array(a: np.ndarray) -> np.ndarray:
    """C-contiguous float64 and writeable: a read-only array (e.g. cached start poses) would be
    another numba type, so another compilation of the kernel; the kernel never writes it."""
    out = np.ascontiguousarray(a, dtype=np.float64)
    return out if out.flags.writeable else out.copy()


@lru_cache(maxsize=16)
def _spec_sizes(spec: NetworkSpec) -> tuple[int, int, int, int]:
    """(weight count, linear output, state size, scratch size) of `spec`, cached: a call of
    `simulate` on a few robots must not spend its time recomputing them."""
    return (
        spec.weight_count,
        network.kernel_plan(spec).linear_output,
        network.state_size(spec),
        network.scratch_size(spec),
    )


@lru_cache(maxsize=16)
def _nominal_gap(batch: int, params: World) -> Gap:
    """`Gap.nominal`, cached for the kernels, which only read it (private: never returned)."""
    return Gap.nominal(batch, params)


_NO_RECORD = (
    np.zeros((0, 0, 3)),
    np.zeros((0, 0, N_WHISKERS), dtype=np.uint8),
    np.zeros((0, 0, 2)),
)
"""The trace arrays of a call without `record`: empty, never written."""


def _prepare(
    spec: NetworkSpec,
    weights: np.ndarray,
    start_poses: np.ndarray,
    steps: int,
    params: World,
    gap: Gap | None,
) -> tuple[np.ndarray, np.ndarray, Gap]:
    if spec.inputs != N_WHISKERS or spec.outputs != 2:
        raise ValueError(
            f"the EvBot needs a network with {N_WHISKERS} inputs and 2 outputs, got "
            f"{spec.inputs} and {spec.outputs}"
        )
    w = _kernel_array(weights)
    n_weights = _spec_sizes(spec)[0]
    if w.ndim != 2 or w.shape[1] != n_weights:
        raise ValueError(f"weights must be (batch, {n_weights}), got {w.shape}")
    batch = w.shape[0]
    poses = _kernel_array(start_poses)
    if poses.shape != (batch, 3):
        raise ValueError(f"start_poses must be ({batch}, 3), got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("start_poses must be finite")
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if gap is None:  # valid by construction (World checks whisker_range)
        return w, poses, _nominal_gap(batch, params)
    ranges = _kernel_array(gap.whisker_range)
    gains = _kernel_array(gap.motor_gain)
    shapes = ((batch,), (batch, N_WHISKERS), (batch, steps, N_WHISKERS))
    if ranges.shape not in shapes or gains.shape != (batch, 2):
        raise ValueError(
            f"gap must hold whisker_range ({batch},), ({batch}, {N_WHISKERS}) or "
            f"({batch}, {steps}, {N_WHISKERS}) and "
            f"motor_gain ({batch}, 2), got {ranges.shape} and {gains.shape}"
        )
    if not (np.isfinite(ranges).all() and (ranges >= 0).all() and np.isfinite(gains).all()):
        raise ValueError("gap values must be finite, whisker ranges >= 0")
    return w, poses, Gap(ranges, gains)


# ---------------------------------------------------------------- numpy reference episode


def simulate_reference(
    spec: NetworkSpec,
    weights: np.ndarray,
    maze: Maze,
    start_poses: np.ndarray,
    steps: int,
    params: World = DEFAULT_WORLD,
    gap: Gap | None = None,
    record: bool = False,
) -> SimResult:
    """`simulate` in vectorised numpy over the batch (a Python loop over steps only)."""
    w, pose, gap = _prepare(spec, weights, start_poses, steps, params, gap)
    batch = w.shape[0]
    start = pose.copy()
    state = network.reset(spec, batch)
    blocked = np.zeros(batch, dtype=np.int64)
    stuck = np.zeros(batch, dtype=bool)
    stuck_step = np.full(batch, -1, dtype=np.int64)
    curve = np.zeros(batch)
    max_off = np.zeros(batch)
    visited = np.zeros((batch, maze.solid.size), dtype=bool)
    _visit(visited, maze, pose)
    trace_p, trace_w, trace_m = [pose.copy()], [], []
    per_step = gap.whisker_range.ndim == 3
    for k in range(steps):
        bits = whisker_bits(
            maze, pose, params, gap.whisker_range[:, k] if per_step else gap.whisker_range
        )
        out, state = network.step_reference(spec, w, bits.astype(np.float64), state)
        motors = network.motor_commands(spec, out)
        cand = move(pose, motors, gap.motor_gain, params)
        hit = body_hits_wall(maze, cand, params)
        moving = ~stuck
        accept = moving & ~hit
        blocked = np.where(moving & hit, blocked + 1, np.where(accept, 0, blocked))
        now_stuck = moving & (blocked >= params.stuck_after)
        stuck_step = np.where(now_stuck, k + 1, stuck_step)
        stuck = stuck | now_stuck
        ddx, ddy = cand[:, 0] - pose[:, 0], cand[:, 1] - pose[:, 1]
        curve = curve + np.where(accept, np.sqrt(ddx * ddx + ddy * ddy), 0.0)
        pose = np.where(accept[:, None], cand, pose)
        _visit(visited, maze, pose)
        ox, oy = pose[:, 0] - start[:, 0], pose[:, 1] - start[:, 1]
        max_off = np.maximum(max_off, np.sqrt(ox * ox + oy * oy))
        if record:
            trace_p.append(pose.copy())
            trace_w.append(bits)
            trace_m.append(motors)
    ox, oy = pose[:, 0] - start[:, 0], pose[:, 1] - start[:, 1]
    net = np.sqrt(ox * ox + oy * oy)
    cells = visited.sum(axis=1, dtype=np.int64)
    if not record:
        return SimResult(pose, curve, net, max_off, stuck_step, cells=cells)
    return SimResult(
        pose,
        curve,
        net,
        max_off,
        stuck_step,
        np.stack(trace_p, axis=1),
        np.stack(trace_w, axis=1) if steps else np.zeros((batch, 0, N_WHISKERS), np.uint8),
        np.stack(trace_m, axis=1) if steps else np.zeros((batch, 0, 2)),
        cells,
    )


def _visit(visited: np.ndarray, maze: Maze, pose: np.ndarray) -> None:
    """Mark the grid cell (row-major over `solid`) under each centre in `visited` (B, ny*nx);
    a centre outside the grid marks nothing."""
    ny, nx = maze.solid.shape
    i = np.floor(pose[:, 0] / maze.cell_size)
    j = np.floor(pose[:, 1] / maze.cell_size)
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    rows = np.flatnonzero(inside)
    visited[rows, (j[rows] * nx + i[rows]).astype(np.int64)] = True


# ---------------------------------------------------------------- compiled kernel


@njit(inline="always")
def _wall(solid: np.ndarray, j: int, i: int) -> bool:
    if j < 0 or i < 0 or j >= solid.shape[0] or i >= solid.shape[1]:
        return True
    return bool(solid[j, i])


@njit(inline="always")
def _sat_extents(
    cell: float, c: float, s: float, a: float, b: float
) -> tuple[float, float, float, float]:
    """Separating-axis half-extents of body (half-sizes a, b; heading (c, s)) plus a wall cell,
    on the world x, y axes and the body's u, v axes."""
    h = cell / 2
    ac = abs(c)
    as_ = abs(s)
    return (a * ac + b * as_ + h, a * as_ + b * ac + h, a + h * (ac + as_), b + h * (ac + as_))


@njit(inline="always")
def _blocked(
    solid: np.ndarray,
    cell: float,
    x: float,
    y: float,
    c: float,
    s: float,
    a: float,
    b: float,
    hd: float,
) -> bool:
    """The SAT test of `body_hits_wall` for one pose, heading given as (cos, sin)."""
    ex, ey, eu, ev = _sat_extents(cell, c, s, a, b)
    i0 = math.floor((x - hd) / cell)
    j0 = math.floor((y - hd) / cell)
    i1 = math.floor((x + hd) / cell)
    j1 = math.floor((y + hd) / cell)
    for i in range(i0, i1 + 1):
        dx = (i + 0.5) * cell - x
        if not abs(dx) < ex:
            continue
        for j in range(j0, j1 + 1):
            if not _wall(solid, j, i):
                continue
            dy = (j + 0.5) * cell - y
            if abs(dy) < ey and abs(dx * c + dy * s) < eu and abs(dy * c - dx * s) < ev:
                return True
    return False


@njit(inline="always")
def _clearance(clear: np.ndarray, cell: float, x: float, y: float) -> float:
    """Lower bound on the distance from (x, y) to any wall (0 outside the grid).

    Multiplies by CLEARANCE_SUB/cell (hoisted out of the episode loop once inlined) instead
    of dividing: where the two round to different squares the point is within an ulp of their
    shared edge, so either square's bound (which keeps a 1e-9 margin) holds; an early out,
    never a result.
    """
    inv = CLEARANCE_SUB / cell
    i = math.floor(x * inv)
    j = math.floor(y * inv)
    if j < 0 or i < 0 or j >= clear.shape[0] or i >= clear.shape[1]:
        return 0.0
    return float(clear[j, i])


@njit(inline="always")
def _slab1(lo: float, hi: float, p: float, u: float) -> tuple[float, float]:
    if abs(u) < 1e-12:
        if lo <= p and p <= hi:
            return -np.inf, np.inf
        return np.inf, -np.inf
    ta = (lo - p) / u
    tb = (hi - p) / u
    return min(ta, tb), max(ta, tb)


@njit(inline="always")
def _whisker(
    solid: np.ndarray, cell: float, px: float, py: float, ux: float, uy: float, r: float
) -> bool:
    """True if a wall cell meets the segment p + t u, 0 <= t <= r (exact slab test)."""
    ex = px + r * ux
    ey = py + r * uy
    i0 = math.floor(min(px, ex) / cell)
    i1 = math.floor(max(px, ex) / cell)
    j0 = math.floor(min(py, ey) / cell)
    j1 = math.floor(max(py, ey) / cell)
    for i in range(i0, i1 + 1):
        tx0, tx1 = _slab1(i * cell, (i + 1) * cell, px, ux)
        if tx0 > tx1:
            continue
        for j in range(j0, j1 + 1):
            if not _wall(solid, j, i):
                continue
            ty0, ty1 = _slab1(j * cell, (j + 1) * cell, py, uy)
            t_in = max(max(tx0, ty0), 0.0)
            t_out = min(tx1, ty1)
            if t_in <= t_out and t_in <= r:
                return True
    return False


SINCOS_LIMIT = 1e8
"""Angles beyond this magnitude (only in absurd worlds, a tiny wheel base spun fast) take cos
and sin from libm; within it the three-part reduction by pi/2 below is accurate."""
TWO_OVER_PI = 0.6366197723675814
PIO2 = (1.570796012878418, 3.139164164167596e-07, 6.223372171896613e-14)
"""pi/2 in three parts, the first two of 21 bits, so n * part is exact for |n| < 2^32."""
SIN_TAYLOR = tuple((-1.0) ** j / math.factorial(2 * j + 1) for j in range(8, 0, -1))
"""sin r = r + r z S(z), z = r^2: S's Taylor coefficients, Horner order (to r^17)."""
COS_TAYLOR = tuple((-1.0) ** j / math.factorial(2 * j) for j in range(9, 0, -1))
"""cos r = 1 + z C(z): C's Taylor coefficients, Horner order (to r^18)."""


@njit(cache=True)
def _sincos(x: float) -> tuple[float, float]:
    """(cos x, sin x) in the operations `_sincos_tile` repeats lane by lane.

    Not libm's (which has no SIMD form in numba) but one fixed sequence of IEEE operations:
    x = n pi/2 + r, |r| <= pi/4, Taylor polynomials in r, the quadrant n mod 4 picking signs
    and order. Within a few ulp of libm; identical bits scalar or vectorised, on any machine.
    """
    if not abs(x) <= SINCOS_LIMIT:
        return math.cos(x), math.sin(x)
    n = math.floor(x * TWO_OVER_PI + 0.5)
    r = ((x - n * PIO2[0]) - n * PIO2[1]) - n * PIO2[2]
    z = r * r
    ps = SIN_TAYLOR[0]
    for i in range(1, len(SIN_TAYLOR)):
        ps = ps * z + SIN_TAYLOR[i]
    pc = COS_TAYLOR[0]
    for i in range(1, len(COS_TAYLOR)):
        pc = pc * z + COS_TAYLOR[i]
    s = r + r * z * ps
    c = 1.0 + z * pc
    q = int(n) & 3
    if q == 0:
        return c, s
    if q == 1:
        return -s, c
    if q == 2:
        return -c, -s
    return s, -c


@intrinsic
def _sincos_tile(
    typingctx: object, x: Any, cos_out: Any, sin_out: Any
) -> tuple[Signature, Callable[..., object]]:
    """cos_out, sin_out = `_sincos`(x) for the LANES values of 1-D arrays, as SIMD.

    Lanes beyond SINCOS_LIMIT (or NaN) get garbage: the caller takes libm's for them, as
    `_sincos` does.
    """
    sig = types.void(x, cos_out, sin_out)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        lanes = network.LANES
        f64 = llvm_ir.DoubleType()
        vec = llvm_ir.VectorType(f64, lanes)
        ivec = llvm_ir.VectorType(llvm_ir.IntType(64), lanes)

        def splat(value: float) -> object:
            return llvm_ir.Constant(vec, [value] * lanes)

        def pointer(k: int) -> object:
            data = context.make_array(signature.args[k])(context, builder, args[k]).data
            return builder.bitcast(data, vec.as_pointer())

        fnty = llvm_ir.FunctionType(vec, [vec])
        floor = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
            builder.module, fnty, f"llvm.floor.v{lanes}f64"
        )
        fabs = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
            builder.module, fnty, f"llvm.fabs.v{lanes}f64"
        )
        x_v = builder.load(pointer(0), align=8)
        inside = builder.fcmp_ordered("<=", builder.call(fabs, [x_v]), splat(SINCOS_LIMIT))
        xc = builder.select(inside, x_v, splat(0.0))
        n = builder.call(floor, [builder.fadd(builder.fmul(xc, splat(TWO_OVER_PI)), splat(0.5))])
        r = xc
        for part in PIO2:
            r = builder.fsub(r, builder.fmul(n, splat(part)))
        z = builder.fmul(r, r)
        ps = splat(SIN_TAYLOR[0])
        for coefficient in SIN_TAYLOR[1:]:
            ps = builder.fadd(builder.fmul(ps, z), splat(coefficient))
        pc = splat(COS_TAYLOR[0])
        for coefficient in COS_TAYLOR[1:]:
            pc = builder.fadd(builder.fmul(pc, z), splat(coefficient))
        s = builder.fadd(r, builder.fmul(builder.fmul(r, z), ps))
        c = builder.fadd(splat(1.0), builder.fmul(z, pc))
        q = builder.and_(builder.fptosi(n, ivec), llvm_ir.Constant(ivec, [3] * lanes))

        def quadrant(k: int) -> object:
            return builder.icmp_signed("==", q, llvm_ir.Constant(ivec, [k] * lanes))

        neg_s, neg_c = builder.fneg(s), builder.fneg(c)
        cos_v = builder.select(
            quadrant(0),
            c,
            builder.select(quadrant(1), neg_s, builder.select(quadrant(2), neg_c, s)),
        )
        sin_v = builder.select(
            quadrant(0),
            s,
            builder.select(quadrant(1), c, builder.select(quadrant(2), neg_s, neg_c)),
        )
        builder.store(cos_v, pointer(1), align=8)
        builder.store(sin_v, pointer(2), align=8)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _act_tile(
    typingctx: object,
    out: Any,
    gains: Any,
    ths: Any,
    world: Any,
    linear_output: Any,
    motors: Any,
    speed: Any,
    mids: Any,
    nths: Any,
) -> tuple[Signature, Callable[..., object]]:
    """The act step of `_episodes` for the LANES lanes at once, as SIMD.

    From raw outputs `out` (2, LANES) and wheel gains (2, LANES): the wheel commands
    (`network.motor_one`'s operations: 2y - 1 unless linear, NaN to 0, clipped to [-1, 1])
    into `motors` (2, LANES), and with headings `ths` the move's speed, midpoint heading and
    wrapped new heading, in `_drive`'s operations lane by lane (no FMA contraction).
    """
    sig = types.void(out, gains, ths, world, linear_output, motors, speed, mids, nths)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        lanes = network.LANES
        f64 = llvm_ir.DoubleType()
        vec = llvm_ir.VectorType(f64, lanes)

        def splat(value: Any) -> Any:
            if isinstance(value, float):
                return llvm_ir.Constant(vec, [value] * lanes)
            undef = llvm_ir.Constant(vec, llvm_ir.Undefined)
            one = builder.insert_element(undef, value, llvm_ir.Constant(llvm_ir.IntType(32), 0))
            return builder.shuffle_vector(
                one,
                undef,
                llvm_ir.Constant(llvm_ir.VectorType(llvm_ir.IntType(32), lanes), [0] * lanes),
            )

        def row(k: int, r: int) -> Any:
            data = context.make_array(signature.args[k])(context, builder, args[k]).data
            return builder.bitcast(
                builder.gep(data, [llvm_ir.Constant(llvm_ir.IntType(64), r * lanes)]),
                vec.as_pointer(),
            )

        world_data = context.make_array(signature.args[3])(context, builder, args[3]).data

        def world_at(i: int) -> Any:
            return builder.load(builder.gep(world_data, [llvm_ir.Constant(llvm_ir.IntType(64), i)]))

        dt, vmax, base = world_at(0), world_at(1), world_at(2)
        floor = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
            builder.module, llvm_ir.FunctionType(vec, [vec]), f"llvm.floor.v{lanes}f64"
        )
        linear = builder.icmp_signed("!=", args[4], llvm_ir.Constant(args[4].type, 0))
        commands = []
        for k in range(2):
            y = builder.load(row(0, k), align=8)
            y = builder.select(linear, y, builder.fsub(builder.fmul(splat(2.0), y), splat(1.0)))
            m = builder.select(builder.fcmp_ordered("<", y, splat(-1.0)), splat(-1.0), y)
            m = builder.select(builder.fcmp_ordered(">", y, splat(1.0)), splat(1.0), m)
            m = builder.select(builder.fcmp_unordered("uno", y, y), splat(0.0), m)
            builder.store(m, row(5, k), align=8)
            commands.append(m)
        vm = splat(vmax)
        vl = builder.fmul(builder.fmul(commands[0], builder.load(row(1, 0), align=8)), vm)
        vr = builder.fmul(builder.fmul(commands[1], builder.load(row(1, 1), align=8)), vm)
        builder.store(builder.fmul(builder.fadd(vl, vr), splat(0.5)), row(6, 0), align=8)
        om = builder.fdiv(builder.fsub(vr, vl), splat(base))
        th = builder.load(row(2, 0), align=8)
        builder.store(
            builder.fadd(th, builder.fmul(om, splat(builder.fmul(dt, llvm_ir.Constant(f64, 0.5))))),
            row(7, 0),
            align=8,
        )
        nth = builder.fadd(th, builder.fmul(om, splat(dt)))
        turns = builder.call(
            floor, [builder.fdiv(builder.fadd(nth, splat(math.pi)), splat(TWO_PI))]
        )
        builder.store(builder.fsub(nth, builder.fmul(splat(TWO_PI), turns)), row(8, 0), align=8)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _near_tile(
    typingctx: object,
    xs: Any,
    ys: Any,
    cs: Any,
    ss: Any,
    wx: Any,
    wy: Any,
    rq: Any,
    clear: Any,
    inv: Any,
    near: Any,
) -> tuple[Signature, Callable[..., object]]:
    """near[q, lane] = 1 where whisker q of the lane's robot may touch a wall, as SIMD over
    the LANES lanes, for the N_WHISKERS whiskers.

    From the robot's pose (xs, ys, cos cs, sin ss), whisker q's attachment point in
    `_sense_one`'s operations lane by lane; its square of the clearance map at `inv` =
    CLEARANCE_SUB / cell (`_clearance`'s, 0 outside the grid); 1 if that clearance is no more
    than the whisker's range rq[q, lane], else 0: no wall within its reach. No branch on a
    lane's outcome; idle lanes (any values, NaN included) form no index off the map.
    """
    sig = types.void(xs, ys, cs, ss, wx, wy, rq, clear, inv, near)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> object:
        lanes = network.LANES
        f64 = llvm_ir.DoubleType()
        i64 = llvm_ir.IntType(64)
        i32 = llvm_ir.IntType(32)
        vec = llvm_ir.VectorType(f64, lanes)
        flags = llvm_ir.VectorType(llvm_ir.IntType(8), lanes)

        def array(k: int) -> Any:
            return context.make_array(signature.args[k])(context, builder, args[k])

        def row(k: int, r: int, ty: Any = vec) -> Any:
            data = builder.gep(array(k).data, [llvm_ir.Constant(i64, r * lanes)])
            return builder.bitcast(data, ty.as_pointer())

        def splat(value: Any) -> Any:
            if isinstance(value, float):
                return llvm_ir.Constant(vec, [value] * lanes)
            undef = llvm_ir.Constant(vec, llvm_ir.Undefined)
            one = builder.insert_element(undef, value, llvm_ir.Constant(i32, 0))
            zeros = llvm_ir.Constant(llvm_ir.VectorType(i32, lanes), [0] * lanes)
            return builder.shuffle_vector(one, undef, zeros)

        def scalar(k: int, q: int) -> Any:
            return splat(builder.load(builder.gep(array(k).data, [llvm_ir.Constant(i64, q)])))

        floor = cgutils.get_or_insert_function(  # type: ignore[no-untyped-call]
            builder.module, llvm_ir.FunctionType(vec, [vec]), f"llvm.floor.v{lanes}f64"
        )
        x, y, c, s = (builder.load(row(k, 0), align=8) for k in range(4))
        grid = array(7)
        n_rows, n_cols = (
            splat(builder.sitofp(v, f64))
            for v in cgutils.unpack_tuple(builder, grid.shape, 2)  # type: ignore[no-untyped-call]
        )
        zero = splat(0.0)
        scale = splat(args[8])
        for q in range(N_WHISKERS):
            wxq, wyq = scalar(4, q), scalar(5, q)
            px = builder.fsub(builder.fadd(x, builder.fmul(c, wxq)), builder.fmul(s, wyq))
            py = builder.fadd(builder.fadd(y, builder.fmul(s, wxq)), builder.fmul(c, wyq))
            i = builder.call(floor, [builder.fmul(px, scale)])
            j = builder.call(floor, [builder.fmul(py, scale)])
            inside = builder.and_(
                builder.and_(
                    builder.fcmp_ordered(">=", i, zero), builder.fcmp_ordered("<", i, n_cols)
                ),
                builder.and_(
                    builder.fcmp_ordered(">=", j, zero), builder.fcmp_ordered("<", j, n_rows)
                ),
            )
            at = builder.fptosi(
                builder.fadd(
                    builder.fmul(builder.select(inside, j, zero), n_cols),
                    builder.select(inside, i, zero),
                ),
                llvm_ir.VectorType(i64, lanes),
            )
            squares = llvm_ir.Constant(vec, llvm_ir.Undefined)
            for lane in range(lanes):
                k = llvm_ir.Constant(i32, lane)
                value = builder.load(builder.gep(grid.data, [builder.extract_element(at, k)]))
                squares = builder.insert_element(squares, value, k)
            clearance = builder.select(inside, squares, zero)
            reach = builder.load(row(6, q), align=8)
            maybe = builder.fcmp_ordered("<=", clearance, reach)
            builder.store(builder.zext(maybe, flags), row(9, q, flags), align=1)
        return context.get_dummy_value()

    return sig, codegen


@njit(inline="always")
def _episodes(
    kernel: network.Kernel,
    weights: np.ndarray,
    linear_output: int,
    n_state: int,
    n_scratch: int,
    solid: np.ndarray,
    cell: float,
    starts: np.ndarray,
    steps: int,
    world: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    ca: np.ndarray,
    sa: np.ndarray,
    clear: np.ndarray,
    stuck_after: int,
    ranges: np.ndarray,
    gains: np.ndarray,
    record: bool,
    watch: bool,
    marks: tuple[float, int, int],
    confine: tuple[int, float, int],
    final: np.ndarray,
    metrics: np.ndarray,
    stuck_out: np.ndarray,
    cells_out: np.ndarray,
    traces: tuple[np.ndarray, np.ndarray, np.ndarray],
    watched: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Every robot's whole trial: sense, think, act, collide, score (see the module docstring).

    `kernel` is the controller (`network.spec_kernel`), which steps a tile of `network.LANES`
    robots at once. Each lane carries one robot through its trial; a lane whose robot is done
    (all steps, or stuck when not recording: its terms are final) takes the next robot of the
    batch, and once the batch is used up it idles (zero weights, skipped by the physics and
    the activations). Robots meet the same arithmetic in any lane, so each robot's result is
    bit-identical whatever the batch. Inlined (numba IR) into the generated per-spec wrapper
    (`_episode_kernel`), where `kernel` is a module global: a dispatcher passed as a value
    would make the wrapper uncacheable. Not disk-cached itself; the wrapper's cache key covers
    this file, so an edit here is never served stale from disk.

    `ranges` (B, S, W) holds the whiskers' trigger distances: S = 1, fixed for the trial, or
    S = steps, one row per step; W = 1, shared by the five whiskers, or W = 5.

    `cells_out[r]` counts the squares of side `mark_cell` (a grid of `mark_rows` x `mark_cols`
    from the origin: `marks`) robot r's centre visited: a bitmap per lane, marked on every accepted move,
    whose marks are undone from the lane's `trail` when its robot is done (cheaper than clearing
    the whole map).

    With `record`, `traces` receives every robot's poses, whisker bits and motor commands.

    With `watch` (never with `record`: the generated wrappers fix both, so the other's code is
    compiled out) the kernel also measures what `explore.trials` reads from recorded paths, as
    the robots move, into `watched`: `confined_out[r]`, a run of `window` steps before sticking
    whose positions fit a box of `diagonal` (`_confine`; `confine` is window, diagonal, horizon); `offsets_out[:, r]`, the largest distance from the
    start by step `horizon` and over the trial and the distance at step `horizon`; and
    `moves_out[r, k]`, the length of move k < `horizon` (0 when blocked). Distances are
    `math.hypot`'s, numpy's libm function, as the recorded definition computes them.
    """
    dt = world[0]
    a = world[3]
    b = world[4]
    hd = world[5]
    mark_cell, mark_rows, mark_cols = marks
    window, diagonal, horizon = confine
    rec_poses, rec_whiskers, rec_motors = traces
    confined_out, offsets_out, moves_out = watched
    lanes = network.LANES
    n_q = wx.shape[0]
    n_w = weights.shape[1]
    batch = weights.shape[0]
    w_tile = np.zeros((n_w, lanes))
    state = np.zeros((n_state, lanes))
    scratch = np.empty((n_scratch, lanes))
    inputs = np.zeros((n_q, lanes))
    out = np.empty((2, lanes))
    motors = np.zeros((2, lanes))
    speed = np.zeros(lanes)
    mids = np.zeros(lanes)
    nths = np.zeros(lanes)
    cos_mid = np.empty(lanes)
    sin_mid = np.empty(lanes)
    cos_new = np.empty(lanes)
    sin_new = np.empty(lanes)
    live = np.zeros(lanes, dtype=np.uint8)
    gain_tile = np.zeros((2, lanes))
    changed = np.zeros(lanes, dtype=np.uint8)  # robot taken or retired in this refill
    sensed = np.zeros(lanes, dtype=np.uint8)  # inputs hold the bits at the lane's pose
    wall_x = np.full(lanes, np.nan)  # the last pose the lane's body was blocked at
    wall_y = np.full(lanes, np.nan)
    wall_th = np.full(lanes, np.nan)
    new_lanes = np.zeros(lanes, dtype=np.int64)
    robot = np.full(lanes, -1, dtype=np.int64)
    step = np.zeros(lanes, dtype=np.int64)
    xs = np.zeros(lanes)
    ys = np.zeros(lanes)
    ths = np.zeros(lanes)
    cs = np.zeros(lanes)
    ss = np.zeros(lanes)
    x0s = np.zeros(lanes)
    y0s = np.zeros(lanes)
    rq = np.zeros((n_q, lanes))  # whisker ranges
    near = np.zeros((n_q, lanes), dtype=np.uint8)  # `_near_tile`'s
    inv_square = CLEARANCE_SUB / cell  # `_clearance`'s
    blocked = np.zeros(lanes, dtype=np.int64)
    stuck_at = np.full(lanes, -1, dtype=np.int64)
    curve = np.zeros(lanes)
    max_off = np.zeros(lanes)
    n_cells = np.zeros(lanes, dtype=np.int64)
    visited = np.zeros((lanes, mark_rows * mark_cols), dtype=np.uint8)
    trail = np.empty((lanes, min(steps + 1, mark_rows * mark_cols)), dtype=np.int64)  # new only
    span = window + 1 if watch else 0  # positions of a confinement window
    window_xy = np.empty((lanes, 2, span))
    suffix = np.empty((lanes, 4, span))
    window_state = np.zeros((lanes, 2), dtype=np.int64)  # place in the block, `_confine`'s
    confined = np.zeros(lanes, dtype=np.uint8)
    farthest = np.zeros(lanes)
    per_step = ranges.shape[1] != 1
    last = ranges.shape[2] - 1
    next_robot = 0
    while True:
        n_live = 0
        for lane in range(lanes):
            while True:  # retire a finished robot, take the next one
                r = robot[lane]
                if r >= 0 and step[lane] < steps and (stuck_at[lane] < 0 or record):
                    break
                if r >= 0:
                    final[r, 0] = xs[lane]
                    final[r, 1] = ys[lane]
                    final[r, 2] = ths[lane]
                    ox = xs[lane] - x0s[lane]
                    oy = ys[lane] - y0s[lane]
                    metrics[0, r] = curve[lane]
                    metrics[1, r] = math.sqrt(ox * ox + oy * oy)
                    metrics[2, r] = max_off[lane]
                    stuck_out[r] = stuck_at[lane]
                    cells_out[r] = n_cells[lane]
                    if watch:
                        if not confined[lane]:  # the windows ending in the last, partial block
                            n = window_state[lane, 0]
                            confined[lane] = _confine(
                                window_xy, suffix, window_state, lane, n, diagonal
                            )
                        confined_out[r] = confined[lane]
                        offsets_out[1, r] = farthest[lane]
                        if step[lane] < horizon:  # stuck before it: nothing moves from here
                            offsets_out[0, r] = farthest[lane]
                            offsets_out[2, r] = math.hypot(ox, oy)
                    for t in range(n_cells[lane]):
                        visited[lane, trail[lane, t]] = 0
                    robot[lane] = -1
                    changed[lane] = 1
                if next_robot == batch:
                    break
                r = next_robot
                next_robot += 1
                robot[lane] = r
                changed[lane] = 1
                gain_tile[0, lane] = gains[r, 0]
                gain_tile[1, lane] = gains[r, 1]
                sensed[lane] = 0
                step[lane] = 0
                for i in range(n_state):
                    state[i, lane] = 0.0
                x = starts[r, 0]
                y = starts[r, 1]
                th = starts[r, 2]
                xs[lane] = x
                ys[lane] = y
                ths[lane] = th
                x0s[lane] = x
                y0s[lane] = y
                cs[lane], ss[lane] = _sincos(th)
                if not per_step:
                    for q in range(n_q):
                        rq[q, lane] = ranges[r, 0, min(q, last)]
                blocked[lane] = 0
                stuck_at[lane] = -1
                curve[lane] = 0.0
                max_off[lane] = 0.0
                n_cells[lane] = _mark(
                    visited[lane], trail[lane], 0, mark_cols, mark_rows, mark_cell, x, y
                )
                if watch:
                    farthest[lane] = 0.0
                    confined[lane] = 0
                    window_xy[lane, 0, 0] = x
                    window_xy[lane, 1, 0] = y
                    window_state[lane, 0] = 1
                    window_state[lane, 1] = span
                if record:
                    rec_poses[r, 0, 0] = x
                    rec_poses[r, 0, 1] = y
                    rec_poses[r, 0, 2] = th
            live[lane] = robot[lane] >= 0
            n_live += live[lane]
        if n_live == 0:
            break
        n_new = 0  # the weights of lanes that changed robot: one pass over the tile's rows
        for lane in range(lanes):
            if changed[lane]:
                changed[lane] = 0
                if live[lane]:
                    new_lanes[n_new] = lane
                    n_new += 1
                else:  # idle from now on: zero weights
                    for i in range(n_w):
                        w_tile[i, lane] = 0.0
        if n_new == lanes:  # row by row: each row of the tile written whole
            for i in range(n_w):
                for lane in range(lanes):
                    w_tile[i, lane] = weights[robot[lane], i]
        else:
            for f in range(n_new):
                lane = new_lanes[f]
                r = robot[lane]
                for i in range(n_w):
                    w_tile[i, lane] = weights[r, i]
        n_sense = 0  # a blocked or stuck robot senses what it did: not these
        for lane in range(lanes):
            if live[lane] and not sensed[lane]:
                n_sense += 1
                if per_step:
                    for q in range(n_q):
                        rq[q, lane] = ranges[robot[lane], step[lane], min(q, last)]
        # sense: which whiskers may touch a wall, all lanes at once; the exact test for those
        if n_sense:
            _near_tile(xs, ys, cs, ss, wx, wy, rq, clear, inv_square, near)  # type: ignore[call-arg]
        for lane in range(lanes):
            if not live[lane] or sensed[lane]:
                continue
            x = xs[lane]
            y = ys[lane]
            c = cs[lane]
            s = ss[lane]
            for q in range(n_q):
                inputs[q, lane] = 0.0
                if not near[q, lane]:
                    continue
                px = x + c * wx[q] - s * wy[q]
                py = y + s * wx[q] + c * wy[q]
                ux = c * ca[q] - s * sa[q]
                uy = s * ca[q] + c * sa[q]
                if _whisker(solid, cell, px, py, ux, uy, rq[q, lane]):
                    inputs[q, lane] = 1.0
            sensed[lane] = not per_step
        kernel(w_tile, state, inputs, out, scratch, live)  # think: the whole tile at once
        # act; intrinsics: numba supplies their typingctx
        _act_tile(out, gain_tile, ths, world, linear_output, motors, speed, mids, nths)  # type: ignore[call-arg]
        _sincos_tile(mids, cos_mid, sin_mid)
        _sincos_tile(nths, cos_new, sin_new)
        for lane in range(lanes):  # collide, score
            if not live[lane]:
                continue
            r = robot[lane]
            k = step[lane]
            if stuck_at[lane] < 0:
                x = xs[lane]
                y = ys[lane]
                mid = mids[lane]
                nth = nths[lane]
                cm, sm = cos_mid[lane], sin_mid[lane]
                if not abs(mid) <= SINCOS_LIMIT:
                    cm, sm = _sincos(mid)
                nc, ns = cos_new[lane], sin_new[lane]
                if not abs(nth) <= SINCOS_LIMIT:
                    nc, ns = _sincos(nth)
                v = speed[lane]
                nx = x + v * dt * cm
                ny = y + v * dt * sm
                # a robot pushing into a wall often tries the same blocked pose again
                again = nx == wall_x[lane] and ny == wall_y[lane] and nth == wall_th[lane]
                if again or (
                    _clearance(clear, cell, nx, ny) <= hd
                    and _blocked(solid, cell, nx, ny, nc, ns, a, b, hd)
                ):
                    wall_x[lane] = nx
                    wall_y[lane] = ny
                    wall_th[lane] = nth
                    blocked[lane] += 1
                    if blocked[lane] >= stuck_after:
                        stuck_at[lane] = k + 1
                else:
                    sensed[lane] = 0
                    blocked[lane] = 0
                    ddx = nx - x
                    ddy = ny - y
                    curve[lane] += math.sqrt(ddx * ddx + ddy * ddy)
                    xs[lane] = nx
                    ys[lane] = ny
                    ths[lane] = nth
                    cs[lane] = nc
                    ss[lane] = ns
                    ox = nx - x0s[lane]
                    oy = ny - y0s[lane]
                    off = math.sqrt(ox * ox + oy * oy)
                    max_off[lane] = max(max_off[lane], off)
                    n_cells[lane] = _mark(
                        visited[lane],
                        trail[lane],
                        n_cells[lane],
                        mark_cols,
                        mark_rows,
                        mark_cell,
                        nx,
                        ny,
                    )
                    if watch:
                        if k < horizon:
                            moves_out[r, k] = math.hypot(ddx, ddy)
                        # hypot and this root differ by a few ulp at most: only a root
                        # within 1e-12 of the farthest so far can move it
                        if off * (1.0 + 1e-12) > farthest[lane]:
                            farthest[lane] = max(farthest[lane], math.hypot(ox, oy))
                if watch:
                    n = window_state[lane, 0]
                    if stuck_at[lane] < 0 and not confined[lane]:  # a position before sticking
                        window_xy[lane, 0, n] = xs[lane]
                        window_xy[lane, 1, n] = ys[lane]
                        n += 1
                        if n == span:
                            confined[lane] = _confine(
                                window_xy, suffix, window_state, lane, n, diagonal
                            )
                            n = 0
                        window_state[lane, 0] = n
                    if k + 1 == horizon:
                        offsets_out[0, r] = farthest[lane]
                        offsets_out[2, r] = math.hypot(xs[lane] - x0s[lane], ys[lane] - y0s[lane])
            if record:
                rec_poses[r, k + 1, 0] = xs[lane]
                rec_poses[r, k + 1, 1] = ys[lane]
                rec_poses[r, k + 1, 2] = ths[lane]
                for q in range(n_q):
                    rec_whiskers[r, k, q] = np.uint8(inputs[q, lane])
                rec_motors[r, k, 0] = motors[0, lane]
                rec_motors[r, k, 1] = motors[1, lane]
            step[lane] = k + 1


@njit(inline="always")
def _confine(
    xy: np.ndarray, suffix: np.ndarray, state: np.ndarray, lane: int, n: int, diagonal: float
) -> bool:
    """True if a window of `xy.shape[2]` positions of the lane's robot ending at one of the
    first n positions of its current block fits a box of `diagonal` (`explore.confined`'s
    test); with a whole block (n = span), its suffix extremes then serve the next block's.

    The robot's positions go to `xy[lane]` in blocks of a window's length (`_episodes`); a
    window's extremes are the suffix extremes of the previous block and the prefix extremes of
    this one (van Herk-Gil-Werman, as `explore._confined_rows`): exact, max and min never round.
    hypot(dx, dy) >= max(dx, dy) up to its rounding, so a side longer than `loose` rules out a
    window and every window holding that side: prefixes stop growing at the first, suffixes
    are kept while they have none (from state[lane, 1] on; span: none, the first block). A
    roaming robot thus pays a few positions a block, once a block.
    """
    span = xy.shape[2]
    loose = diagonal * (1.0 + 1e-9)
    reach = state[lane, 1]
    fits = False
    x_hi = x_lo = xy[lane, 0, 0]
    y_hi = y_lo = xy[lane, 1, 0]
    for j in range(n):
        x_hi = max(x_hi, xy[lane, 0, j])
        x_lo = min(x_lo, xy[lane, 0, j])
        y_hi = max(y_hi, xy[lane, 1, j])
        y_lo = min(y_lo, xy[lane, 1, j])
        if x_hi - x_lo > loose or y_hi - y_lo > loose:
            break
        if j == span - 1:  # the window is the block
            dx = x_hi - x_lo
            dy = y_hi - y_lo
        elif j + 1 >= reach:  # the window starts at j + 1 in the previous block
            dx = max(suffix[lane, 0, j + 1], x_hi) - min(suffix[lane, 1, j + 1], x_lo)
            dy = max(suffix[lane, 2, j + 1], y_hi) - min(suffix[lane, 3, j + 1], y_lo)
        else:
            continue
        if dx <= loose and dy <= loose and math.hypot(dx, dy) <= diagonal:
            fits = True
            break
    if n < span:
        return fits
    q = span - 1
    x_hi = x_lo = xy[lane, 0, q]
    y_hi = y_lo = xy[lane, 1, q]
    while q >= 0:
        x_hi = max(x_hi, xy[lane, 0, q])
        x_lo = min(x_lo, xy[lane, 0, q])
        y_hi = max(y_hi, xy[lane, 1, q])
        y_lo = min(y_lo, xy[lane, 1, q])
        if x_hi - x_lo > loose or y_hi - y_lo > loose:
            break
        suffix[lane, 0, q] = x_hi
        suffix[lane, 1, q] = x_lo
        suffix[lane, 2, q] = y_hi
        suffix[lane, 3, q] = y_lo
        q -= 1
    state[lane, 1] = q + 1
    return fits


@njit(inline="always")
def _mark(
    visited: np.ndarray,
    trail: np.ndarray,
    n: int,
    cols: int,
    rows: int,
    cell: float,
    x: float,
    y: float,
) -> int:
    """Mark the cell under (x, y) visited (`_visit` of one robot); the new count of cells."""
    fi = math.floor(x / cell)
    fj = math.floor(y / cell)
    if fi < 0 or fj < 0 or fi >= cols or fj >= rows:
        return n
    k = fj * cols + fi
    if visited[k]:
        return n
    visited[k] = 1
    trail[n] = k
    return n + 1


@njit(cache=True)
def _body_overlaps(
    solid: np.ndarray,
    cell: float,
    x: float,
    y: float,
    c: float,
    s: float,
    a: float,
    b: float,
    hd: float,
    k: int,
) -> bool:
    """`body_hits_wall` of one pose: its k x k cells and its operations, in the same order."""
    ex, ey, eu, ev = _sat_extents(cell, c, s, a, b)
    i0 = math.floor((x - hd) / cell)
    j0 = math.floor((y - hd) / cell)
    for i in range(i0, i0 + k):
        dx = (i + 0.5) * cell - x
        for j in range(j0, j0 + k):
            dy = (j + 0.5) * cell - y
            if (
                _wall(solid, j, i)
                and abs(dx) < ex
                and abs(dy) < ey
                and abs(dx * c + dy * s) < eu
                and abs(dy * c - dx * s) < ev
            ):
                return True
    return False


@njit(cache=True)
def _whisker_touches(
    solid: np.ndarray, cell: float, px: float, py: float, ux: float, uy: float, r: float, k: int
) -> bool:
    """`whisker_bits` of one whisker: its k x k cells and its operations, in the same order."""
    i0 = math.floor(min(px, px + r * ux) / cell)
    j0 = math.floor(min(py, py + r * uy) / cell)
    for i in range(i0, i0 + k):
        tx0, tx1 = _slab1(i * cell, (i + 1) * cell, px, ux)
        for j in range(j0, j0 + k):
            if not _wall(solid, j, i):
                continue
            ty0, ty1 = _slab1(j * cell, (j + 1) * cell, py, uy)
            t_in = max(max(tx0, ty0), 0.0)
            t_out = min(tx1, ty1)
            if t_in <= t_out and t_in <= r:
                return True
    return False


@njit(cache=True)
def _clear_of_walls(
    solid: np.ndarray,
    cell: float,
    poses: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    body: np.ndarray,
    k_body: int,
    wx: np.ndarray,
    wy: np.ndarray,
    ca: np.ndarray,
    sa: np.ndarray,
    r: np.ndarray,
    k_whisker: int,
    out: np.ndarray,
) -> None:
    for n in range(poses.shape[0]):
        x = poses[n, 0]
        y = poses[n, 1]
        c = cos[n, 0]
        s = sin[n, 0]
        free = not _body_overlaps(solid, cell, x, y, c, s, body[0], body[1], body[2], k_body)
        for q in range(wx.shape[0]):
            if not free:
                break
            px = x + c * wx[q] - s * wy[q]
            py = y + s * wx[q] + c * wy[q]
            ux = c * ca[q] - s * sa[q]
            uy = s * ca[q] + c * sa[q]
            free = not _whisker_touches(solid, cell, px, py, ux, uy, r[q], k_whisker)
        out[n] = free


def clear_of_walls(maze: Maze, poses: np.ndarray, params: World = DEFAULT_WORLD) -> np.ndarray:
    """(B,) True where the body at `poses` (B, 3) is clear and no whisker (nominal ranges) touches.

    Bit for bit `~body_hits_wall(...) & ~whisker_bits(...).any(axis=1)` (the start-pose test),
    over ten times cheaper: the same cells and operations, one pose at a time in compiled code
    with no temporaries. Only cos and sin stay in numpy, computed on the same arrays as there,
    because numba's libm may round them differently.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must be (B, 3), got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("poses must be finite")
    th = poses[:, 2:3]
    c, s = np.cos(th), np.sin(th)
    angles = np.array(params.whisker_angle)
    cell = maze.cell_size
    out = np.empty(poses.shape[0], dtype=np.bool_)
    _clear_of_walls(
        _solid_u8(maze),
        cell,
        np.array(poses, order="C"),
        c,
        s,
        np.array([params.body_length / 2, params.body_width / 2, params.half_diagonal]),
        math.ceil(2 * params.half_diagonal / cell) + 1,
        np.array(params.whisker_x),
        np.array(params.whisker_y),
        np.cos(angles),
        np.sin(angles),
        np.array(params.whisker_ranges),
        math.ceil(max(params.whisker_ranges) / cell) + 2,
        out,
    )
    return out


_EPISODE_PARAMS = list(inspect.signature(_episodes.py_func).parameters)[1:]
_FIXED = {"episodes": {"watch": "False"}, "watched": {"record": "False", "watch": "True"}}
"""The generated wrappers and the `_episodes` flags each fixes: a constant, so the code of the
other mode is compiled out of it (the training kernel carries nothing of the watching one)."""


def _wrapper(name: str) -> str:
    """The source of wrapper `name`: `_episodes` with its fixed flags, the rest passed on."""
    fixed = _FIXED[name]
    params = ", ".join(p for p in _EPISODE_PARAMS if p not in fixed)
    constants = "".join(f"    {p} = {value}\n" for p, value in fixed.items())
    return (
        "@njit(cache=True, nogil=True)\n"
        f"def {name}({params}):\n"
        f"{constants}"
        f"    _episodes(kernel, {', '.join(_EPISODE_PARAMS)})\n"
    )


@lru_cache(maxsize=16)
def _episode_module(spec: NetworkSpec) -> Any:
    """`_episodes` bound to `network.spec_kernel(spec)` in wrappers `episodes` and `watched`,
    disk-cached per spec (each compiled on its first call).

    A closure over the controller's dispatcher cannot be cached by numba, so a tiny module is
    generated per spec that imports the controller's generated module and calls `_episodes`
    from `@njit(cache=True)` code (`network.cached_module`): compiled once per machine.
    """
    source = (
        f'"""Generated by evorobotics.sim for {spec!r}; do not edit."""\n\n'
        "from numba import njit\n\n"
        "from evorobotics.sim import _episodes\n"
        f"from {network.kernel_module(spec)} import kernel\n\n\n"
        + "\n\n".join(_wrapper(name) for name in _FIXED)
    )
    return network.cached_module("episodes", source, (network.__file__, __file__))


def _episode_kernel(spec: NetworkSpec) -> Callable[..., None]:
    """The episodes of `simulate` (`_episodes` without watching)."""
    return cast(Callable[..., None], _episode_module(spec).episodes)


_NOT_WATCHED = (np.zeros(0, dtype=np.uint8), np.zeros((0, 0)), np.zeros((0, 0)))
"""The watch outputs of a call of `simulate`: empty, never written."""


def kernel_cached(spec: NetworkSpec) -> bool:
    """Whether `simulate`'s kernel for `spec` is compiled already: loaded in this process, or
    in numba's disk cache for this machine's CPU. False: the first `simulate` compiles it
    (about 15 s, once per machine), which a command says rather than sit silent. Reads numba's
    cache index only (no machine code is loaded)."""
    kernel: Any = _episode_kernel(spec)  # a numba dispatcher
    if kernel.overloads:
        return True
    index = kernel._cache._cache_file._load_index()  # {} when absent or stale
    if not index:
        return False
    cpu = kernel.targetctx.codegen().magic_tuple()
    return any(key[1] == cpu for key in index)  # keys: (signature, cpu, code hashes)


def simulate(
    spec: NetworkSpec,
    weights: np.ndarray,
    maze: Maze,
    start_poses: np.ndarray,
    steps: int,
    params: World = DEFAULT_WORLD,
    gap: Gap | None = None,
    record: bool = False,
) -> SimResult:
    """Run every robot (row of `weights`, row of `start_poses`) for `steps` steps in one call.

    The canonical path: one compiled kernel, robots in tiles of `network.LANES`, each robot
    with the same operations in whichever lane, so its result is bit-identical whatever the
    batch it is part of.
    """
    w, starts, gap = _prepare(spec, weights, start_poses, steps, params, gap)
    batch = w.shape[0]
    final = np.empty((batch, 3))
    metrics = np.empty((3, batch))
    stuck = np.empty(batch, dtype=np.int64)
    cells = np.empty(batch, dtype=np.int64)
    rec_p, rec_w, rec_m = _NO_RECORD
    if record:
        rec_p = np.zeros((batch, steps + 1, 3))
        rec_w = np.zeros((batch, steps, N_WHISKERS), dtype=np.uint8)
        rec_m = np.zeros((batch, steps, 2))
    rows, cols = maze.solid.shape
    _episode_kernel(spec)(
        *_kernel_inputs(spec, w, maze, starts, steps, params, gap),
        record,
        (maze.cell_size, rows, cols),
        (0, 0.0, 0),
        final,
        metrics,
        stuck,
        cells,
        (rec_p, rec_w, rec_m),
        _NOT_WATCHED,
    )
    curve, net, max_off = metrics
    if record:
        return SimResult(final, curve, net, max_off, stuck, rec_p, rec_w, rec_m, cells)
    return SimResult(final, curve, net, max_off, stuck, cells=cells)


def _kernel_inputs(
    spec: NetworkSpec,
    w: np.ndarray,
    maze: Maze,
    starts: np.ndarray,
    steps: int,
    params: World,
    gap: Gap,
) -> tuple[Any, ...]:
    """`_episodes`' arguments from `weights` to `gains`, of `_prepare`d inputs."""
    world, wx, wy, ca, sa, _ = _world_arrays(params)
    ranges = gap.whisker_range
    if ranges.ndim < 3:  # fixed for the trial: the kernel's (B, S, W) with S = 1, a view
        ranges = ranges.reshape(w.shape[0], 1, -1)
    _, linear_output, n_state, n_scratch = _spec_sizes(spec)
    return (
        w,
        linear_output,
        n_state,
        n_scratch,
        _solid_u8(maze),
        maze.cell_size,
        starts,
        steps,
        world,
        wx,
        wy,
        ca,
        sa,
        _clearance_map(maze),
        params.stuck_after,
        ranges,
        gap.motor_gain,
    )


@dataclass(frozen=True)
class Watched(_Trials):
    """Per trial, what `simulate_watched` measured as the robots moved; no path is kept."""

    curve_length: np.ndarray
    net_offset: np.ndarray
    max_offset: np.ndarray
    stuck_step: np.ndarray
    """Eq 12's terms and the step the robot stuck on (-1: never), as `SimResult`'s."""
    confined: np.ndarray
    """(B,) bool: `window` consecutive steps, before sticking, inside a box of `diagonal`."""
    coverage: np.ndarray
    """(B,) int64: distinct squares of side `cell` (from the origin) the centre visited."""
    horizon_offset: np.ndarray
    """(B,) largest distance from the start by step `horizon`."""
    farthest: np.ndarray
    """(B,) largest distance from the start over the trial (`max_offset` but by `math.hypot`,
    which may round differently in the last bit)."""
    horizon_net: np.ndarray
    """(B,) distance from the start at step `horizon`."""
    moves: np.ndarray
    """(B, horizon): length of each of the first `horizon` moves, 0 for a blocked one."""


def simulate_watched(
    spec: NetworkSpec,
    weights: np.ndarray,
    maze: Maze,
    start_poses: np.ndarray,
    steps: int,
    params: World = DEFAULT_WORLD,
    gap: Gap | None = None,
    *,
    window: int,
    diagonal: float,
    cell: float,
    horizon: int,
) -> Watched:
    """`simulate`'s trials, measured as the robots move (confinement, coverage, offsets: see
    `Watched`) instead of recorded: the figures of a long trial at the kernel's speed.

    A stuck robot's trial ends when it sticks (nothing of it changes after), so its lane takes
    the next robot. Start positions must lie on the maze's grid (where any accepted pose lies):
    coverage squares are counted over it.
    """
    if not 1 <= horizon <= steps:
        raise ValueError(f"horizon must be in 1..steps ({steps}), got {horizon}")
    if window < 1 or not diagonal >= 0.0 or not cell > 0.0:
        raise ValueError(f"bad window {window}, diagonal {diagonal} or cell {cell}")
    w, starts, gap = _prepare(spec, weights, start_poses, steps, params, gap)
    inside = (starts[:, 0] >= 0) & (starts[:, 0] < maze.width)
    inside &= (starts[:, 1] >= 0) & (starts[:, 1] < maze.height)
    if not inside.all():
        raise ValueError("start positions must lie inside the maze")
    batch = w.shape[0]
    final = np.empty((batch, 3))
    metrics = np.empty((3, batch))
    stuck = np.empty(batch, dtype=np.int64)
    coverage = np.empty(batch, dtype=np.int64)
    confined = np.empty(batch, dtype=np.uint8)
    offsets = np.empty((3, batch))
    moves = np.zeros((batch, horizon))
    _episode_module(spec).watched(
        *_kernel_inputs(spec, w, maze, starts, steps, params, gap),
        (cell, math.floor(maze.height / cell) + 1, math.floor(maze.width / cell) + 1),
        (window, float(diagonal), horizon),
        final,
        metrics,
        stuck,
        coverage,
        _NO_RECORD,
        (confined, offsets, moves),
    )
    curve, net, max_off = metrics
    near, far, net_h = offsets
    return Watched(curve, net, max_off, stuck, confined == 1, coverage, near, far, net_h, moves)


@lru_cache(maxsize=16)
def _world_arrays(
    params: World,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The kernel's constants of `params` (world, wx, wy, cos, sin of whisker angles, reach).

    Cached per World so a call does not rebuild them; private, the kernel only reads them.
    """
    world = np.array(
        [
            params.dt,
            params.max_speed,
            params.wheel_base,
            params.body_length / 2,
            params.body_width / 2,
            params.half_diagonal,
        ]
    )
    angles = np.array(params.whisker_angle)
    reach = max(math.hypot(x, y) for x, y in zip(params.whisker_x, params.whisker_y, strict=True))
    return (
        world,
        np.array(params.whisker_x),
        np.array(params.whisker_y),
        np.cos(angles),
        np.sin(angles),
        reach + 1e-9,
    )


CLEARANCE_CELLS = 4
"""Clearance maps look this many cells around each cell (0.4 m at 0.1 m cells)."""
CLEARANCE_SUB = 4
"""Clearance maps split each maze cell into CLEARANCE_SUB x CLEARANCE_SUB squares: a bound
per square (25 mm at 0.1 m cells) is tight enough that a whisker or a body near a wall but
clear of it rarely needs the exact test."""


@lru_cache(maxsize=64)
def _clearance_map(maze: Maze) -> np.ndarray:
    """clear[b, a]: a lower bound on the distance from any point of square (b, a) to a wall.

    Squares of cell / CLEARANCE_SUB, rows b over y. Exact minimum over wall cells within
    CLEARANCE_CELLS of the square's cell (square-to-square gap), capped at the window's reach,
    minus 1e-9 for rounding. The kernel skips the exact whisker and body tests when it proves
    no wall is near: an early out that never changes a result.
    """
    k, sub = CLEARANCE_CELLS, CLEARANCE_SUB
    cell = maze.cell_size
    side = cell / sub
    padded = np.pad(maze.solid, k, constant_values=True)
    ny, nx = maze.solid.shape
    at = np.arange(sub)  # a square's place in its cell, on one axis
    clear = np.full((ny, sub, nx, sub), k * cell)
    for dj in range(-k, k + 1):
        gy = np.maximum(np.maximum(dj * cell - (at + 1) * side, at * side - (dj + 1) * cell), 0.0)
        for di in range(-k, k + 1):
            gx = np.maximum(
                np.maximum(di * cell - (at + 1) * side, at * side - (di + 1) * cell), 0.0
            )
            gap = np.hypot(gy[:, None], gx[None, :])  # (sub, sub): row b, column a
            wall = padded[k + dj : k + dj + ny, k + di : k + di + nx]
            clear = np.where(
                wall[:, None, :, None], np.minimum(clear, gap[None, :, None, :]), clear
            )
    return np.ascontiguousarray(clear.reshape(ny * sub, nx * sub) - 1e-9)


@lru_cache(maxsize=64)
def _solid_u8(maze: Maze) -> np.ndarray:
    """The kernel's copy of a maze: uint8 solid[j, i], C-contiguous (cached per Maze)."""
    return np.ascontiguousarray(maze.solid, dtype=np.uint8)


# ---------------------------------------------------------------- step-wise entry (evorobotics.gym)


@dataclass(frozen=True)
class Bodies:
    """N robots stepped one dt at a time (`step_bodies`), their arrays updated in place.

    The step-wise twin of a trial in `simulate`, for callers that choose every wheel command
    from outside (`evorobotics.gym`): the same compiled sensing and collision helpers and the
    same operations for the move (`_drive`), so a robot driven by the motor commands of a
    recorded trial retraces it bit for bit (tests/test_gym.py).
    """

    poses: np.ndarray
    """(N, 3) float64 x, y, heading."""
    gains: np.ndarray
    """(N, 2) float64 wheel gains (the reality gap; ones without)."""
    ranges: np.ndarray
    """(N, 5) float64 whisker trigger distances in m, read by the next sensing."""
    blocked: np.ndarray = field(init=False)
    """(N,) int64 consecutive blocked steps."""
    stuck: np.ndarray = field(init=False)
    """(N,) bool: stuck (`World.stuck_after` blocked steps in a row), immobile from then on."""
    travelled: np.ndarray = field(init=False)
    """(N,) float64 length of each robot's last accepted move (0 when blocked or stuck)."""
    whiskers: np.ndarray = field(init=False)
    """(N, 5) uint8 bits sensed at the current poses."""

    def __post_init__(self) -> None:
        n = self.poses.shape[0] if self.poses.ndim else 0
        if self.poses.shape != (n, 3) or self.gains.shape != (n, 2):
            raise ValueError(
                f"poses must be (N, 3) and gains (N, 2), got {self.poses.shape} and "
                f"{self.gains.shape}"
            )
        if self.ranges.shape != (n, N_WHISKERS):
            raise ValueError(f"ranges must be ({n}, {N_WHISKERS}), got {self.ranges.shape}")
        for name in ("poses", "gains", "ranges"):
            if (
                getattr(self, name).dtype != np.float64
                or not getattr(self, name).flags.c_contiguous
            ):
                raise ValueError(f"{name} must be C-contiguous float64")
        object.__setattr__(self, "blocked", np.zeros(n, dtype=np.int64))
        object.__setattr__(self, "stuck", np.zeros(n, dtype=np.bool_))
        object.__setattr__(self, "travelled", np.zeros(n))
        object.__setattr__(self, "whiskers", np.zeros((n, N_WHISKERS), dtype=np.uint8))


@njit(inline="always")
def _drive(
    x: float, y: float, th: float, left: float, right: float, world: np.ndarray
) -> tuple[float, float, float]:
    """The unobstructed move of one robot (`move`, in `_episodes`' operations and order):
    wheel commands times gains `left`, `right`; the new pose, heading wrapped."""
    dt = world[0]
    vl = left * world[1]
    vr = right * world[1]
    v = (vl + vr) * 0.5
    om = (vr - vl) / world[2]
    mid = th + om * (dt * 0.5)
    nth = th + om * dt
    cm, sm = _sincos(mid)
    return (
        x + v * dt * cm,
        y + v * dt * sm,
        nth - TWO_PI * math.floor((nth + math.pi) / TWO_PI),
    )


@njit(inline="always")
def _sense_one(
    solid: np.ndarray,
    cell: float,
    clear: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    ca: np.ndarray,
    sa: np.ndarray,
    reach: float,
    x: float,
    y: float,
    th: float,
    rq: np.ndarray,
    bits: np.ndarray,
) -> None:
    """The sensing of one robot into `bits` (5,): `_episodes`' bits, with scalar early outs
    (the centre far from walls, an attachment point further than its range from them)."""
    c, s = _sincos(th)
    r_max = 0.0
    for q in range(wx.shape[0]):
        r_max = max(r_max, rq[q])
    far = _clearance(clear, cell, x, y) > reach + r_max
    for q in range(wx.shape[0]):
        bits[q] = 0
        if far:
            continue
        px = x + c * wx[q] - s * wy[q]
        py = y + s * wx[q] + c * wy[q]
        if _clearance(clear, cell, px, py) > rq[q]:
            continue
        ux = c * ca[q] - s * sa[q]
        uy = s * ca[q] + c * sa[q]
        if _whisker(solid, cell, px, py, ux, uy, rq[q]):
            bits[q] = 1


@njit(cache=True, nogil=True)
def _step_rows(
    solid: np.ndarray,
    cell: float,
    clear: np.ndarray,
    world: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    ca: np.ndarray,
    sa: np.ndarray,
    reach: float,
    stuck_after: int,
    rows: np.ndarray,
    motors: np.ndarray,
    poses: np.ndarray,
    gains: np.ndarray,
    ranges: np.ndarray,
    blocked: np.ndarray,
    stuck: np.ndarray,
    travelled: np.ndarray,
    whiskers: np.ndarray,
    move_first: bool,
) -> None:
    """Robots `rows`: with `move_first`, act and collide on motors[r] as `_episodes` does;
    then sense at the (new) pose."""
    a = world[3]
    b = world[4]
    hd = world[5]
    for r in rows:
        x = poses[r, 0]
        y = poses[r, 1]
        th = poses[r, 2]
        travelled[r] = 0.0
        if move_first and not stuck[r]:
            nx, ny, nth = _drive(
                x, y, th, motors[r, 0] * gains[r, 0], motors[r, 1] * gains[r, 1], world
            )
            nc, ns = _sincos(nth)
            if _clearance(clear, cell, nx, ny) <= hd and _blocked(
                solid, cell, nx, ny, nc, ns, a, b, hd
            ):
                blocked[r] += 1
                if blocked[r] >= stuck_after:
                    stuck[r] = True
            else:
                blocked[r] = 0
                ddx = nx - x
                ddy = ny - y
                travelled[r] = math.sqrt(ddx * ddx + ddy * ddy)
                x = nx
                y = ny
                th = nth
                poses[r, 0] = x
                poses[r, 1] = y
                poses[r, 2] = th
        _sense_one(solid, cell, clear, wx, wy, ca, sa, reach, x, y, th, ranges[r], whiskers[r])


def _run_rows(
    maze: Maze, params: World, bodies: Bodies, rows: np.ndarray, motors: np.ndarray, move: bool
) -> None:
    world, wx, wy, ca, sa, reach = _world_arrays(params)
    _step_rows(
        _solid_u8(maze),
        maze.cell_size,
        _clearance_map(maze),
        world,
        wx,
        wy,
        ca,
        sa,
        reach,
        params.stuck_after,
        np.ascontiguousarray(rows, dtype=np.int64),
        motors,
        bodies.poses,
        bodies.gains,
        bodies.ranges,
        bodies.blocked,
        bodies.stuck,
        bodies.travelled,
        bodies.whiskers,
        move,
    )


def sense_bodies(maze: Maze, params: World, bodies: Bodies, rows: np.ndarray) -> None:
    """Sense `bodies.whiskers[rows]` at their poses (after placing robots)."""
    _run_rows(maze, params, bodies, rows, np.zeros((bodies.poses.shape[0], 2)), False)


def step_bodies(
    maze: Maze, params: World, bodies: Bodies, rows: np.ndarray, motors: np.ndarray
) -> None:
    """One dt of robots `rows` on wheel commands `motors` (N, 2) float64 in [-1, 1] (rows not
    stepped are ignored): act, collide and update `blocked`, `stuck`, `travelled`, then sense
    at the new poses. A stuck robot stays where it is (`simulate`'s rule)."""
    m = np.ascontiguousarray(motors, dtype=np.float64)
    if m.shape != (bodies.poses.shape[0], 2):
        raise ValueError(f"motors must be ({bodies.poses.shape[0]}, 2), got {m.shape}")
    _run_rows(maze, params, bodies, rows, m, True)
