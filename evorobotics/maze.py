"""Mazes (paper section 2.2): planar grids of solid/empty cells in a continuous plane.

Text format (one file per maze, `evorobotics/mazes/<name>.txt` for the shipped ones):
`#` is a wall cell, `.` a free cell; every grid line has the same length; lines starting with
`;` and blank lines are comments. Row 0 of the text is the north (top) edge.

World frame: metres, x east, y north, origin at the south-west corner of the grid; text row r,
column c is the square x in [c, c+1] * cell, y in [rows-1-r, rows-r] * cell. Everything outside
the grid counts as wall, so a robot can never leave a maze with an open border.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from evorobotics.errors import MazeError
from evorobotics.seeds import Purpose, rng

DEFAULT_CELL = 0.1
"""Side of one grid cell in metres: walls are one cell (100 mm) thick, like plywood maze walls."""

CORRIDOR_CELLS = 4
"""Width in cells of a generated maze's corridors: 0.4 m, wide enough for the EvBot to turn."""

GENERATED_PREFIX = "gen:"
"""`load_maze("gen:SIZE:SEED")` returns `generate_maze(SIZE, SEED)`, so a RunConfig can name one."""


@dataclass(frozen=True, eq=False)
class Maze:
    """A named grid; `grid[r, c]` is True for a wall, row 0 the north edge (read-only)."""

    name: str
    grid: np.ndarray
    cell_size: float

    @property
    def width(self) -> float:
        """Extent along x in metres."""
        return float(self.grid.shape[1] * self.cell_size)

    @property
    def height(self) -> float:
        """Extent along y in metres."""
        return float(self.grid.shape[0] * self.cell_size)

    @property
    def solid(self) -> np.ndarray:
        """The grid indexed [j, i] by y cell j = floor(y / cell) and x cell i (row 0 = south)."""
        return self.grid[::-1]

    def text(self) -> str:
        """The maze in the text format (round-trips through `parse_maze`)."""
        return "\n".join("".join("#" if v else "." for v in row) for row in self.grid) + "\n"


def _make(name: str, grid: np.ndarray, cell_size: float) -> Maze:
    if not (np.isfinite(cell_size) and cell_size > 0):
        raise ValueError(f"cell_size must be a positive number of metres, got {cell_size}")
    if grid.ndim != 2 or grid.size == 0:
        raise MazeError(f"maze {name!r}: the grid must be a non-empty 2-D array")
    if grid.all():
        raise MazeError(f"maze {name!r} has no free cell")
    frozen = np.ascontiguousarray(grid, dtype=bool).copy()
    frozen.flags.writeable = False
    return Maze(name, frozen, float(cell_size))


def parse_maze(text: str, name: str = "<text>", cell_size: float = DEFAULT_CELL) -> Maze:
    """Parse the text format; MazeError naming the first bad line (1-based)."""
    rows: list[list[bool]] = []
    width = -1
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.rstrip()
        if not line or line.startswith(";"):
            continue
        bad = sorted(set(line) - {"#", "."})
        if bad:
            raise MazeError(
                f"maze {name!r} line {lineno}: unexpected character(s) {bad!r}; "
                "use '#' for wall, '.' for free, ';' to start a comment line"
            )
        if width >= 0 and len(line) != width:
            raise MazeError(
                f"maze {name!r} line {lineno}: {len(line)} cells, expected {width} like the "
                "first grid line"
            )
        width = len(line)
        rows.append([ch == "#" for ch in line])
    if not rows:
        raise MazeError(f"maze {name!r} has no grid lines")
    return _make(name, np.array(rows, dtype=bool), cell_size)


def _shipped() -> dict[str, str]:
    folder = resources.files("evorobotics") / "mazes"
    return {
        entry.name.removesuffix(".txt"): entry.read_text(encoding="utf-8")
        for entry in folder.iterdir()
        if entry.name.endswith(".txt")
    }


