"""drop the jobs table: jobs, leases and job results live in the server's memory

The same release stores GA states as raw-array frames (schemas.wire) instead of .npz; the
downgrade writes them back as .npz, so the release before can resume its runs.

Revision ID: 0004_drop_jobs
Revises: 0003_nullable_fitness
Create Date: 2026-11-22 07:00:00.000000
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
import sqlalchemy as sa
from alembic import op

from schemas.wire import MAGIC, decode_frame

revision: str = "0004_drop_jobs"
down_revision: str | None = "0003_nullable_fitness"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Rows left by servers that kept jobs here go with it: a restart re-asks the generation
    in flight from the last committed one anyway."""
    with op.batch_alter_table("jobs") as batch:
        batch.drop_index("ix_jobs_status_run")
    op.drop_table("jobs")


def downgrade() -> None:
    """The table of 0001, empty; GA states back to .npz."""
    conn = op.get_bind()
    states = conn.execute(sa.text("SELECT run_id, generation, state FROM generations")).all()
    for run_id, generation, state in states:
        if bytes(state).startswith(MAGIC):
            buffer = io.BytesIO()
            np.savez(buffer, allow_pickle=False, **decode_frame(bytes(state))[1])
            conn.execute(
                sa.text("UPDATE generations SET state = :s WHERE run_id = :r AND generation = :g"),
                {"s": buffer.getvalue(), "r": run_id, "g": generation},
            )
    op.create_table(
        "jobs",
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("generation", sa.Integer(), nullable=False),
        sa.Column("index", sa.Integer(), nullable=False),
        sa.Column("start", sa.Integer(), nullable=False),
        sa.Column("stop", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("worker", sa.String(length=128), nullable=True),
        sa.Column("deadline", sa.Float(), nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("genomes", sa.LargeBinary(), nullable=False),
        sa.Column("dtype", sa.String(length=16), nullable=False),
        sa.Column("shape", sa.String(length=64), nullable=False),
        sa.Column("fitness", sa.LargeBinary(), nullable=True),
        sa.Column("components", sa.LargeBinary(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["runs.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("run_id", "generation", "index"),
    )
    with op.batch_alter_table("jobs") as batch:
        batch.create_index("ix_jobs_status_run", ["status", "run_id"], unique=False)
