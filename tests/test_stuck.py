"""Stuck detection from whisker and motor history (docs/stuck-detection.md)."""

from collections.abc import Sequence

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from robot_agent.stuck import StuckConfig, StuckDetector, StuckReason, detect

NONE = (False,) * 5
LEFT = (True, True, False, False, False)
CENTRE = (False, False, True, False, False)


def _run(
    detector: StuckDetector, steps: Sequence[tuple[tuple[bool, ...], tuple[float, float]]]
) -> list[StuckReason | None]:
    return [detector.update(w, m) for w, m in steps]


def test_driving_straight_in_open_space_is_not_stuck() -> None:
    assert set(_run(StuckDetector(), [(NONE, (0.8, 0.8))] * 500)) == {None}


def test_contact_held_while_driving() -> None:
    cfg = StuckConfig()
    out = _run(StuckDetector(cfg), [(CENTRE, (0.8, 0.8))] * cfg.contact_steps)
    assert out[-2] is None and out[-1] is StuckReason.CONTACT_HELD


def test_contact_without_driving_is_not_contact_held() -> None:
    cfg = StuckConfig(odometry_window=1000)
    assert set(_run(StuckDetector(cfg), [(CENTRE, (0.0, 0.0))] * 100)) == {None}


def test_a_wall_follower_touching_the_wall_again_and_again_is_not_stuck() -> None:
    """An evolved champion follows walls: the same whisker touches and leaves the wall every few
    steps while it drives on. That is roaming, not the paper's bumping in place."""
    follow = [(LEFT, (0.9, 0.6))] * 3 + [(NONE, (0.7, 0.9))] * 5
    assert set(_run(StuckDetector(), follow * 100)) == {None}


def test_spinning_in_place_goes_nowhere_but_a_wide_arc_does_not_fire() -> None:
    cfg = StuckConfig()
    spin = _run(StuckDetector(cfg), [(NONE, (-0.5, 0.5))] * 200)
    assert spin[cfg.odometry_window - 2] is None
    assert spin[cfg.odometry_window - 1] is StuckReason.GOING_NOWHERE
    arc = _run(StuckDetector(cfg), [(NONE, (0.8, 0.7))] * 200)  # radius ~ 0.8 m
    assert set(arc) == {None}


def test_reset_forgets_history() -> None:
    cfg = StuckConfig()
    detector = StuckDetector(cfg)
    _run(detector, [(CENTRE, (0.8, 0.8))] * (cfg.contact_steps - 1))
    detector.reset()
    assert detector.update(CENTRE, (0.8, 0.8)) is None


@given(st.integers(0, 2**32 - 1))
def test_detect_matches_streaming_and_never_fires_on_a_clear_straight_run(seed: int) -> None:
    gen = np.random.default_rng(seed)
    whiskers = gen.random((120, 5)) < 0.2
    motors = gen.uniform(-1, 1, (120, 2))
    detector = StuckDetector()
    assert detect(whiskers, motors) == [
        detector.update(tuple(bool(b) for b in w), m) for w, m in zip(whiskers, motors, strict=True)
    ]
    speed = gen.uniform(0.3, 1.0)
    clear = detect(np.zeros((120, 5), bool), np.full((120, 2), speed))
    assert set(clear) == {None}


@given(
    drift=st.floats(0.0, 0.2),
    gap_at=st.one_of(st.none(), st.integers(0, 39)),
)
def test_a_tracker_sees_a_robot_pinned_with_its_whiskers_clear(
    drift: float, gap_at: int | None
) -> None:
    """Whiskers clear, wheels forward: no sign from them. With tracked poses over 40 steps
    (41 poses) staying within 0.1 m it is stuck; a moving robot, or a window with a missing
    pose, is not (yet)."""
    config = StuckConfig()
    clear, forward = (False,) * 5, (0.8, 0.8)
    blind = StuckDetector(config)
    assert all(blind.update(clear, forward) is None for _ in range(200))
    detector = StuckDetector(config)
    seen = []
    for t in range(41):
        pose = None if t == gap_at else (1.0 + drift * t / 40, 2.0, 0.0)
        seen.append(detector.update(clear, forward, pose))
    pinned = drift < config.tracker_radius and gap_at is None
    assert seen[:-1] == [None] * 40
    assert seen[-1] == (StuckReason.TRACKED_STILL if pinned else None)


def test_arguments_are_checked() -> None:
    for kwargs in ({"contact_steps": 0}, {"odometry_radius": 0.0}, {"drive_min": 2.0}):
        with pytest.raises(ValueError):
            StuckConfig(**kwargs)
    with pytest.raises(ValueError):
        StuckDetector().update((True,) * 4, (0.0, 0.0))
    with pytest.raises(ValueError):
        detect(np.zeros((3, 5)), np.zeros((2, 2)))
