"""robots keep the physics fitted from their traces

`colony robot calibrate` fits each whisker's trigger range and each wheel's gain from a robot's
traces with poses and stores them with the robot (`POST /api/robots/{id}/calibration`,
docs/robots.md). Robots calibrated before: none (null).

Revision ID: 0006_robot_calibration
Revises: 0005_trace_poses
Create Date: 2026-12-03 16:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006_robot_calibration"
down_revision: str | None = "0005_trace_poses"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.add_column(sa.Column("calibration", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("calibrated_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.drop_column("calibrated_at")
        batch_op.drop_column("calibration")
