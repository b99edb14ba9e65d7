"""Initial schema: devices, raw messages, positions, events, geofences, API tokens.

Revision ID: 0001
Revises:
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "devices",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("unique_id", sa.String(128), nullable=False, unique=True),
        sa.Column("name", sa.String(256), nullable=False),
        sa.Column("protocol", sa.String(32), nullable=True),
        sa.Column("created_at", sa.Float, nullable=False),
        sa.Column("last_update", sa.Float, nullable=True),
        sa.Column("disabled", sa.Boolean, nullable=False, server_default=sa.false()),
        sa.Column("attributes", sa.JSON, nullable=False),
    )
    op.create_table(
        "raw_messages",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
        sa.Column("protocol", sa.String(32), nullable=False),
        sa.Column("received_at", sa.Float, nullable=False),
        sa.Column("remote", sa.String(128), nullable=True),
        sa.Column("payload", sa.LargeBinary, nullable=False),
        sa.Column("dedup_key", sa.String(64), nullable=False),
        sa.Column("n_records", sa.Integer, nullable=False),
        sa.UniqueConstraint("protocol", "dedup_key", name="uq_raw_messages_protocol_dedup"),
    )
    op.create_table(
        "positions",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
        sa.Column("raw_id", sa.Integer, sa.ForeignKey("raw_messages.id", ondelete="SET NULL"), nullable=True),
        sa.Column("engine", sa.String(32), nullable=False),
        sa.Column("fix_time", sa.Float, nullable=False),
        sa.Column("server_time", sa.Float, nullable=False),
        sa.Column("valid", sa.Boolean, nullable=False),
        sa.Column("latitude", sa.Float, nullable=False),
        sa.Column("longitude", sa.Float, nullable=False),
        sa.Column("altitude", sa.Float, nullable=True),
        sa.Column("speed_mps", sa.Float, nullable=True),
        sa.Column("course_rad", sa.Float, nullable=True),
        sa.Column("accuracy_m", sa.Float, nullable=True),
        sa.Column("attributes", sa.JSON, nullable=False),
        sa.Column("dedup_key", sa.String(64), nullable=False),
        sa.UniqueConstraint("device_id", "engine", "dedup_key", name="uq_positions_device_engine_dedup"),
    )
    op.create_index("ix_positions_device_engine_time", "positions", ["device_id", "engine", "fix_time"])
    op.create_table(
        "events",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("device_id", sa.Integer, sa.ForeignKey("devices.id", ondelete="CASCADE"), nullable=False),
        sa.Column("type", sa.String(64), nullable=False),
        sa.Column("event_time", sa.Float, nullable=False),
        sa.Column("server_time", sa.Float, nullable=False),
        sa.Column("attributes", sa.JSON, nullable=False),
    )
    op.create_index("ix_events_device_time", "events", ["device_id", "event_time"])
    op.create_table(
        "geofences",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("name", sa.String(256), nullable=False),
        sa.Column("area", sa.Text, nullable=False),
        sa.Column("attributes", sa.JSON, nullable=False),
    )
    op.create_table(
        "api_tokens",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("token_sha256", sa.String(64), nullable=False, unique=True),
        sa.Column("scope", sa.String(16), nullable=False),
        sa.Column("created_at", sa.Float, nullable=False),
    )


def downgrade() -> None:
    for name in ("api_tokens", "geofences", "events", "positions", "raw_messages", "devices"):
        op.drop_table(name)
