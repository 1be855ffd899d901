"""Figures of a run, like the paper's: fitness curves (Fig 4), paths (Fig 6), networks (Figs 1, 5).

Matplotlib with the Agg backend only (no display); imported by the CLI when it writes files,
never by the science modules. PNGs carry no timestamp metadata, so reruns give equal bytes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.lines import Line2D

from evorobotics.document import ControllerDocument
from evorobotics.evaluate import unseen_paths
from evorobotics.evolution import GenerationSummary
from evorobotics.layout import layout
from evorobotics.maze import Maze, load_maze
from evorobotics.robustness import RobustnessMap
from evorobotics.sim import SimResult
from evorobotics.strategies import Archive
from schemas.network import NetworkSpec
from schemas.run import RunConfig

PNG_METADATA: dict[str, Any] = {"Software": None}
"""Drop matplotlib's version stamp so a PNG depends on its data only."""


def _save(fig: Any, path: Path) -> None:
    fig.savefig(path, dpi=110, metadata=PNG_METADATA)
    plt.close(fig)


def fitness_plot(history: Sequence[GenerationSummary], path: Path) -> None:
    """Best, mean and worst fitness against generation (Fig 4)."""
    if not history:
        raise ValueError("history is empty: nothing to plot")
    gens = np.array([h.generation for h in history])
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, style in (("best", "-"), ("mean", "--"), ("worst", ":")):
        ax.plot(gens, [getattr(h, name) for h in history], style, color="black", label=name)
    ax.set_xlabel("generation")
    ax.set_ylabel("fitness (Eq 12)")
    ax.set_title("training performance")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)


def _curve(p0: np.ndarray, p1: np.ndarray, bend: float, points: int = 16) -> np.ndarray:
    """A quadratic Bezier from p0 to p1 bulging by `bend` (a loop when p0 == p1)."""
    d = p1 - p0
    length = float(np.hypot(*d))
    if length == 0:  # self loop: a small circle to the right of the neuron
        angle = np.linspace(np.pi, -np.pi, points)
        radius = bend / 2
        return np.stack([p0[0] + radius * (1 + np.cos(angle)), p0[1] + radius * np.sin(angle)], 1)
    ctrl = (p0 + p1) / 2 + bend * np.array([-d[1], d[0]]) / length
    u = np.linspace(0, 1, points)[:, None]
    return np.asarray(((1 - u) ** 2) * p0 + 2 * (1 - u) * u * ctrl + (u**2) * p1)


KIND_COLOURS = {"feed-forward": "black", "delayed": "tab:blue", "recurrent": "tab:red"}


def network_plot(spec: NetworkSpec, weights: np.ndarray, path: Path) -> None:
    """Neurons in layer columns; line width proportional to |w| (Figs 1, 5).

    Feed-forward (t = 0, s = 0) lines are straight black, delayed ones (t >= 1) blue arcs
    bending more with the lag, recurrent ones (s >= 1) red arcs back from deeper layers or
    loops on the same layer. Biases are the grey node under each source column.
    """
    fig, ax = plt.subplots(figsize=(2.0 + 1.6 * len(spec.sizes), 5))
    draw_network(ax, spec, weights)
    ax.set_title(
        f"{layout(spec).n_weights} weights, T={spec.delays}, S={spec.recurrence} (width ~ |w|)",
        pad=22,
    )
    fig.tight_layout()
    _save(fig, path)


