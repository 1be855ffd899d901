"""Figures of `colony analyze`: step responses, Fig 5 before/after training, a Fig 7 close-up.

Matplotlib Agg only; like `plots.py`, PNGs carry no version metadata, so the same inputs give
the same bytes. `responses_plot` draws an `Analysis` (no simulation); the other two build a run
config around the controller (the maze given, "paper" by default) to draw a generation-0
controller or record a trial.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from evorobotics.analysis import Analysis, Encounter, wall_encounter
from evorobotics.document import ControllerDocument
from evorobotics.evaluate import record_path, start_poses
from evorobotics.evolution import RunLoop
from evorobotics.maze import load_maze
from evorobotics.plots import PNG_METADATA, _body_outline, draw_network
from evorobotics.sim import DEFAULT_WORLD, SimResult
from schemas.network import NetworkSpec
from schemas.run import RunConfig

WHEELS = (("left", "tab:blue"), ("right", "tab:red"))

ENCOUNTER_STARTS = 16
"""Start poses tried, in draw order, until one trial has a wall encounter with a backward move."""

ENCOUNTER_STEPS = 200
"""Steps recorded per tried start pose."""

MARGIN_M = 0.2
"""Maze shown around the close-up's path, metres."""


def _save(fig: Figure, path: Path) -> None:
    fig.savefig(path, dpi=110, metadata=PNG_METADATA)
    plt.close(fig)


def responses_plot(analysis: Analysis, path: Path) -> None:
    """One panel per input: left/right commands against step for a one-step contact at 0.

    Solid lines are the response, dashed the zero-input reference; the grey band is the contact
    step, the dotted vertical line where the response settled (title: steps, or "no"). The
    right axis gives the same commands as wheel travel in mm per step.
    """
    singles = [c for c in analysis.contacts if c.duration == 1 and len(c.inputs) == 1]
    if not singles:
        raise ValueError("analysis has no single-input contact to plot")
    reference = np.asarray(analysis.reference)
    ends = [c.settle_steps if c.settle_steps is not None else c.new_steady_steps for c in singles]
    last = len(singles[0].motors) - 1 + analysis.trace_start
    # zoom on the transient unless some panel never settles
    xmax = last if None in ends else min(last, max(10, *[e or 0 for e in ends]) + 5)
    fig, axes = plt.subplots(
        1, len(singles), figsize=(2.6 * len(singles) + 1.0, 3.4), sharey=True, squeeze=False
    )
    mm = analysis.full_speed_mm_per_step
    for ax, contact in zip(axes[0], singles, strict=True):
        motors = np.asarray(contact.motors)
        steps = np.arange(motors.shape[0]) + analysis.trace_start
        ax.axvspan(-0.5, 0.5, color="lightgrey", alpha=0.6, linewidth=0)
        for k, (name, colour) in enumerate(WHEELS[: motors.shape[1]]):
            ax.plot(steps, reference[: motors.shape[0], k], "--", color=colour, linewidth=0.8)
            ax.plot(steps, motors[:, k], ".-", color=colour, markersize=3, label=name)
        if contact.settle_steps is not None:
            ax.axvline(contact.settle_steps, color="black", linestyle=":", linewidth=0.8)
            verdict = f"settles in {contact.settle_steps}"
        elif contact.new_steady_steps is not None:
            verdict = f"new steady state in {contact.new_steady_steps}"
        else:
            verdict = "does not settle"
        ax.set_title(f"{contact.label}: {verdict}", fontsize=9)
        ax.set_xlabel("step after contact")
        ax.set_ylim(-1.05, 1.05)
        ax.set_xlim(analysis.trace_start - 0.5, xmax + 0.5)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("wheel command")
    axes[0][0].legend(loc="lower right", fontsize=8)
    right = axes[0][-1].secondary_yaxis("right", functions=(lambda c: c * mm, lambda m: m / mm))
    right.set_ylabel("wheel travel, mm per step")
    fig.suptitle(
        f"controller {analysis.sha256[:12]}: response to a one-step contact "
        f"(baseline {analysis.baseline.kind}, tolerance "
        f"{analysis.tolerance_mm_per_step:g} mm per step)",
        fontsize=10,
    )
    fig.tight_layout()
    _save(fig, path)


def initial_controller(spec: NetworkSpec, seed: int) -> np.ndarray:
    """Individual 0 of generation 0 of a run of `spec` with `seed`: the untrained network."""
    return np.array(RunLoop(RunConfig(seed=seed, network=spec)).ask()[0])


def network_before_after_plot(doc: ControllerDocument, seed: int, path: Path) -> None:
    """Fig 5: (a) `initial_controller(doc.spec, seed)`, (b) the controller `doc`.

    Both panels share one width scale (the largest |w| of the two), so thicker lines in (b)
    mean weights that grew during evolution.
    """
    before = initial_controller(doc.spec, seed)
    after = np.asarray(doc.weights, dtype=np.float64)
    scale = float(max(np.abs(before).max(), np.abs(after).max())) or 1.0
    width = 4.0 + 1.6 * len(doc.spec.sizes)  # as plots.network_figure: room for the names
    fig, axes = plt.subplots(1, 2, figsize=(2 * width, 5.2))
    score = "" if doc.fitness is None else f", training fitness {doc.fitness:.3g}"
    titles = (
        f"(a) before training: generation 0, individual 0 (seed {seed})",
        f"(b) after training: {doc.sha256[:12]}{score}",
    )
    for ax, weights, title in zip(axes, (before, after), titles, strict=True):
        draw_network(ax, doc.spec, weights, scale)
        ax.set_title(title, pad=22, fontsize=10)
    fig.suptitle(
        f"{after.size} weights, T={doc.spec.delays}, S={doc.spec.recurrence}; "
        f"line width ~ |w|, widest = {scale:.3g}",
        fontsize=10,
    )
    fig.tight_layout()
    _save(fig, path)


