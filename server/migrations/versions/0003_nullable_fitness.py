"""individuals.fitness nullable: a failed (NaN) evaluation is stored as NULL

Revision ID: 0003_nullable_fitness
Revises: 0002_robots
Create Date: 2026-11-22 04:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003_nullable_fitness"
down_revision: str | None = "0002_robots"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("individuals") as batch:
        batch.alter_column("fitness", existing_type=sa.Float(), nullable=True)


def downgrade() -> None:
    with op.batch_alter_table("individuals") as batch:
        batch.alter_column("fitness", existing_type=sa.Float(), nullable=False)
