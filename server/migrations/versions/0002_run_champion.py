"""runs.champion_sha256: the validated champion a completed run exports

A completed run's champion (its final population's best on the run's validation set) is
stored in `controllers`; the run names it, so `GET /api/runs/{id}/best` and pushes find it
after a restart without re-scoring. Runs completed before this revision get theirs when the
server next starts (`RunManager.recover`).

Revision ID: 0002_run_champion
Revises: 0001_initial
Create Date: 2026-12-02 08:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002_run_champion"
down_revision: str | None = "0001_initial"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("champion_sha256", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.drop_column("champion_sha256")
