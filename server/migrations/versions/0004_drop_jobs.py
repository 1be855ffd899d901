"""drop the jobs table: jobs, leases and job results live in the server's memory

Revision ID: 0004_drop_jobs
Revises: 0003_nullable_fitness
Create Date: 2026-11-22 07:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

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
    """The table of 0001, empty."""
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
