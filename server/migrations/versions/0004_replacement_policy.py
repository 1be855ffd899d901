"""robots' replacement policy and the stuck ledger's policy, answer and steps run

A robot may carry its own replacement policy (`robots.replacement`; NULL follows the colony's
COLONY_REPLACEMENT). Each stuck event records the policy that served it, the reply's reason,
the boot its step counts from, and once known the steps the robot ran before its next stuck
event (docs/robots.md). Events recorded before this revision keep NULL in all four.

Revision ID: 0004_replacement_policy
Revises: 0003_studies
Create Date: 2026-12-02 16:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004_replacement_policy"
down_revision: str | None = "0003_studies"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.add_column(sa.Column("replacement", sa.String(length=16), nullable=True))
    with op.batch_alter_table("robot_stuck_events", schema=None) as batch_op:
        batch_op.add_column(sa.Column("policy", sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column("answer", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("boot", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("steps_run", sa.BigInteger(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("robot_stuck_events", schema=None) as batch_op:
        batch_op.drop_column("steps_run")
        batch_op.drop_column("boot")
        batch_op.drop_column("answer")
        batch_op.drop_column("policy")
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.drop_column("replacement")
