"""``iotnav serve``: the live service that trackers talk to (an edge, STYLE §14).

Layers, each knowing only the one below it:

* :mod:`iotnav.service.protocols`: pure decoders, bytes in, records plus the answer out (or a
  typed rejection); no socket, no database;
* :mod:`iotnav.service.store`: SQLAlchemy 2 tables, the same schema on SQLite (WAL) and
  PostgreSQL, created and upgraded by the Alembic migrations of ``migrations/``;
* :mod:`iotnav.service.ingest`: one transaction per message (raw message, fixes as sent,
  engine outputs, the engine's checkpoint), then the answer; one engine per device fed in
  device-time order; :mod:`iotnav.service.checkpoint`: the saved per-device state;
* :mod:`iotnav.service.teltonika_tcp` (asyncio TCP), :mod:`iotnav.service.http` (OsmAnd,
  OwnTracks and the Traccar-compatible API, FastAPI), :mod:`iotnav.service.mqtt` (OwnTracks
  over MQTT, aiomqtt), :mod:`iotnav.service.app` (configuration and the event loop that runs
  them all).

Importing this package needs the optional ``service`` dependencies (FastAPI, uvicorn,
SQLAlchemy, Alembic, aiomqtt) only for the modules that use them; the decoders need none.
"""
