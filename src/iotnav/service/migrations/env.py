"""Alembic environment: runs on the connection handed in by :func:`iotnav.service.store.upgrade`."""

from __future__ import annotations

from alembic import context

from iotnav.service.store import metadata

conn = context.config.attributes.get("connection")
if conn is None:  # pragma: no cover - the alembic command line, with sqlalchemy.url set
    import sqlalchemy as sa

    engine = sa.create_engine(context.config.get_main_option("sqlalchemy.url") or "")
    with engine.begin() as conn:
        context.configure(connection=conn, target_metadata=metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
else:
    context.configure(connection=conn, target_metadata=metadata, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()
