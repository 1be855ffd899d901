"""The simulator's fused kernel as it was before robot tiles: one robot at a time, scalar network.

Kept only so bench/sim.py can compare it with the tiled kernel interleaved in one run. A copy
of evorobotics/sim.py's `_episodes` and geometry helpers and of evorobotics/network.py's
scalar kernel generator, bound together in generated modules like the real ones.
"""

from __future__ import annotations

import inspect
import math
import sys
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import cast

import numpy as np
from numba import njit

from evorobotics import network
from evorobotics.maze import Maze
from evorobotics.network import cached_module, kernel_plan, motor_one
from evorobotics.sim import (
    DEFAULT_WORLD,
    TWO_PI,
    SimResult,
    _prepare,
    _solid_u8,
    _world_arrays,
)
from schemas.network import NetworkSpec
from schemas.world import World

sys.path.insert(0, str(Path(__file__).parent))  # generated modules import this one by name


@njit(cache=True)
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


@njit(cache=True)
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


@njit(cache=True)
def _clearance(clear: np.ndarray, cell: float, x: float, y: float) -> float:
    """Lower bound on the distance from (x, y) to any wall (0 outside the grid), from a
    per-cell map (`_clearance_map`)."""
    i = math.floor(x / cell)
    j = math.floor(y / cell)
    if j < 0 or i < 0 or j >= clear.shape[0] or i >= clear.shape[1]:
        return 0.0
    return float(clear[j, i])


@cache
def _clearance_map(maze: Maze) -> np.ndarray:
    """clear[j, i]: a lower bound on the distance from any point of cell (j, i) to a wall
    (within 4 cells, square-to-square gap, capped, minus 1e-9)."""
    k = 4
    cell = maze.cell_size
    padded = np.pad(maze.solid, k, constant_values=True)
    ny, nx = maze.solid.shape
    clear = np.full((ny, nx), k * cell)
    for dj in range(-k, k + 1):
        for di in range(-k, k + 1):
            gap = math.hypot(max(abs(di) - 1, 0) * cell, max(abs(dj) - 1, 0) * cell)
            wall = padded[k + dj : k + dj + ny, k + di : k + di + nx]
            clear = np.where(wall, np.minimum(clear, gap), clear)
    return np.ascontiguousarray(clear - 1e-9)


@njit(cache=True)
def _slab1(lo: float, hi: float, p: float, u: float) -> tuple[float, float]:
    if abs(u) < 1e-12:
        if lo <= p and p <= hi:
            return -np.inf, np.inf
        return np.inf, -np.inf
    ta = (lo - p) / u
    tb = (hi - p) / u
    return min(ta, tb), max(ta, tb)


@njit(cache=True)
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


