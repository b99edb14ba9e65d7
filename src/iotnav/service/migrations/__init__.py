"""Alembic migrations of the service database (run by :func:`iotnav.service.store.upgrade`)."""
