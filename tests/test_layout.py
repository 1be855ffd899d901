"""Network specs, presets and the chromosome layout (Eqs 4-6, 8)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from evorobotics.evaluate import trial_steps
from evorobotics.layout import layout
from schemas.network import PRESETS, NetworkSpec
from schemas.run import RunConfig


def test_preset_weight_counts() -> None:
    counts = {name: spec.weight_count for name, spec in PRESETS.items()}
    assert counts == {
        "paper-best": 222,
        "paper-largest": 7104,
        "reactive": 218,
        "recurrent-small": 232,
        "fig1b": 396,
    }


def test_blocks_follow_paper_order_m_t_s() -> None:
    lay = layout(PRESETS["recurrent-small"])
    keys = [(b.m, b.t, b.s) for b in lay.blocks]
    assert keys == sorted(keys)
    # layer 2 (outputs) has no s=2 source: layer 3 does not exist
    assert (2, 0, 2) not in keys
    assert lay.blocks[0].offset == 0
    for a, b in zip(lay.blocks, lay.blocks[1:], strict=False):
        assert b.offset == a.offset + a.size


@given(
    hidden=st.lists(st.integers(1, 6), max_size=3),
    delays=st.integers(0, 3),
    data=st.data(),
)
def test_layout_indices_cover_every_weight(
    hidden: list[int], delays: int, data: st.DataObject
) -> None:
    recurrence = data.draw(st.integers(0, len(hidden) + 1))
    spec = NetworkSpec(hidden=tuple(hidden), delays=delays, recurrence=recurrence)
    lay = layout(spec)
    assert lay.n_weights == spec.weight_count
    w = np.arange(lay.n_weights, dtype=np.float64)
    seen = np.concatenate([lay.view(w, b).ravel() for b in lay.blocks])
    assert np.array_equal(seen, w)
    for b in lay.blocks:
        sl = slice(b.offset, b.offset + b.size)
        assert set(lay.m[sl]) == {b.m} and set(lay.t[sl]) == {b.t} and set(lay.s[sl]) == {b.s}
        assert set(lay.block_size[sl]) == {b.rows * b.cols}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"hidden": (0,)}, "hidden layer 1 has 0 neurons"),
        ({"recurrence": 3, "hidden": (4,)}, r"recurrence depth 3 is outside 0\.\.2"),
        ({"delays": -1}, "greater than or equal to 0"),
        ({"hidden": (1024, 1024, 1024), "delays": 3}, "the limit is"),
    ],
)
def test_impossible_specs_are_rejected_with_a_message(
    kwargs: dict[str, object], message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        NetworkSpec.model_validate(kwargs)


def test_run_config_defaults_are_the_paper_experiment() -> None:
    cfg = RunConfig()
    assert (cfg.population, cfg.generations, cfg.trials) == (100, 350, 3)
    # the crossing rule: 2.4 m at 30 mm/step is 80 steps; three crossings by default
    assert cfg.steps is None and cfg.crossings == 3 and trial_steps(cfg) == 240
    assert trial_steps(RunConfig(crossings=1)) == 80 and trial_steps(RunConfig(steps=40)) == 40
    slow = RunConfig(crossings=1, world={"max_speed": 0.15})
    assert trial_steps(slow) == 160 and trial_steps(RunConfig(maze="arena", crossings=1)) == 67
    assert (cfg.fitness.k1, cfg.fitness.k2, cfg.fitness.k3, cfg.fitness.k4) == (0, 20, 20, 50)
    assert cfg.replacement_count == 25
    assert cfg.network_spec.weight_count == 222


def test_run_config_rejects_unknown_network_and_tiny_population() -> None:
    with pytest.raises(ValidationError, match="unknown network preset"):
        RunConfig(network="nope")
    with pytest.raises(ValidationError, match="too small"):
        RunConfig(population=4, ga={"replacement": 0.45})
