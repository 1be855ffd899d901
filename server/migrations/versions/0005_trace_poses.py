"""robot traces carry each sample's time and pose

Protocol 12 trace batches carry `times` (Unix seconds) and `poses` (x, y, heading) with their
`pose_source` (sim or odometry), which the Colony page's map draws (docs/robots.md). Batches
stored before have none (null).

Revision ID: 0005_trace_poses
Revises: 0004_replacement_policy
Create Date: 2026-12-02 18:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005_trace_poses"
down_revision: str | None = "0004_replacement_policy"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("robot_traces", schema=None) as batch_op:
        batch_op.add_column(sa.Column("times", sa.LargeBinary(), nullable=True))
        batch_op.add_column(sa.Column("poses", sa.LargeBinary(), nullable=True))
        batch_op.add_column(sa.Column("pose_source", sa.String(length=16), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("robot_traces", schema=None) as batch_op:
        batch_op.drop_column("pose_source")
        batch_op.drop_column("poses")
        batch_op.drop_column("times")
