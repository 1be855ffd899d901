"""robots keep the controllers the server gave them; trace batches carry a checksum

Field statistics count a controller's steps and stuck events only on robots the server gave it
to (a push the robot acknowledged, or a replacement it was sent), so no robot raises another
controller's figures by naming it (docs/security.md). Robots before: none recorded (null).
A trace batch's arrays share one CRC-32, verified on every read (`server.core.integrity`); batches
stored before: null, read unverified.

Revision ID: 0007_served_checksums
Revises: 0006_robot_calibration
Create Date: 2026-12-04 02:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007_served_checksums"
down_revision: str | None = "0006_robot_calibration"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.add_column(sa.Column("served", sa.Text(), nullable=True))
    with op.batch_alter_table("robot_traces", schema=None) as batch_op:
        batch_op.add_column(sa.Column("checksum", sa.BigInteger(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("robot_traces", schema=None) as batch_op:
        batch_op.drop_column("checksum")
    with op.batch_alter_table("robots", schema=None) as batch_op:
        batch_op.drop_column("served")
