"""TensorBoard event files: `colony evolve --tensorboard DIR` and a server with
COLONY_TENSORBOARD_DIR write one scalar per generation (best, mean fitness) and the champion's
validation, read back here from the files' TFRecord framing with tensorboardX's Event protobuf.

Real CLI app, real uvicorn on a temporary SQLite file with in-process evaluation.
"""

from __future__ import annotations

import csv
import struct
from collections import defaultdict
from pathlib import Path

import httpx
import numpy as np
from tensorboardX.proto.event_pb2 import Event
from typer.testing import CliRunner

from colony.cli import app as cli
from evorobotics.document import ControllerDocument
from server.app import create_app
from server.core.settings import Settings
from tests.helpers import completed_run, serve

CONFIG = {
    "population": 8,
    "generations": 4,
    "steps": 10,
    "job_size": 4,
    "seed": 5,
    "validation": {"poses": 3, "steps": 50, "candidates": 4},
}


def scalars(directory: Path) -> dict[str, dict[int, float]]:
    """tag -> step -> value over every event file in `directory`."""
    found: dict[str, dict[int, float]] = defaultdict(dict)
    files = sorted(directory.glob("events.out.tfevents.*"))
    assert files, f"no event file in {directory}"
    for path in files:
        data = path.read_bytes()
        at = 0
        while at < len(data):  # length (u64), its crc (u32), the record, its crc (u32)
            (length,) = struct.unpack_from("<Q", data, at)
            event = Event.FromString(data[at + 12 : at + 12 + length])
            at += 12 + length + 4
            for value in event.summary.value:
                found[value.tag][event.step] = value.simple_value
    return found


def f32(x: float) -> float:
    """Event files hold scalars as float32."""
    return float(np.float32(x))


def test_colony_evolve_writes_a_scalar_per_generation_and_the_validation(tmp_path: Path) -> None:
    config = tmp_path / "config.json"
    config.write_text('{"validation": {"poses": 3, "steps": 50, "candidates": 4}, "job_size": 4}')
    out, board = tmp_path / "out", tmp_path / "board"
    flags = ["--population", "8", "--generations", "4", "--steps", "10", "--seed", "5"]
    result = CliRunner().invoke(
        cli,
        ["evolve", *flags, "--config", str(config), "--out", str(out), "--tensorboard", str(board)],
    )
    assert result.exit_code == 0, result.output
    with (out / "generations.csv").open() as f:
        rows = list(csv.DictReader(f))
    tags = scalars(board)
    assert tags["fitness/best"] == {int(r["generation"]): f32(float(r["best"])) for r in rows}
    assert tags["fitness/mean"] == {int(r["generation"]): f32(float(r["mean"])) for r in rows}
    validation = ControllerDocument.from_json((out / "best.json").read_text()).validation
    assert validation is not None
    assert tags["validation/score"] == {3: f32(validation.score)}
    assert tags["validation/roaming"] == {3: f32(validation.roaming)}
    assert tags["validation/stuck"] == {3: f32(validation.stuck)}


def test_server_writes_event_files_per_run_when_the_setting_is_set(tmp_path: Path) -> None:
    board = tmp_path / "board"
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        executors=1,
        zenoh=False,
        tensorboard_dir=board,
    )
    with serve(tmp_path, create_app(settings)) as served:
        runs = [completed_run(served.url, {**CONFIG, "seed": seed}) for seed in (1, 2)]
        with httpx.Client(base_url=served.url, timeout=30) as client:
            for run_id in runs:
                generations = client.get(f"/api/runs/{run_id}/generations").json()
                validation = client.get(f"/api/runs/{run_id}/best").json()["validation"]
                tags = scalars(board / f"run-{run_id}")
                assert tags["fitness/best"] == {
                    g["generation"]: f32(g["best"]) for g in generations
                }
                assert tags["fitness/mean"] == {
                    g["generation"]: f32(g["mean"]) for g in generations
                }
                assert tags["validation/score"] == {3: f32(validation["score"])}
                assert tags["validation/roaming"] == {3: f32(validation["roaming"])}
    assert sorted(p.name for p in board.iterdir()) == sorted(f"run-{r}" for r in runs)


def test_without_the_setting_the_server_writes_no_event_file(tmp_path: Path) -> None:
    with serve(tmp_path) as served:
        completed_run(served.url, CONFIG)
    assert not list(tmp_path.rglob("events.out.tfevents.*"))
