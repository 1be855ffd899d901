"""`colony evolve` end to end through the real CLI app, writing into tmp dirs."""

import csv
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import evorobotics
from colony.cli import app
from evorobotics.document import ControllerDocument
from schemas.network import PRESETS
from schemas.run import RunConfig

SMALL = ["--population", "12", "--generations", "4", "--steps", "20", "--seed", "3"]
FILES = ("best.json", "generations.csv", "config.json", "fitness.png", "paths.png", "network.png")

runner = CliRunner()


def _evolve(out: Path, *extra: str) -> str:
    result = runner.invoke(app, ["evolve", *SMALL, "--out", str(out), *extra])
    assert result.exit_code == 0, result.output
    return result.output


def test_writes_every_file_and_reruns_byte_identical(tmp_path: Path) -> None:
    out_a = _evolve(tmp_path / "a")
    _evolve(tmp_path / "b")
    for name in FILES:
        assert (tmp_path / "a" / name).stat().st_size > 0, name
    for name in ("best.json", "generations.csv", "config.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert "wall time" in out_a
    rows = list(csv.reader((tmp_path / "a" / "generations.csv").read_text().splitlines()))
    assert rows[0] == ["generation", "best", "mean", "worst"]
    assert [int(r[0]) for r in rows[1:]] == [0, 1, 2, 3]
    for r in rows[1:]:
        best, mean, worst = map(float, r[1:])
        assert worst <= mean <= best
    # plain log lines when stdout is not a terminal: each number says what it is
    so_far = max(float(r[1]) for r in rows[1:])
    assert (
        f"generation 4/4 training fitness: best {float(rows[-1][1]):.4f} "
        f"mean {float(rows[-1][2]):.4f} worst {float(rows[-1][3]):.4f}; "
        f"best so far {so_far:.4f}"
    ) in out_a

    config = RunConfig.model_validate_json((tmp_path / "a" / "config.json").read_text())
    assert (config.population, config.generations, config.steps, config.seed) == (12, 4, 20, 3)
    assert config.trials == 3 and config.network == "paper-best"  # paper defaults kept

    doc = ControllerDocument.from_json((tmp_path / "a" / "best.json").read_text())
    assert doc.spec == PRESETS["paper-best"]
    # best.json is the validated champion of the last generation: training fitness and rank
    assert doc.validation is not None and doc.provenance["rank"] == doc.validation.training_rank
    assert doc.fitness is not None and float(rows[-1][3]) <= doc.fitness <= float(rows[-1][1])
    assert doc.provenance["generation"] == 3 and doc.world == config.world
    assert doc.test is not None
    assert f"champion {doc.sha256[:12]}: training fitness {doc.fitness:.4f}" in out_a
    assert f"held-out test on {doc.test.poses} unseen poses" in out_a


def test_config_file_with_flag_override_and_files_for_maze_and_network(tmp_path: Path) -> None:
    shipped = Path(evorobotics.__file__).parent / "mazes" / "paper.txt"
    maze_file = tmp_path / "maze.txt"
    maze_file.write_text(shipped.read_text())
    net_file = tmp_path / "net.json"
    net_file.write_text(PRESETS["recurrent-small"].model_dump_json())
    cfg_file = tmp_path / "run.json"
    cfg_file.write_text(json.dumps({"population": 9, "generations": 2, "steps": 10, "seed": 5}))
    result = runner.invoke(
        app,
        [
            *("evolve", "--config", str(cfg_file), "--seed", "6", "--out", str(tmp_path / "o")),
            *("--maze", str(maze_file), "--network", str(net_file)),
        ],
    )
    assert result.exit_code == 0, result.output
    config = RunConfig.model_validate_json((tmp_path / "o" / "config.json").read_text())
    assert (config.population, config.generations, config.seed) == (9, 2, 6)
    assert config.maze == shipped.read_text()  # shipped as text: workers need no file
    assert config.network_spec == PRESETS["recurrent-small"]


def test_every_file_is_the_same_on_one_thread_and_two(tmp_path: Path) -> None:
    # the plots come from another process, the generations from two threads: same bytes
    assert "1 threads" in _evolve(tmp_path / "one", "--threads", "1")
    assert "2 threads" in _evolve(tmp_path / "two", "--threads", "2")
    for name in FILES:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--threads", "0"], "threads"),
        (["--population", "2"], "population"),
        (["--trials", "0"], "trials"),
        (["--network", "no-such-net"], "network"),
        (["--maze", "no-such-maze"], "maze"),
    ],
)
def test_bad_values_exit_nonzero_with_one_line_naming_the_field(
    tmp_path: Path, flags: list[str], named: str
) -> None:
    result = runner.invoke(app, ["evolve", *flags, "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert named in lines[0]
    assert not (tmp_path / "best.json").exists()


def test_bad_config_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"population": 100, "colour": "red"}')
    result = runner.invoke(app, ["evolve", "--config", str(bad), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "colour" in result.output


def test_a_plot_that_cannot_be_written_is_a_one_line_error(tmp_path: Path) -> None:
    (tmp_path / "fitness.png").mkdir()  # the plotter process cannot save over a directory
    result = runner.invoke(app, ["evolve", *SMALL, "--out", str(tmp_path)])
    assert result.exit_code == 1
    assert "Traceback" not in result.output
    assert "colony evolve: plot failed: fitness_plot: IsADirectoryError" in result.output
    assert (tmp_path / "network.png").stat().st_size > 0  # the other plots are drawn