def _config(doc: ControllerDocument, maze: str, seed: int) -> RunConfig:
    """A run of the document's network in its world (default world if it names none)."""
    return RunConfig(seed=seed, network=doc.spec, maze=maze, world=doc.world or DEFAULT_WORLD)


def find_encounter(
    doc: ControllerDocument, maze: str, seed: int
) -> tuple[SimResult, Encounter, int]:
    """The first of ENCOUNTER_STARTS start poses (`start_poses(maze, seed, 0, ...)`) whose
    recorded trial has a wall encounter with a backward move, else the first with any encounter:
    (recording, encounter, start index). ValueError when no trial touches a wall."""
    config = _config(doc, maze, seed)
    starts = start_poses(load_maze(maze), seed, 0, ENCOUNTER_STARTS, config.world)
    fallback: tuple[SimResult, Encounter, int] | None = None
    for k, start in enumerate(starts):
        sim = record_path(config, doc.weights, start, ENCOUNTER_STEPS)
        if sim.whiskers is None or sim.motors is None:
            raise ValueError("record_path returned no whiskers or motors")
        found = wall_encounter(sim.whiskers[0], sim.motors[0])
        if found is None:
            continue
        if any(step >= found.onset for step in found.backward):
            return sim, found, k
        fallback = fallback or (sim, found, k)
    if fallback is None:
        raise ValueError(
            f"no wall encounter in {ENCOUNTER_STARTS} trials of {ENCOUNTER_STEPS} steps"
        )
    return fallback


def encounter_plot(doc: ControllerDocument, path: Path, maze: str = "paper", seed: int = 0) -> None:
    """Fig 7: the path around one wall encounter (`find_encounter`), each move's end marked.

    Orange: a backward move (mean wheel command < 0); light blue: a move while a whisker
    touches; black: a move after contact ended; grey: before the contact. Numbers are steps
    from the contact onset; the body is drawn at the onset (solid) and at the end (faint).
    """
    sim, enc, start_index = find_encounter(doc, maze, seed)
    world = doc.world or DEFAULT_WORLD
    if sim.poses is None or sim.whiskers is None:
        raise ValueError("record_path returned no poses or whiskers")
    the_maze = load_maze(maze)
    poses = sim.poses[0]
    touch = sim.whiskers[0].any(axis=1)
    back = set(enc.backward)
    shown = poses[enc.start : enc.stop + 1]
    fig, ax = plt.subplots(figsize=(6.4, 6.0))
    extent = (0.0, the_maze.width, 0.0, the_maze.height)
    ax.imshow(the_maze.grid, cmap="Greys", extent=extent, origin="upper", vmin=0, vmax=1.0)
    ax.plot(shown[:, 0], shown[:, 1], ":", color="black", linewidth=1.0)
    styles = {
        "before contact": ("o", "grey", 3),
        "whisker touching": ("o", "tab:cyan", 6),
        "after contact": ("o", "black", 5),
        "backward move": ("o", "tab:orange", 8),
    }
    used: set[str] = set()
    for k in range(enc.start, enc.stop):
        if k in back:
            kind = "backward move"
        elif touch[k]:
            kind = "whisker touching"
        elif k >= enc.release:
            kind = "after contact"
        else:
            kind = "before contact"
        marker, colour, size = styles[kind]
        x, y = poses[k + 1, :2]
        ax.plot(x, y, marker, color=colour, markersize=size, label=None if kind in used else kind)
        used.add(kind)
        if k >= enc.onset:
            ax.annotate(
                str(k - enc.onset), (x, y), xytext=(3, 3), textcoords="offset points", fontsize=7
            )
    for pose, alpha in ((poses[enc.onset], 1.0), (poses[enc.stop], 0.35)):
        outline = _body_outline(pose, world.body_length, world.body_width)
        ax.plot(outline[:, 0], outline[:, 1], "-", color="tab:red", linewidth=1.4, alpha=alpha)
    lo = shown[:, :2].min(axis=0) - MARGIN_M
    hi = shown[:, :2].max(axis=0) + MARGIN_M
    side = float((hi - lo).max())
    mid = (lo + hi) / 2
    ax.set_xlim(mid[0] - side / 2, mid[0] + side / 2)
    ax.set_ylim(mid[1] - side / 2, mid[1] + side / 2)
    ax.set_aspect("equal")
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_title(
        f"controller {doc.sha256[:12]}: wall encounter at step {enc.onset}\n"
        f"maze {the_maze.name!r}, start pose {start_index} of seed {seed}; "
        f"contact for {enc.release - enc.onset} step(s)",
        fontsize=10,
    )
    fig.tight_layout()
    _save(fig, path)
