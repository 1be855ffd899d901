"""Controller analysis: settling after contacts, distinct responses, memory, `colony analyze`."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from colony.cli import app
from evorobotics.analysis import PRE, analyze, classify_baseline, mm_per_step, wall_encounter
from evorobotics.document import ControllerDocument
from evorobotics.layout import layout
from evorobotics.seeds import Purpose, rng
from evorobotics.thresholds import RESOLUTION_MM, TOLERANCE_MM
from schemas.network import PRESETS, NetworkSpec
from schemas.world import World

FAST = settings(max_examples=8, deadline=None)


def random_doc(spec: NetworkSpec, seed: int, scale: float = 1.0) -> ControllerDocument:
    w = rng(seed, 0, Purpose.INIT).normal(scale=scale, size=spec.weight_count)
    return ControllerDocument(spec, w)


def loop_doc(
    self_weight: float, bias: float = 0.0, gains: tuple[float, ...] = (0.5,) * 5
) -> ControllerDocument:
    """Linear outputs, no hidden layer, y(k) = self_weight * y(k-1) + bias + gains . whiskers."""
    spec = NetworkSpec(hidden=(), delays=0, recurrence=1, output_activation="linear")
    lay = layout(spec)
    w = np.zeros(lay.n_weights)
    for b in lay.blocks:
        view = lay.view(w, b)
        if b.s == 0:
            view[:, :-1] = gains
            view[:, -1] = bias
        else:
            view[:, :-1] = self_weight * np.eye(spec.outputs)
    return ControllerDocument(spec, w)


@FAST
@given(seed=st.integers(0, 2**31), scale=st.sampled_from([0.5, 2.0]))
def test_reactive_settles_in_one_step_with_at_most_32_responses(seed: int, scale: float) -> None:
    a = analyze(random_doc(PRESETS["reactive"], seed, scale), history=3, warmup=8)
    assert a.baseline.kind == "fixed"
    for c in a.contacts:
        touched = c.peak_deviation_mm_per_step > a.tolerance_mm_per_step
        assert c.settle_steps == (1 if touched else 0), c
    assert all(n <= 32 for n in a.distinct)
    assert a.distinct[0] == a.distinct[1] == a.distinct[2]
    assert a.memory <= 1 and a.reactive_bound == 32


FIR_SPECS = [
    PRESETS["paper-best"],
    NetworkSpec(hidden=(), delays=2, recurrence=0),
    NetworkSpec(hidden=(4, 3), delays=1, recurrence=0, output_activation="linear"),
]


@FAST
@given(
    which=st.sampled_from(range(len(FIR_SPECS))),
    seed=st.integers(0, 2**31),
    scale=st.sampled_from([0.3, 1.0, 4.0]),
)
def test_delayed_net_is_a_finite_impulse_response(which: int, seed: int, scale: float) -> None:
    """S = 0: a contact is forgotten exactly M*T steps later, so it settles within M*T + 1
    steps, even with zero tolerance."""
    spec = FIR_SPECS[which]
    bound = spec.layers * spec.delays + 1
    a = analyze(random_doc(spec, seed, scale), history=1, tolerance_mm=0.0, max_steps=12)
    assert a.baseline.kind == "fixed" and a.baseline.period == 1
    for c in a.contacts:
        assert c.settle_steps is not None and c.settle_steps <= bound, c
        # from the settling step on, the trace equals the reference bit for bit
        end = -a.trace_start + c.duration - 1
        tail = np.asarray(c.motors)[end + c.settle_steps :]
        ref = np.asarray(a.reference)[end + c.settle_steps : end + c.settle_steps + len(tail)]
        assert np.array_equal(tail, ref)
    assert a.max_settle_steps is not None and a.max_settle_steps <= bound


@FAST
@given(seed=st.integers(0, 2**31))
def test_delayed_net_gives_more_than_32_responses(seed: int) -> None:
    a = analyze(random_doc(PRESETS["paper-best"], seed), history=2, warmup=8, resolution_mm=1e-6)
    assert a.distinct[0] <= 32 < a.distinct[1] <= 1024
    assert a.memory == 2 and a.memory_saturated


def test_oscillating_recurrent_net_never_settles_and_reports_it() -> None:
    a = analyze(loop_doc(-1.0), history=2, max_steps=5, warmup=8)
    assert a.baseline.kind == "fixed"  # zero whiskers, zero bias: y stays 0
    for c in a.contacts:
        if c.duration % 2:
            assert c.settle_steps is None and c.new_steady_steps is None, c
        else:  # y = u, then -u + u = 0 at the last contact step: already back
            assert c.settle_steps == 0, c
    assert a.max_settle_steps is None
    json.dumps(a.to_dict(), allow_nan=False)  # the dashboard can still show it


def test_integrating_recurrent_net_latches_on_a_new_steady_state() -> None:
    gains = (0.01, 0.02, 0.04, 0.08, 0.16)  # y sums distinct multiples of 0.01, unclipped
    # cells of 0.067 mm per step = 0.00223 command: each multiple of 0.01 up to 0.63 in its own
    # cell and at least 1.5 % of a cell from its edges (float sums never straddle one)
    a = analyze(
        loop_doc(1.0, gains=gains),
        history=2,
        max_steps=5,
        warmup=8,
        tolerance_mm=0.03,
        resolution_mm=0.067,
    )
    for c in a.contacts:
        assert c.settle_steps is None
        assert c.new_steady_steps == 0  # from the last contact step on, y holds its new value
    assert a.distinct == (32, 63) and a.memory == 2 and a.memory_saturated


def test_limit_cycle_baseline_is_detected() -> None:
    a = analyze(loop_doc(-1.0, bias=0.5), history=1, max_steps=5, warmup=16)
    assert a.baseline.kind == "cycle" and a.baseline.period == 2
    assert sorted(m[0] for m in a.baseline.motors) == [0.0, 0.5]


@given(
    period=st.integers(1, 6),
    tol=st.sampled_from([0.0, 1e-3]),
    seed=st.integers(0, 2**31),
)
def test_classify_baseline_finds_the_smallest_period(period: int, tol: float, seed: int) -> None:
    cycle = rng(seed, 0, Purpose.INIT).uniform(-1, 1, size=(period, 2))
    trace = np.tile(cycle, (48 // period + 1, 1))[:48]
    b = classify_baseline(trace, tol)
    # a random cycle has no shorter sub-period, so the smallest period is the period
    assert (b.kind, b.period) == (("fixed" if period == 1 else "cycle"), period)
    drifting = np.linspace(0, 1, 48)[:, None] * np.ones((1, 2))
    assert classify_baseline(drifting, 1e-3).kind == "unsteady"


def test_trace_geometry_and_determinism() -> None:
    doc = random_doc(PRESETS["paper-best"], 3)
    a = analyze(doc, history=1, max_steps=7, warmup=8)
    assert a.to_dict() == analyze(doc, history=1, max_steps=7, warmup=8).to_dict()
    assert a.trace_start == -PRE and len(a.contacts) == 3 * 6
    for c in a.contacts:
        assert len(c.motors) == PRE + c.duration + a.max_steps
        assert np.array_equal(np.asarray(c.motors)[:PRE], np.asarray(a.reference)[:PRE])
    assert {c.label for c in a.contacts} == {*(f"whisker {i}" for i in range(5)), "all"}


def test_default_tolerances_are_wheel_travel_of_the_default_world() -> None:
    assert mm_per_step() == pytest.approx(30.0)  # 0.3 m/s * 0.1 s
    a = analyze(random_doc(PRESETS["reactive"], 0), history=1, warmup=8)
    assert (a.tolerance_mm_per_step, a.resolution_mm_per_step) == (TOLERANCE_MM, RESOLUTION_MM)
    assert a.full_speed_mm_per_step == pytest.approx(30.0)


@pytest.mark.parametrize(
    ("tolerance_mm", "max_speed", "settle"),
    # deviation after the last contact step j: 0.5 * 0.5^j commands = 15 * 0.5^j mm per step
    [(2.0, 0.3, 3), (4.0, 0.3, 2), (1.0, 0.3, 4), (16.0, 0.3, 0), (2.0, 0.6, 4)],
)
def test_decaying_loop_settles_when_its_travel_is_within_tolerance(
    tolerance_mm: float, max_speed: float, settle: int
) -> None:
    """y(k) = 0.5 y(k-1) + 0.5 whiskers: a one-step contact leaves 0.5^(j+1) of a command j
    steps later, so the settling time follows from the tolerance in mm (and the world's speed)."""
    doc = loop_doc(0.5)
    world = World(max_speed=max_speed)
    a = analyze(doc, history=1, max_steps=10, warmup=8, tolerance_mm=tolerance_mm, world=world)
    singles = [c for c in a.contacts if c.duration == 1 and len(c.inputs) == 1]
    assert {c.settle_steps for c in singles} == {settle}
    assert a.max_settle_steps == settle
    assert singles[0].peak_deviation_mm_per_step == pytest.approx(1e3 * max_speed * 0.1 * 0.5)
    # a document that names its world is measured in it by default
    evolved_in = ControllerDocument(doc.spec, doc.weights, world=world)
    b = analyze(evolved_in, history=1, max_steps=10, warmup=8, tolerance_mm=tolerance_mm)
    assert b.max_settle_steps == settle


@FAST
@given(
    which=st.sampled_from(range(len(FIR_SPECS))),
    seed=st.integers(0, 2**31),
    tols=st.lists(st.floats(0.0, 40.0), min_size=2, max_size=2).map(sorted),
)
def test_a_tighter_tolerance_never_settles_sooner(which: int, seed: int, tols: list[float]) -> None:
    doc = random_doc(FIR_SPECS[which], seed)
    tight, loose = (analyze(doc, history=1, max_steps=8, tolerance_mm=t) for t in tols)
    for t, lo in zip(tight.contacts, loose.contacts, strict=True):
        assert t.settle_steps is not None and lo.settle_steps is not None  # FIR: always settles
        assert t.settle_steps >= lo.settle_steps, (t.label, t.duration, tols)
    assert (tight.max_settle_steps or 0) >= (loose.max_settle_steps or 0)


@FAST
@given(
    spec=st.sampled_from([PRESETS["paper-best"], PRESETS["recurrent-small"]]),
    seed=st.integers(0, 2**31),
    resolution_mm=st.floats(1e-3, 10.0),
    factor=st.integers(2, 7),
)
def test_coarser_cells_never_count_more_responses(
    spec: NetworkSpec, seed: int, resolution_mm: float, factor: int
) -> None:
    """A cell `factor` times larger is a union of finer cells: counts and memory can only fall."""
    doc = random_doc(spec, seed)
    fine = analyze(doc, history=2, max_steps=4, warmup=8, resolution_mm=resolution_mm)
    coarse = analyze(doc, history=2, max_steps=4, warmup=8, resolution_mm=factor * resolution_mm)
    assert all(c <= f for c, f in zip(coarse.distinct, fine.distinct, strict=True))
    assert coarse.memory <= fine.memory
    # wheel travel spans 60 mm per step (-30..30): a 100 mm cell leaves at most 2 per wheel
    huge = analyze(doc, history=2, max_steps=4, warmup=8, resolution_mm=100.0)
    assert all(n <= 4 for n in huge.distinct)


def test_wall_encounter_prefers_one_with_a_backward_move() -> None:
    touch = np.zeros((30, 5), dtype=np.uint8)
    motors = np.full((30, 2), 0.5)
    touch[5:7, 2] = 1  # first encounter: onset 5, forward only
    touch[15:18, 0] = 1  # second: onset 15, reverses at 16
    motors[16] = (-0.6, -0.2)
    motors[3] = (-1.0, 0.0)  # a backward move before the first onset does not count
    enc = wall_encounter(touch, motors, lead=3, after=4)
    assert enc is not None
    assert (enc.start, enc.onset, enc.release, enc.stop, enc.backward) == (12, 15, 18, 22, (16,))
    motors[16] = 0.5
    first = wall_encounter(touch, motors, lead=3, after=4)
    assert first is not None and (first.onset, first.release, first.backward) == (5, 7, (3,))
    assert wall_encounter(np.zeros((30, 5)), motors) is None
    always = np.ones((30, 5))  # touching from the first step: no onset after a free step
    assert wall_encounter(always, motors) is None
    with pytest.raises(ValueError):
        wall_encounter(touch, motors[:-1])


@pytest.mark.parametrize(
    "kwargs",
    [
        {"history": 0},
        {"history": 5},
        {"tolerance_mm": -1.0},
        {"tolerance_mm": float("nan")},
        {"resolution_mm": 0.0},
        {"resolution_mm": float("inf")},
        {"max_steps": 0},
        {"warmup": 3},
    ],
)
def test_bad_arguments_raise_value_error(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        analyze(random_doc(PRESETS["reactive"], 0), **kwargs)  # type: ignore[arg-type]


@pytest.fixture
def controller_file(tmp_path: Path) -> tuple[Path, ControllerDocument]:
    doc = random_doc(PRESETS["paper-best"], 11)
    path = tmp_path / "best.json"
    path.write_text(doc.to_json())
    return path, doc


def test_cli_writes_json_and_deterministic_figures(
    controller_file: tuple[Path, ControllerDocument],
) -> None:
    path, doc = controller_file
    args = ["analyze", str(path), "--history", "2", "--max-steps", "8", "--json"]
    first = CliRunner().invoke(app, [*args, "--out", str(path.parent / "a")])
    assert first.exit_code == 0, first.output
    printed = json.loads(first.stdout)
    assert printed == analyze(doc, history=2, max_steps=8).to_dict()
    assert printed["tolerance_mm_per_step"] == TOLERANCE_MM
    assert printed["resolution_mm_per_step"] == RESOLUTION_MM
    assert json.loads((path.parent / "a" / "analysis.json").read_text()) == printed
    again = CliRunner().invoke(app, [*args, "--out", str(path.parent / "b")])
    assert again.exit_code == 0, again.output
    for name in ("responses.png", "network.png", "encounter.png"):
        png = (path.parent / "a" / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n", name
        assert png == (path.parent / "b" / name).read_bytes(), name
    table = CliRunner().invoke(app, ["analyze", str(path), "--history", "1"])
    assert table.exit_code == 0 and "distinct motor responses" in table.stdout
    assert "mm per step" in table.stdout


def test_cli_skips_the_encounter_of_a_robot_that_never_moves(tmp_path: Path) -> None:
    """Zero weights: sigmoid outputs 0.5, wheel commands 0, so no whisker ever touches."""
    spec = PRESETS["paper-best"]
    path = tmp_path / "still.json"
    path.write_text(ControllerDocument(spec, np.zeros(spec.weight_count)).to_json())
    result = CliRunner().invoke(
        app, ["analyze", str(path), "--history", "1", "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 0, result.output
    assert "no encounter.png: no wall encounter" in result.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "analysis.json",
        "network.png",
        "responses.png",
    ]
    bad = CliRunner().invoke(app, ["analyze", str(path), "--out", str(tmp_path), "--maze", "x"])
    assert bad.exit_code == 2 and "--maze" in bad.output
    negative = CliRunner().invoke(
        app, ["analyze", str(path), "--out", str(tmp_path), "--seed", "-1"]
    )
    assert negative.exit_code == 2


@pytest.fixture
def doc_server(
    controller_file: tuple[Path, ControllerDocument],
) -> Iterator[tuple[str, ControllerDocument]]:
    """A real HTTP server on loopback answering the two REST paths `colony analyze` uses."""
    _, doc = controller_file
    routes = {"/api/runs/7/best": doc.to_json(), f"/api/controllers/{doc.sha256}": doc.to_json()}

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = routes.get(self.path)
            self.send_response(200 if body else 404)
            self.end_headers()
            self.wfile.write((body or '{"detail":"not found"}').encode())

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_port}", doc
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=10)


def test_cli_fetches_from_a_server(doc_server: tuple[str, ControllerDocument]) -> None:
    url, doc = doc_server
    base = ["analyze", "--server", url, "--history", "1", "--max-steps", "6", "--json"]
    for extra in (["--run", "7"], ["--sha", doc.sha256]):
        result = CliRunner().invoke(app, [*base, *extra])
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout)["sha256"] == doc.sha256
    missing = CliRunner().invoke(app, [*base, "--run", "8"])
    assert missing.exit_code == 2 and "404" in missing.output


def test_cli_rejects_bad_sources(controller_file: tuple[Path, ControllerDocument]) -> None:
    path, _ = controller_file
    for args in (
        [],
        [str(path), "--server", "http://127.0.0.1:9", "--run", "1"],
        ["--server", "http://127.0.0.1:9"],
        [str(path.parent / "nope.json")],
        [str(path), "--tolerance-mm", "-1"],
        [str(path), "--resolution-mm", "0"],
    ):
        result = CliRunner().invoke(app, ["analyze", *args])
        assert result.exit_code == 2, (args, result.output)