@njit(inline="always")
def _episodes(
    kernel: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], None],
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
    reach: float,
    stuck_after: int,
    ranges: np.ndarray,
    gains: np.ndarray,
    record: bool,
    final: np.ndarray,
    metrics: np.ndarray,
    stuck_out: np.ndarray,
    cells_out: np.ndarray,
    rec_poses: np.ndarray,
    rec_whiskers: np.ndarray,
    rec_motors: np.ndarray,
) -> None:
    """Every robot's whole trial: sense, think, act, collide, score (see the module docstring).

    `kernel` is the controller (`network.spec_kernel`). Inlined (numba IR) into the generated
    per-spec wrapper (`_episode_kernel`), where `kernel` is a module global: a dispatcher passed
    as a value would make the wrapper uncacheable. Not disk-cached itself; the wrapper's cache
    key covers this file, so an edit here is never served stale from disk.

    `ranges` (B, S, W) holds the whiskers' trigger distances: S = 1, fixed for the trial, or
    S = steps, one row per step; W = 1, shared by the five whiskers, or W = 5.

    `cells_out[r]` counts the grid cells robot r's centre visited: a bitmap over the maze in
    scratch, marked on every accepted move, whose marks are undone from `trail` after each robot
    (cheaper than clearing the whole map).
    """
    dt = world[0]
    vmax = world[1]
    base = world[2]
    a = world[3]
    b = world[4]
    hd = world[5]
    state = np.empty(n_state)
    scratch = np.empty(n_scratch)
    inputs = np.empty(wx.shape[0])
    out = np.empty(2)
    motor = np.empty(2)
    rq = np.empty(wx.shape[0])
    rows = solid.shape[0]
    cols = solid.shape[1]
    visited = np.zeros(rows * cols, dtype=np.uint8)
    trail = np.empty(steps + 1, dtype=np.int64)
    per_step = ranges.shape[1] != 1
    last = ranges.shape[2] - 1
    for r in range(weights.shape[0]):
        w = weights[r]
        state[:] = 0.0
        x0 = starts[r, 0]
        y0 = starts[r, 1]
        x = x0
        y = y0
        th = starts[r, 2]
        r_max = 0.0  # the longest whisker: the body's early out must cover all five
        if not per_step:
            for q in range(wx.shape[0]):
                rq[q] = ranges[r, 0, min(q, last)]
                r_max = max(r_max, rq[q])
        gl = gains[r, 0]
        gr = gains[r, 1]
        blocked = 0
        stuck = False
        stuck_at = -1
        curve = 0.0
        max_off = 0.0
        n_cells = _mark(visited, trail, 0, cols, rows, cell, x, y)
        if record:
            rec_poses[r, 0, 0] = x
            rec_poses[r, 0, 1] = y
            rec_poses[r, 0, 2] = th
        c = math.cos(th)
        s = math.sin(th)
        for k in range(steps):
            if stuck and not record:
                break  # frozen for good: its fitness terms are final
            if per_step:
                r_max = 0.0
                for q in range(wx.shape[0]):
                    rq[q] = ranges[r, k, min(q, last)]
                    r_max = max(r_max, rq[q])
            # early outs: no wall within reach of the centre / of an attachment point
            far = _clearance(clear, cell, x, y) > reach + r_max
            for q in range(wx.shape[0]):
                inputs[q] = 0.0
                if far:
                    continue
                px = x + c * wx[q] - s * wy[q]
                py = y + s * wx[q] + c * wy[q]
                if _clearance(clear, cell, px, py) > rq[q]:
                    continue
                ux = c * ca[q] - s * sa[q]
                uy = s * ca[q] + c * sa[q]
                if _whisker(solid, cell, px, py, ux, uy, rq[q]):
                    inputs[q] = 1.0
            kernel(w, state, inputs, out, scratch)
            motor_one(out, linear_output, motor)
            if not stuck:
                vl = motor[0] * gl * vmax
                vr = motor[1] * gr * vmax
                v = (vl + vr) * 0.5
                om = (vr - vl) / base
                mid = th + om * (dt * 0.5)
                nx = x + v * dt * math.cos(mid)
                ny = y + v * dt * math.sin(mid)
                nth = th + om * dt
                nth = nth - TWO_PI * math.floor((nth + math.pi) / TWO_PI)
                nc = math.cos(nth)
                ns = math.sin(nth)
                if _clearance(clear, cell, nx, ny) <= hd and _blocked(
                    solid, cell, nx, ny, nc, ns, a, b, hd
                ):
                    blocked += 1
                    if blocked >= stuck_after:
                        stuck = True
                        stuck_at = k + 1
                else:
                    blocked = 0
                    ddx = nx - x
                    ddy = ny - y
                    curve += math.sqrt(ddx * ddx + ddy * ddy)
                    x = nx
                    y = ny
                    th = nth
                    c = nc
                    s = ns
                    ox = x - x0
                    oy = y - y0
                    max_off = max(max_off, math.sqrt(ox * ox + oy * oy))
                    n_cells = _mark(visited, trail, n_cells, cols, rows, cell, x, y)
            if record:
                rec_poses[r, k + 1, 0] = x
                rec_poses[r, k + 1, 1] = y
                rec_poses[r, k + 1, 2] = th
                for q in range(wx.shape[0]):
                    rec_whiskers[r, k, q] = np.uint8(inputs[q])
                rec_motors[r, k, 0] = motor[0]
                rec_motors[r, k, 1] = motor[1]
        final[r, 0] = x
        final[r, 1] = y
        final[r, 2] = th
        ox = x - x0
        oy = y - y0
        metrics[r, 0] = curve
        metrics[r, 1] = math.sqrt(ox * ox + oy * oy)
        metrics[r, 2] = max_off
        stuck_out[r] = stuck_at
        cells_out[r] = n_cells
        for t in range(n_cells):
            visited[trail[t]] = 0


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


