"""Raw messages' de-duplication key as the 32-byte SHA-256 digest instead of its 64-character hex text.

Every stored message writes one entry of the unique index ``(protocol, dedup_key)``; the binary
key halves its bytes (issue 18: SQLite's work inside the write lock at 10,000 devices). Existing
rows are converted (hex text -> the same digest's bytes); a key that is not 64 hex characters
(none written by iotnav) becomes the SHA-256 of its text, so it stays unique. Same schema on
SQLite (``BLOB``, the table rebuilt by Alembic's batch mode) and PostgreSQL (``BYTEA``).

Revision ID: 0004
Revises: 0003
"""

import hashlib
import re

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

_HEX = re.compile(r"[0-9a-fA-F]{64}")
_CHUNK = 5000


def _binary(key: str) -> bytes:
    """The digest of a stored hex key (a key of another form: the SHA-256 of its text)."""
    return bytes.fromhex(key) if _HEX.fullmatch(key) else hashlib.sha256(key.encode()).digest()


def upgrade() -> None:
    conn = op.get_bind()
    if conn.dialect.name == "postgresql":
        op.alter_column(
            "raw_messages",
            "dedup_key",
            type_=sa.LargeBinary(32),
            existing_nullable=False,
            postgresql_using=(
                "CASE WHEN dedup_key ~ '^[0-9a-fA-F]{64}$' THEN decode(dedup_key, 'hex') "
                "ELSE sha256(convert_to(dedup_key, 'UTF8')) END"
            ),
        )
        return
    last = 0
    while True:  # convert in place first (the rebuild below copies with CAST(... AS BLOB): the text's bytes)
        rows = conn.exec_driver_sql(
            "SELECT id, dedup_key FROM raw_messages WHERE id > ? AND typeof(dedup_key) = 'text' "
            "ORDER BY id LIMIT ?",
            (last, _CHUNK),
        ).all()
        if not rows:
            break
        conn.exec_driver_sql(
            "UPDATE raw_messages SET dedup_key = ? WHERE id = ?", [(_binary(k), i) for i, k in rows]
        )
        last = rows[-1][0]
    with op.batch_alter_table("raw_messages") as batch:
        batch.alter_column("dedup_key", type_=sa.LargeBinary(32), existing_nullable=False)


def downgrade() -> None:
    conn = op.get_bind()
    if conn.dialect.name == "postgresql":
        op.alter_column(
            "raw_messages",
            "dedup_key",
            type_=sa.String(64),
            existing_nullable=False,
            postgresql_using="encode(dedup_key, 'hex')",
        )
        return
    conn.exec_driver_sql("UPDATE raw_messages SET dedup_key = lower(hex(dedup_key))")
    with op.batch_alter_table("raw_messages") as batch:
        batch.alter_column("dedup_key", type_=sa.String(64), existing_nullable=False)
