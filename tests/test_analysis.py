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
from evorobotics.analysis import PRE, analyze, classify_baseline
from evorobotics.document import ControllerDocument
from evorobotics.layout import layout
from evorobotics.seeds import Purpose, rng
from schemas.network import PRESETS, NetworkSpec

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
        touched = c.peak_deviation > a.settle_tol
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
    a = analyze(random_doc(spec, seed, scale), history=1, settle_tol=0.0, max_steps=12)
    assert a.baseline.kind == "fixed" and a.baseline.period == 1
    for c in a.contacts:
        assert c.settle_steps is not None and c.settle_steps <= bound, c
        # from the settling step on, the trace equals the reference bit for bit
        end = -a.trace_start + c.duration - 1
        tail = np.asarray(c.motors)[end + c.settle_steps :]
        ref = np.asarray(a.reference)[end + c.settle_steps : end + c.settle_steps + len(tail)]
        assert np.array_equal(tail, ref)
    assert a.max_settle is not None and a.max_settle <= bound


@FAST
@given(seed=st.integers(0, 2**31))
def test_delayed_net_gives_more_than_32_responses(seed: int) -> None:
    a = analyze(random_doc(PRESETS["paper-best"], seed), history=2, warmup=8)
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
    assert a.max_settle is None
    json.dumps(a.to_dict(), allow_nan=False)  # the dashboard can still show it


def test_integrating_recurrent_net_latches_on_a_new_steady_state() -> None:
    gains = (0.01, 0.02, 0.04, 0.08, 0.16)  # y sums distinct multiples of 0.01, unclipped
    a = analyze(loop_doc(1.0, gains=gains), history=2, max_steps=5, warmup=8)
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


@pytest.mark.parametrize(
    "kwargs",
    [{"history": 0}, {"history": 5}, {"settle_tol": -1.0}, {"max_steps": 0}, {"warmup": 3}],
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


def test_cli_writes_png_and_json(controller_file: tuple[Path, ControllerDocument]) -> None:
    path, doc = controller_file
    out = path.parent / "analysis"
    result = CliRunner().invoke(
        app,
        ["analyze", str(path), "--history", "2", "--max-steps", "8", "--json", "--out", str(out)],
    )
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)
    assert printed["sha256"] == doc.sha256 and printed["max_settle"] == 5
    assert json.loads((out / "analysis.json").read_text()) == printed
    assert (out / "responses.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = CliRunner().invoke(app, ["analyze", str(path), "--history", "1"])
    assert table.exit_code == 0 and "distinct motor responses" in table.stdout


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
    ):
        result = CliRunner().invoke(app, ["analyze", *args])
        assert result.exit_code == 2, (args, result.output)