def _kernel_source(spec: NetworkSpec) -> str:
    """Module source of `kernel` (one step, `step_one` unrolled over blocks) and `batch` for `spec`.

    Per neuron the sums are those of `step_one` in the same order (u = 0, then per block in
    chromosome order acc = 0, += w x input by input, += bias, u += acc), so the results are
    bit-identical; only the loop nest changes (neuron outer, blocks inner, u in a register).
    """
    plan = kernel_plan(spec)
    sizes = [int(v) for v in plan.sizes]
    hist = [int(v) for v in plan.hist_off]
    act = [int(v) for v in plan.act_off]
    top = len(sizes) - 1
    lines = [
        f'"""Generated by evorobotics.network for {spec!r}; do not edit."""',
        "",
        "from numba import njit",
        "",
        "from evorobotics.network import _saturate, _sigmoid",
        "",
        "",
        "@njit(cache=True)",
        "def kernel(w, state, x, out, scratch):",
        f"    for i in range({sizes[0]}):",
        "        scratch[i] = x[i]",
    ]
    for m in range(1, top + 1):
        lines += [f"    for n in range({sizes[m]}):", "        u = 0.0"]
        for m_b, t, s, src, offset in plan.blocks.tolist():
            if m_b != m:
                continue
            n_src = sizes[src]
            if s == 0 and t == 0:
                x = f"scratch[{act[src]} + i]"
            elif s == 0:
                x = f"state[{hist[src] + (t - 1) * n_src} + i]"
            else:
                x = f"state[{hist[src] + t * n_src} + i]"
            lines += [
                f"        row = {offset} + n * {n_src + 1}",
                "        acc = 0.0",
                f"        for i in range({n_src}):",
                f"            acc += w[row + i] * {x}",
                f"        acc += w[row + {n_src}]",
                "        u += acc",
            ]
        linear = m == top and plan.linear_output == 1
        lines.append(
            f"        scratch[{act[m]} + n] = {'_saturate(u)' if linear else '_sigmoid(u)'}"
        )
    for j in range(top + 1):
        n_j, h = sizes[j], hist[j]
        for r in range(spec.delays, 0, -1):
            lines += [
                f"    for i in range({n_j}):",
                f"        state[{h + r * n_j} + i] = state[{h + (r - 1) * n_j} + i]",
            ]
        lines += [f"    for i in range({n_j}):", f"        state[{h} + i] = scratch[{act[j]} + i]"]
    lines += [
        f"    for i in range({sizes[top]}):",
        f"        out[i] = scratch[{act[top]} + i]",
    ]
    return "\n".join(lines) + "\n"


@cache
def _old_episodes(spec: NetworkSpec) -> Callable[..., None]:
    net = cached_module("oldnet", _kernel_source(spec), (network.__file__,))
    args = ", ".join(list(inspect.signature(_episodes.py_func).parameters)[1:])
    source = (
        "from numba import njit\n\n"
        "from _old_kernel import _episodes\n"
        f"from {net.__name__} import kernel\n\n\n"
        "@njit(cache=True, nogil=True)\n"
        f"def episodes({args}):\n"
        f"    _episodes(kernel, {args})\n"
    )
    return cast(Callable[..., None], cached_module("oldepisodes", source, (__file__,)).episodes)


def simulate_old(
    spec: NetworkSpec,
    weights: np.ndarray,
    maze: Maze,
    start_poses: np.ndarray,
    steps: int,
    params: World = DEFAULT_WORLD,
) -> SimResult:
    """`sim.simulate` without gap or recording, through the old kernel."""
    w, starts, gap = _prepare(spec, weights, start_poses, steps, params, None)
    batch = w.shape[0]
    world, wx, wy, ca, sa, reach = _world_arrays(params)
    final = np.empty((batch, 3))
    metrics = np.empty((batch, 3))
    stuck = np.empty(batch, dtype=np.int64)
    cells = np.empty(batch, dtype=np.int64)
    _old_episodes(spec)(
        w,
        kernel_plan(spec).linear_output,
        network.state_size(spec),
        network.scratch_size(spec),
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
        reach,
        params.stuck_after,
        gap.whisker_range.reshape(batch, 1, -1),
        gap.motor_gain,
        False,
        final,
        metrics,
        stuck,
        cells,
        np.zeros((0, 0, 3)),
        np.zeros((0, 0, 5), dtype=np.uint8),
        np.zeros((0, 0, 2)),
    )
    return SimResult(final, metrics[:, 0], metrics[:, 1], metrics[:, 2], stuck, cells=cells)
