"""The figures read alone (`evorobotics.plots`, as `colony evolve`, the demo and the dashboard
draw them): fitness.png's legend beside the data, paths.png's marks explained in a legend
below the maze, network.png's inputs and outputs named as on the robot."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pytest

from evorobotics import plots
from evorobotics.evolution import GenerationSummary
from schemas.network import PRESETS, NetworkSpec
from schemas.run import RunConfig, ValidationScore
from tests.helpers import random_controller


@pytest.fixture
def closing() -> Iterator[list[Any]]:
    """Figures a test made, closed after it."""
    figures: list[Any] = []
    yield figures
    for fig in figures:
        plt.close(fig)


def extent(artist: Any, fig: Any) -> Any:
    return artist.get_window_extent(fig.canvas.get_renderer())


def test_fitness_legend_lies_beside_the_curves(closing: list[Any]) -> None:
    rng = np.random.default_rng(0)
    best = rng.normal(10.0, 5.0, 60)
    history = [
        GenerationSummary(g, float(b), float(b) - 10.0, float(b) - 50.0, 0)
        for g, b in enumerate(best)
    ]
    fig = plots.fitness_figure(history)
    closing.append(fig)
    fig.canvas.draw()
    (ax,) = fig.axes
    legend = ax.get_legend()
    assert legend is not None
    labels = [t.get_text() for t in legend.get_texts()]
    assert labels == ["best of generation", "mean", "worst", "best so far"]
    assert not extent(legend, fig).overlaps(extent(ax, fig))  # outside the data
    assert extent(legend, fig).x1 <= fig.bbox.x1  # and inside the picture
    so_far = next(line for line in ax.get_lines() if line.get_label() == "best so far")
    assert np.array_equal(so_far.get_ydata(), np.maximum.accumulate(best))
    assert ax.get_ylabel() == "training fitness (Eq 12)"


def test_paths_have_a_legend_for_path_start_and_end_and_strong_lines(
    closing: list[Any],
) -> None:
    config = RunConfig(network=PRESETS["reactive"], steps=20, seed=4)
    doc = random_controller(5)
    fig = plots.paths_figure(config, doc)
    closing.append(fig)
    fig.canvas.draw()
    (legend,) = fig.legends
    labels = [t.get_text() for t in legend.get_texts()]
    assert labels == ["path", "start", "body at the last step"]
    for ax in fig.axes:
        assert not extent(legend, fig).overlaps(extent(ax, fig))
        path = ax.get_lines()[0]
        assert path.get_linestyle() == "-" and path.get_linewidth() >= 1.5
    assert fig.get_suptitle().startswith(f"best of generation {doc.provenance.get('generation')}")


def test_the_champions_paths_say_champion(closing: list[Any]) -> None:
    config = RunConfig(network=PRESETS["reactive"], steps=20, seed=4)
    score = ValidationScore(
        poses=4, steps=50, seed=4, candidates=2, training_rank=1, score=1.0, stuck=0.25, roaming=0.5
    )
    doc = replace(random_controller(5), validation=score)
    fig = plots.paths_figure(config, doc)
    closing.append(fig)
    assert fig.get_suptitle().startswith("champion, ")
    assert "roaming 50%" in fig.get_suptitle()


def names_at(fig: Any) -> dict[str, tuple[float, float]]:
    """Every annotation's text -> where it points (data coordinates)."""
    (ax,) = fig.axes
    return {t.get_text(): tuple(t.xy) for t in ax.texts}


def test_network_names_whiskers_and_wheels_as_on_the_robot(closing: list[Any]) -> None:
    """Whisker 0 is the robot's leftmost (docs/serial-protocol.md): with the robot heading right
    across the figure its left is up, so the whiskers run top to bottom from the far left, and
    the left wheel is above the right."""
    spec = PRESETS["paper-best"]
    fig = plots.network_figure(spec, random_controller(1, spec).weights)
    closing.append(fig)
    at = names_at(fig)
    heights = [at[name][1] for name in plots.WHISKER_NAMES]
    assert heights == sorted(heights, reverse=True) and len(set(heights)) == 5
    assert {at[name][0] for name in plots.WHISKER_NAMES} == {0.0}  # the input column
    left, right = (at[name] for name in plots.WHEEL_NAMES)
    assert left[0] == right[0] == len(spec.sizes) - 1 and left[1] > right[1]
    assert plots.WHISKER_NAMES[0] == "whisker 0 (far left)"


def test_a_network_of_another_shape_gets_numbered_names(closing: list[Any]) -> None:
    spec = NetworkSpec(**{**PRESETS["reactive"].model_dump(), "inputs": 3, "outputs": 4})
    fig = plots.network_figure(spec, random_controller(1, spec).weights)
    closing.append(fig)
    at = names_at(fig)
    assert {f"input {k}" for k in range(3)} | {f"output {k}" for k in range(4)} <= set(at)
    assert not set(plots.WHISKER_NAMES) & set(at)
