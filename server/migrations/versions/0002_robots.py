"""robot traces, robot state, stuck events, controller field stats

Revision ID: 0002_robots
Revises: 0001
Create Date: 2026-11-23 10:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002_robots"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "robot_traces",
        sa.Column("robot_id", sa.String(length=128), nullable=False),
        sa.Column("boot", sa.Integer(), nullable=False),
        sa.Column("first", sa.BigInteger(), nullable=False),
        sa.Column("last", sa.BigInteger(), nullable=False),
        sa.Column("count", sa.Integer(), nullable=False),
        sa.Column("controllers", sa.Text(), nullable=False),
        sa.Column("steps", sa.LargeBinary(), nullable=False),
        sa.Column("whiskers", sa.LargeBinary(), nullable=False),
        sa.Column("motors", sa.LargeBinary(), nullable=False),
        sa.Column("controller", sa.LargeBinary(), nullable=False),
        sa.Column("fresh", sa.LargeBinary(), nullable=False),
        sa.Column("received_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("robot_id", "boot", "first"),
    )
    op.create_table(
        "robot_state",
        sa.Column("robot_id", sa.String(length=128), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("steps", sa.BigInteger(), nullable=False),
        sa.Column("boot", sa.Integer(), nullable=False),
        sa.Column("whiskers", sa.String(length=8), nullable=False),
        sa.Column("controller_sha256", sa.String(length=64), nullable=True),
        sa.Column("serial_ok", sa.Boolean(), nullable=False),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("stuck_events", sa.Integer(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("robot_id"),
    )
    op.create_table(
        "robot_stuck_events",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("robot_id", sa.String(length=128), nullable=False),
        sa.Column("controller_sha256", sa.String(length=64), nullable=True),
        sa.Column("reason", sa.String(length=64), nullable=False),
        sa.Column("step", sa.BigInteger(), nullable=False),
        sa.Column("replacement_sha256", sa.String(length=64), nullable=True),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("robot_stuck_events", schema=None) as batch_op:
        batch_op.create_index("ix_stuck_robot", ["robot_id", "id"], unique=False)
        batch_op.create_index(
            batch_op.f("ix_robot_stuck_events_controller_sha256"),
            ["controller_sha256"],
            unique=False,
        )
    op.create_table(
        "controller_field_stats",
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("steps", sa.BigInteger(), nullable=False),
        sa.Column("stuck_events", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("sha256"),
    )


def downgrade() -> None:
    op.drop_table("controller_field_stats")
    with op.batch_alter_table("robot_stuck_events", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_robot_stuck_events_controller_sha256"))
        batch_op.drop_index("ix_stuck_robot")
    op.drop_table("robot_stuck_events")
    op.drop_table("robot_state")
    op.drop_table("robot_traces")