def draw_network(
    ax: Any, spec: NetworkSpec, weights: np.ndarray, scale: float | None = None
) -> None:
    """`network_plot`'s drawing on one axes; line width 0.1 + 3 |w| / `scale` (default max |w|),
    so panels given the same scale compare weight sizes."""
    lay = layout(spec)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (lay.n_weights,):
        raise ValueError(f"weights must have shape ({lay.n_weights},), got {w.shape}")
    sizes = spec.sizes

    def pos(layer: int, k: int) -> np.ndarray:
        n = sizes[layer]
        return np.array([float(layer), (k - (n - 1) / 2) / max(max(sizes) - 1, 1)])

    def bias_pos(layer: int) -> np.ndarray:
        return np.asarray(pos(layer, 0) - [0.0, 1.0 / max(max(sizes) - 1, 1) + 0.05])

    if scale is None:
        scale = float(np.max(np.abs(w))) or 1.0
    segments: list[np.ndarray] = []
    widths: list[float] = []
    colours: list[str] = []
    for b in lay.blocks:
        mat = lay.view(w, b)
        kind = "recurrent" if b.s > 0 else ("delayed" if b.t > 0 else "feed-forward")
        for n in range(b.rows):
            dst = pos(b.m, n)
            for i in range(b.cols):
                value = float(mat[n, i])
                if value == 0.0:
                    continue  # a zero weight is an absent connection
                src = bias_pos(b.src) if i == b.cols - 1 else pos(b.src, i)
                if kind == "feed-forward":
                    bend = 0.0
                elif kind == "delayed":
                    bend = 0.06 * b.t
                else:
                    bend = 0.15 + 0.05 * (b.s + b.t)
                segments.append(_curve(src, dst, bend))
                widths.append(0.1 + 3.0 * abs(value) / scale)
                colours.append(KIND_COLOURS[kind])
    ax.add_collection(LineCollection(segments, linewidths=widths, colors=colours, alpha=0.7))
    for layer, n in enumerate(sizes):
        xy = np.array([pos(layer, k) for k in range(n)])
        ax.scatter(xy[:, 0], xy[:, 1], s=120, color="white", edgecolors="black", zorder=3)
        if layer < len(sizes) - 1:
            bx, by = bias_pos(layer)
            ax.scatter([bx], [by], s=60, color="lightgrey", edgecolors="grey", zorder=3)
    names = ["inputs", *[f"hidden {k}" for k in range(1, len(spec.hidden) + 1)], "outputs"]
    ax.set_xticks(range(len(sizes)), names)
    ax.set_yticks([])
    ax.set_xlim(-0.4, len(sizes) - 0.4)
    for side in ("top", "right", "left"):
        ax.spines[side].set_visible(False)
    ax.legend(
        handles=[Line2D([], [], color=c, label=k) for k, c in KIND_COLOURS.items()],
        loc="upper center",
        bbox_to_anchor=(0.5, 1.08),
        ncol=3,
        frameon=False,
        fontsize=8,
    )


def _body_outline(pose: np.ndarray, length: float, width: float) -> np.ndarray:
    """The EvBot body rectangle (closed polygon) at pose (x, y, heading), centred on it."""
    x, y, th = (float(v) for v in pose)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1], [1, 1]], dtype=np.float64) * np.array(
        [length / 2, width / 2]
    )
    c, s = np.cos(th), np.sin(th)
    return np.asarray(corners @ np.array([[c, s], [-s, c]]) + [x, y])


def paths_plot(
    config: RunConfig,
    best: ControllerDocument,
    path: Path,
    paths: SimResult | None = None,
) -> None:
    """The best controller driving from UNSEEN start poses (Fig 6): `paths`, by default
    `evaluate.unseen_paths(config, best.weights)`, which a caller may simulate elsewhere (the
    drawing needs no simulator). Dotted path, start dot, final body outline."""
    if paths is None:
        paths = unseen_paths(config, best.weights)
    if paths.poses is None or len(paths.poses) == 0:
        raise ValueError("paths_plot needs recorded paths of at least one trial")
    maze = load_maze(config.maze)
    params = config.world
    rows, cols = maze.grid.shape
    extent = (0.0, cols * maze.cell_size, 0.0, rows * maze.cell_size)
    trials = len(paths.poses)
    fig, axes = plt.subplots(1, trials, figsize=(4.2 * trials, 4.4))
    for k, ax in enumerate(np.atleast_1d(axes)):
        poses = paths.poses[k]
        ax.imshow(maze.grid, cmap="Greys", extent=extent, origin="upper", vmin=0, vmax=1.4)
        ax.plot(poses[:, 0], poses[:, 1], ":", color="tab:blue", linewidth=1.2)
        ax.plot(poses[0, 0], poses[0, 1], "o", color="tab:green", markersize=4)
        outline = _body_outline(poses[-1], params.body_length, params.body_width)
        ax.plot(outline[:, 0], outline[:, 1], "-", color="tab:red", linewidth=1.5)
        stuck = " (stuck)" if paths.stuck[k] else ""
        ax.set_title(f"start {k + 1}: max offset {float(paths.max_offset[k]):.2f} m{stuck}")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_xticks([])
        ax.set_yticks([])
    score = "n/a" if best.fitness is None else f"{best.fitness:.3f}"
    steps = paths.poses.shape[1] - 1
    title = f"champion, {steps} steps from unseen start poses: training fitness {score}"
    if best.validation is not None:
        v = best.validation
        title += (
            f"\nvalidation ({v.poses} poses x {v.steps} steps): score {v.score:.3f}, "
            f"stuck {v.stuck:.0%}, roaming {v.roaming:.0%}"
        )
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)