def read_maze_file(path: Path) -> str:
    """A maze file's text; MazeError naming the file when it cannot be read or is not text."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise MazeError(f"maze file {path}: not a text maze file (binary or not UTF-8)") from None
    except OSError as exc:
        raise MazeError(f"maze file {path}: cannot read it: {exc.strerror}") from None


def is_shipped_or_generated(spec: str) -> bool:
    """A shipped name, `gen:...` or maze text: a maze that reads no file (what a server takes)."""
    return "\n" in spec or spec.startswith(GENERATED_PREFIX) or spec in _shipped()


def maze_names() -> list[str]:
    """Names of the shipped mazes, sorted."""
    return sorted(_shipped())


def maze_note(name: str) -> str:
    """What a shipped maze is for: its file's first comment without the name, e.g. "an empty
    2 m square room ..."; "" when it has none."""
    for line in _shipped()[name].splitlines():
        if line.startswith(";"):
            note = line.removeprefix(";").strip()
            return note.removeprefix(f'"{name}":').strip()
    return ""


@lru_cache(maxsize=64)
def load_maze(spec: str) -> Maze:
    """A shipped name, `gen:SIZE:SEED`, the maze text itself (contains a newline), or a path."""
    if "\n" in spec:
        return parse_maze(spec)
    shipped = _shipped()
    if spec in shipped:
        return parse_maze(shipped[spec], name=spec)
    if spec.startswith(GENERATED_PREFIX):
        parts = spec[len(GENERATED_PREFIX) :].split(":")
        if len(parts) != 2 or not all(p.isdigit() for p in parts):
            raise MazeError(f"generated maze {spec!r}: expected 'gen:SIZE:SEED', e.g. 'gen:5:0'")
        return generate_maze(int(parts[0]), int(parts[1]))
    path = Path(spec)
    try:
        is_file = path.is_file()
    except OSError:  # a name no file system accepts (too long, NUL): not a file
        is_file = False
    if is_file:
        return parse_maze(read_maze_file(path), name=path.stem)
    raise MazeError(
        f"unknown maze {spec!r}: not a shipped maze {sorted(shipped)}, not 'gen:SIZE:SEED', "
        "not a file, and not maze text"
    )


def generate_maze(size: int, seed: int) -> Maze:
    """A perfect maze (one route between any two corridors) of size x size corridor cells.

    Iterative depth-first backtracker over the corridor lattice, drawing from
    rng(seed, 0, Purpose.MAZE); corridors are CORRIDOR_CELLS wide with one-cell walls.
    """
    if not 1 <= size <= 64:
        raise ValueError(f"size must be in 1..64 corridors, got {size}")
    gen = rng(seed, 0, Purpose.MAZE)
    pitch = CORRIDOR_CELLS + 1
    n = size * pitch + 1
    grid = np.ones((n, n), dtype=bool)
    for r in range(size):
        for c in range(size):
            grid[r * pitch + 1 : (r + 1) * pitch, c * pitch + 1 : (c + 1) * pitch] = False
    visited = np.zeros((size, size), dtype=bool)
    stack = [(0, 0)]
    visited[0, 0] = True
    while stack:
        r, c = stack[-1]
        options = [
            (r + dr, c + dc)
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))
            if 0 <= r + dr < size and 0 <= c + dc < size and not visited[r + dr, c + dc]
        ]
        if not options:
            stack.pop()
            continue
        nr, nc = options[int(gen.integers(len(options)))]
        visited[nr, nc] = True
        if nr != r:  # knock down the horizontal wall between the two corridor cells
            wall_row = max(r, nr) * pitch
            grid[wall_row, c * pitch + 1 : (c + 1) * pitch] = False
        else:
            wall_col = max(c, nc) * pitch
            grid[r * pitch + 1 : (r + 1) * pitch, wall_col] = False
        stack.append((nr, nc))
    return _make(f"{GENERATED_PREFIX}{size}:{seed}", grid, DEFAULT_CELL)
