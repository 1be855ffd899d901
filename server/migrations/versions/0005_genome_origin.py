"""individuals.genome nullable, origin_generation and origin_rank: a copy points to its bytes

From generation 1 on, three quarters of a generation (Eq 11's elites, fill and k-2 elite) are
bit-for-bit copies of genomes already stored; servers from this release store their bytes
once and give each copy the (generation, rank) of the row of the same run that holds them.
Rows written before keep their bytes and a NULL origin, so they need no change.

Revision ID: 0005_genome_origin
Revises: 0004_drop_jobs
Create Date: 2026-11-22 10:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005_genome_origin"
down_revision: str | None = "0004_drop_jobs"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("individuals") as batch:
        batch.alter_column("genome", existing_type=sa.LargeBinary(), nullable=True)
        batch.add_column(sa.Column("origin_generation", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("origin_rank", sa.Integer(), nullable=True))


def downgrade() -> None:
    """Copies get their bytes back (one hop: an origin always holds them), as 0004 expects."""
    op.execute(
        "UPDATE individuals SET genome = (SELECT origin.genome FROM individuals AS origin"
        " WHERE origin.run_id = individuals.run_id"
        " AND origin.generation = individuals.origin_generation"
        " AND origin.rank = individuals.origin_rank)"
        " WHERE genome IS NULL"
    )
    with op.batch_alter_table("individuals") as batch:
        batch.drop_column("origin_rank")
        batch.drop_column("origin_generation")
        batch.alter_column("genome", existing_type=sa.LargeBinary(), nullable=False)