def maze_plot(maze: Maze, path: Path) -> None:
    """The maze's walls in metres (`colony mazes --png`), titled with its name."""
    fig, ax = plt.subplots(figsize=(6, 6 * maze.height / maze.width + 0.5))
    extent = (0.0, maze.width, 0.0, maze.height)
    ax.imshow(maze.grid, cmap="Greys", extent=extent, origin="upper", vmin=0, vmax=1.4)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"maze {maze.name}")
    fig.tight_layout()
    _save(fig, path)


def archive_grid(config: RunConfig, archive: Archive) -> np.ndarray:
    """(cells, cells) best fitness per cell of the `strategy_settings.axes` plane, NaN where
    empty, row j the j-th band of the second axis: the pyribs grid itself for map-elites and
    cma-me, the novelty archive binned the same way."""
    n = config.strategy_settings.cells
    grid = np.full((n, n), -np.inf)
    idx = np.clip(np.floor(archive.descriptors * n).astype(np.int64), 0, n - 1)
    np.maximum.at(grid, (idx[:, 1], idx[:, 0]), np.nan_to_num(archive.fitness, nan=-np.inf))
    return np.where(np.isfinite(grid), grid, np.nan)


def archive_plot(config: RunConfig, archive: Archive, path: Path) -> None:
    """A heat map of the archive's best fitness per cell. On the default axes (final_x,
    final_y) it spans the maze's extent with the walls behind it; other axes span [0, 1]."""
    axes = config.strategy_settings.axes
    grid = archive_grid(config, archive)
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    extent = (0.0, 1.0, 0.0, 1.0)
    on_maze = axes == ("final_x", "final_y")
    if on_maze:
        maze = load_maze(config.maze)
        extent = (0.0, maze.width, 0.0, maze.height)
        ax.imshow(maze.grid, cmap="Greys", extent=extent, origin="upper", vmin=0, vmax=1.4)
    image = ax.imshow(grid, cmap="viridis", extent=extent, origin="lower", alpha=0.85)
    fig.colorbar(image, ax=ax, label="best fitness (Eq 12)")
    ax.set_xlabel("x (m)" if on_maze else axes[0])
    ax.set_ylabel("y (m)" if on_maze else axes[1])
    filled = int(np.isfinite(grid).sum())
    ax.set_title(f"{config.strategy} archive: {len(archive.fitness)} entries, {filled} cells")
    fig.tight_layout()
    _save(fig, path)


def robustness_plot(m: RobustnessMap, path: Path) -> None:
    """Roaming and stuck fractions over whisker range x wheel gain ratio, each cell labelled."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4))
    for ax, name, cmap in ((axes[0], "roaming", "viridis"), (axes[1], "stuck", "magma_r")):
        grid = np.array(getattr(m, name))
        image = ax.imshow(grid, cmap=cmap, vmin=0.0, vmax=1.0, origin="lower", aspect="auto")
        for (i, j), value in np.ndenumerate(grid):
            ink = "white" if (value < 0.5) == (name == "roaming") else "black"
            ax.text(j, i, f"{100 * value:.0f}", ha="center", va="center", fontsize=8, color=ink)
        ax.set_xticks(range(len(m.gain_ratios)), [f"{r:g}" for r in m.gain_ratios])
        ax.set_yticks(range(len(m.whisker_ranges)), [f"{1000 * r:g}" for r in m.whisker_ranges])
        ax.set_xlabel("wheel gain ratio, left / right")
        ax.set_ylabel("whisker range (mm)")
        ax.set_title(f"{name} (% of trials)")
        fig.colorbar(image, ax=ax, fraction=0.046)
    fig.suptitle(
        f"robustness map: {m.poses} unseen poses x {m.steps} steps per cell, "
        f"maze {m.maze!r}, seed {m.seed}"
    )
    fig.tight_layout()
    _save(fig, path)
