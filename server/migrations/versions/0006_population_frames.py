"""generations.population: a generation's individuals as one frame; individuals dropped

One row per individual cost the server most of its recording at the paper's scale (350
generations of 100). Each generation now holds its individuals by rank in one frame (see
`server.population`): a copy points to the (generation, row of that generation's genomes)
holding its bytes instead of the (generation, rank) of a row. The upgrade converts every
stored generation; the downgrade writes the rows back, copies pointing to their origins as
0005 left them.

The frame is `schemas.wire`'s (magic "EVC1"), a versioned protocol format, so this revision
may use its encoder.

Revision ID: 0006_population_frames
Revises: 0005_genome_origin
Create Date: 2026-12-01 20:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sqlalchemy as sa
from alembic import op

from schemas.wire import decode_frame, encode_frame

revision: str = "0006_population_frames"
down_revision: str | None = "0005_genome_origin"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_I4 = np.dtype("<i4")
_F8 = np.dtype("<f8")


def _generations(conn: sa.Connection) -> list[tuple[int, int]]:
    """(run, generation) of every stored generation, runs and generations in order."""
    rows = conn.execute(
        sa.text("SELECT run_id, generation FROM generations ORDER BY run_id, generation")
    )
    return [(int(r), int(g)) for r, g in rows]


def upgrade() -> None:
    conn = op.get_bind()
    columns = {c["name"] for c in sa.inspect(conn).get_columns("generations")}
    if "population" not in columns:  # present if an earlier attempt stopped after adding it
        with op.batch_alter_table("generations") as batch:
            batch.add_column(sa.Column("population", sa.LargeBinary(), nullable=True))
    read = sa.text(
        'SELECT rank, "index", parent, fitness, components, genome, dtype, shape,'
        " origin_generation, origin_rank FROM individuals"
        " WHERE run_id = :run AND generation = :g ORDER BY rank"
    )
    write = sa.text(
        "UPDATE generations SET population = :population WHERE run_id = :run AND generation = :g"
    )
    slots: dict[tuple[int, int], tuple[int, int]] = {}
    """(generation, rank) of a row with bytes -> (generation, row of that generation's genomes),
    for the run being converted."""
    current = None
    for run, g in _generations(conn):
        if run != current:
            current, slots = run, {}
        rows = conn.execute(read, {"run": run, "g": g}).all()
        dtype, width = (rows[0].dtype, int(rows[0].shape)) if rows else ("<f8", 0)
        genome_at: list[tuple[int, int]] = []
        genomes: list[bytes] = []
        for row in rows:
            if row.genome is not None:
                slots[(g, row.rank)] = (g, len(genomes))
                genome_at.append((g, len(genomes)))
                genomes.append(bytes(row.genome))
                continue
            origin = slots.get((row.origin_generation, row.origin_rank))
            if origin is None:
                raise RuntimeError(
                    f"run {run} generation {g} rank {row.rank}: no genome bytes, and its origin "
                    f"(generation {row.origin_generation}, rank {row.origin_rank}) holds none; "
                    "the individuals table is damaged; repair it and upgrade again"
                )
            genome_at.append(origin)
        frame = encode_frame(
            {"kind": "population"},
            {
                "index": np.array([row.index for row in rows], dtype=_I4),
                "parent": np.array(
                    [-1 if row.parent is None else row.parent for row in rows], dtype=_I4
                ),
                "fitness": np.array(
                    [np.nan if row.fitness is None else row.fitness for row in rows], dtype=_F8
                ),
                "components": np.stack(
                    [np.frombuffer(bytes(row.components), _F8).reshape(-1, 4) for row in rows]
                )
                if rows
                else np.zeros((0, 0, 4), _F8),
                "genome_at": np.array(genome_at, dtype=_I4).reshape(-1, 2),
                "genomes": np.frombuffer(b"".join(genomes), np.dtype(dtype)).reshape(
                    len(genomes), width
                ),
            },
        )
        conn.execute(write, {"population": frame, "run": run, "g": g})
    op.drop_table("individuals")  # first: SQLite's batch below copies `generations` whole
    with op.batch_alter_table("generations") as batch:
        batch.alter_column("population", existing_type=sa.LargeBinary(), nullable=False)


def downgrade() -> None:
    op.create_table(
        "individuals",
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("generation", sa.Integer(), nullable=False),
        sa.Column("rank", sa.Integer(), nullable=False),
        sa.Column("index", sa.Integer(), nullable=False),
        sa.Column("parent", sa.Integer(), nullable=True),
        sa.Column("fitness", sa.Float(), nullable=True),
        sa.Column("components", sa.LargeBinary(), nullable=False),
        sa.Column("genome", sa.LargeBinary(), nullable=True),
        sa.Column("dtype", sa.String(length=16), nullable=False),
        sa.Column("shape", sa.String(length=64), nullable=False),
        sa.Column("origin_generation", sa.Integer(), nullable=True),
        sa.Column("origin_rank", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("run_id", "generation", "rank"),
    )
    conn = op.get_bind()
    read = sa.text("SELECT population FROM generations WHERE run_id = :run AND generation = :g")
    insert = sa.text(
        'INSERT INTO individuals (run_id, generation, rank, "index", parent, fitness,'
        " components, genome, dtype, shape, origin_generation, origin_rank) VALUES"
        " (:run, :g, :rank, :index, :parent, :fitness, :components, :genome, :dtype, :shape,"
        " :origin_generation, :origin_rank)"
    )
    ranks: dict[tuple[int, int], int] = {}
    """(generation, row of its genomes) -> the rank holding those bytes, for the current run."""
    current = None
    for run, g in _generations(conn):
        if run != current:
            current, ranks = run, {}
        _, arrays = decode_frame(bytes(conn.execute(read, {"run": run, "g": g}).scalar_one()))
        genomes = arrays["genomes"]
        rows = []
        for rank, (at_g, at_row) in enumerate(arrays["genome_at"].tolist()):
            own = at_g == g
            if own:
                ranks[(g, at_row)] = rank
            fitness = float(arrays["fitness"][rank])
            parent = int(arrays["parent"][rank])
            rows.append(
                {
                    "run": run,
                    "g": g,
                    "rank": rank,
                    "index": int(arrays["index"][rank]),
                    "parent": None if parent < 0 else parent,
                    "fitness": fitness if np.isfinite(fitness) else None,
                    "components": arrays["components"][rank].tobytes(),
                    "genome": genomes[at_row].tobytes() if own else None,
                    "dtype": genomes.dtype.str,
                    "shape": str(genomes.shape[1]),
                    "origin_generation": None if own else at_g,
                    "origin_rank": None if own else ranks[(at_g, at_row)],
                }
            )
        if rows:
            conn.execute(insert, rows)
    with op.batch_alter_table("generations") as batch:
        batch.drop_column("population")
