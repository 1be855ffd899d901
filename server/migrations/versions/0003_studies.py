"""studies, and runs' name, tags, study and condition

A study is conditions x seeds ordinary runs of one base config (docs/studies.md); each of its
runs names it (`runs.study_id`) and its condition. Any run may carry a name and tags (a JSON
list; existing runs get none).

Revision ID: 0003_studies
Revises: 0002_run_champion
Create Date: 2026-12-02 13:15:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003_studies"
down_revision: str | None = "0002_run_champion"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "studies",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("spec", sa.Text(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("name", sa.String(length=128), nullable=True))
        batch_op.add_column(sa.Column("tags", sa.Text(), server_default="[]", nullable=False))
        batch_op.add_column(sa.Column("study_id", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("condition", sa.String(length=64), nullable=True))
        batch_op.create_index(batch_op.f("ix_runs_study_id"), ["study_id"], unique=False)
        batch_op.create_foreign_key(
            "fk_runs_study_id_studies", "studies", ["study_id"], ["id"], ondelete="SET NULL"
        )


def downgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.drop_constraint("fk_runs_study_id_studies", type_="foreignkey")
        batch_op.drop_index(batch_op.f("ix_runs_study_id"))
        batch_op.drop_column("condition")
        batch_op.drop_column("study_id")
        batch_op.drop_column("tags")
        batch_op.drop_column("name")
    op.drop_table("studies")
