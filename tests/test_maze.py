"""Maze text format, shipped and generated mazes (paper section 2.2)."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evorobotics.errors import MazeError
from evorobotics.maze import (
    CORRIDOR_CELLS,
    DEFAULT_CELL,
    generate_maze,
    load_maze,
    maze_names,
    parse_maze,
)


def test_parse_with_comments_and_frame() -> None:
    maze = parse_maze("; a comment\n\n####\n#..#\n\n; another\n####\n", name="t")
    assert maze.name == "t"
    assert maze.cell_size == DEFAULT_CELL
    assert maze.grid.tolist() == [[True] * 4, [True, False, False, True], [True] * 4]
    assert maze.solid[0].all() and not maze.solid[1, 1]  # solid is south-up
    assert maze.width == pytest.approx(0.4)
    assert maze.height == pytest.approx(0.3)
    assert parse_maze(maze.text()).grid.tolist() == maze.grid.tolist()
    with pytest.raises(ValueError):
        maze.grid[0, 0] = False


@pytest.mark.parametrize(
    ("text", "line"),
    [("###\n#x#\n###\n", "line 2"), ("; c\n###\n#.#\n##\n", "line 4"), ("###\n# #\n", "line 2")],
)
def test_malformed_maze_names_the_line(text: str, line: str) -> None:
    with pytest.raises(MazeError, match=line):
        parse_maze(text)


def test_empty_or_solid_maze_rejected() -> None:
    with pytest.raises(MazeError, match="no grid lines"):
        parse_maze("; only a comment\n")
    with pytest.raises(MazeError, match="no free cell"):
        parse_maze("##\n##\n")
    with pytest.raises(ValueError, match="cell_size"):
        parse_maze("#.\n", cell_size=0.0)


def test_shipped_mazes_load_and_paper_is_two_to_three_metres() -> None:
    names = maze_names()
    assert {"paper", "arena", "corridor", "zigzag"} <= set(names)
    for name in names:
        maze = load_maze(name)
        assert maze.name == name
        assert not maze.grid.all()
    paper = load_maze("paper")
    assert 2.0 <= paper.width <= 3.0 and 2.0 <= paper.height <= 3.0
    assert load_maze("paper") is paper  # cached


def test_load_text_path_and_unknown(tmp_path: Path) -> None:
    text = "####\n#..#\n####\n"
    assert load_maze(text).grid.shape == (3, 4)
    path = tmp_path / "little.txt"
    path.write_text(text)
    maze = load_maze(str(path))
    assert maze.name == "little"
    with pytest.raises(MazeError, match="paper"):
        load_maze("no-such-maze")
    with pytest.raises(MazeError, match="gen:SIZE:SEED"):
        load_maze("gen:x")


def _free_components(grid: np.ndarray) -> int:
    """Number of 4-connected components of free cells."""
    seen = np.zeros_like(grid)
    count = 0
    for start in zip(*np.nonzero(~grid), strict=True):
        if seen[start]:
            continue
        count += 1
        stack = [start]
        seen[start] = True
        while stack:
            r, c = stack.pop()
            for nr, nc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                if not grid[nr, nc] and not seen[nr, nc]:
                    seen[nr, nc] = True
                    stack.append((nr, nc))
    return count


@settings(max_examples=20, deadline=None)
@given(size=st.integers(1, 8), seed=st.integers(0, 2**32))
def test_generated_maze_is_perfect(size: int, seed: int) -> None:
    maze = generate_maze(size, seed)
    grid = maze.grid
    pitch = CORRIDOR_CELLS + 1
    assert grid.shape == (size * pitch + 1, size * pitch + 1)
    assert grid[0].all() and grid[-1].all() and grid[:, 0].all() and grid[:, -1].all()
    assert _free_components(grid) == 1
    # a spanning tree of size^2 corridor cells opens exactly size^2 - 1 passages
    room_cells = size * size * CORRIDOR_CELLS**2
    passages = (int((~grid).sum()) - room_cells) // CORRIDOR_CELLS
    assert passages == size * size - 1
    assert np.array_equal(generate_maze(size, seed).grid, grid)
    assert load_maze(f"gen:{size}:{seed}").grid.tolist() == grid.tolist()


def test_generated_mazes_depend_on_seed() -> None:
    grids = {generate_maze(6, seed).grid.tobytes() for seed in range(5)}
    assert len(grids) == 5
    with pytest.raises(ValueError):
        generate_maze(0, 0)


def test_a_name_no_file_system_accepts_is_an_unknown_maze() -> None:
    with pytest.raises(MazeError, match="unknown maze"):
        load_maze("x" * 5000)
