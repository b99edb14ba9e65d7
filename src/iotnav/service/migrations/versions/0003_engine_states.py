"""Engine checkpoints: one row per device and engine (:mod:`iotnav.service.checkpoint`).

Revision ID: 0003
Revises: 0002
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "engine_states",
        sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
        sa.Column("engine", sa.String(32), nullable=False),
        sa.Column("saved_at", sa.Float, nullable=False),
        sa.Column("last_t", sa.Float, nullable=True),
        sa.Column("format", sa.String(64), nullable=False),
        sa.Column("state", sa.LargeBinary, nullable=False),
        sa.PrimaryKeyConstraint("device_id", "engine", name="pk_engine_states"),
    )


def downgrade() -> None:
    op.drop_table("engine_states")
