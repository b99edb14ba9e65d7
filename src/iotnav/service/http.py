"""HTTP edges (FastAPI): the OsmAnd / OwnTracks device endpoint and the Traccar-compatible API.

Device endpoint (:func:`device_app`, port 5055 by default)
    any path, GET or POST: OsmAnd (:mod:`iotnav.service.protocols.osmand`; query, form or
    JSON body); ``POST /owntracks``: OwnTracks HTTP mode
    (:mod:`iotnav.service.protocols.owntracks`). The answer (200, or 400 for a rejected or
    refused request) is sent after the message is committed.

API (:func:`api_app`, port 8082 by default; OpenAPI at ``/openapi.json``, docs at ``/docs``)
    the Traccar subset ``GET/POST /api/devices``, ``PUT/DELETE /api/devices/{id}`` and
    ``GET /api/positions?deviceId=&from=&to=`` with Traccar's field names and units (speed in
    knots, course in degrees, times ISO 8601 UTC), ``/api/geofences`` (list, create, update,
    delete; areas validated by :func:`iotnav.service.geofence.parse_area`), the reports
    ``GET /api/reports/route|trips|stops|events?deviceId=&from=&to=`` (``deviceId`` repeatable;
    trips and stops by :func:`iotnav.tracker.describe` on the clean positions). Bearer tokens: ``read`` scope for GET,
    ``admin`` for changes; a missing or wrong token is 401, a read token changing data 403.
"""

# no ``from __future__ import annotations``: FastAPI reads the endpoints' annotations at run
# time, and the dependency aliases (``Read``, ``Admin``) are local to :func:`api_app`.

import asyncio
import logging
import math
import time
from concurrent.futures import Executor
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace
from typing import Annotated, Any

import numpy as np
import sqlalchemy as sa
from fastapi import Depends, FastAPI, HTTPException, Query, Request, Response, WebSocket, WebSocketDisconnect
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field
from sqlalchemy.exc import IntegrityError

from iotnav.service.geofence import parse_area
from iotnav.service.ingest import NO_ENGINE, Ingestor
from iotnav.service.protocols import osmand, owntracks
from iotnav.service.protocols.common import KNOT_MPS, Decoded, Rejected
from iotnav.service.protocols.iotnav_raw import PROTOCOL as RAW_PROTOCOL
from iotnav.service.store import api_tokens, devices, events, geofences, inserted_id, positions, token_digest

log = logging.getLogger("iotnav.service.http")

MAX_BODY_BYTES = 65536


async def _store(
    ingestor: Ingestor,
    executor: Executor,
    protocol: str,
    result: Decoded | Rejected,
    raw: bytes,
    remote: str,
    unique: bool = False,
) -> Response:
    if isinstance(result, Rejected):
        ingestor.count(f"{protocol}_rejected_{result.reason}")
        log.warning("%s %s: rejected (%s): %s", protocol, remote, result.reason, result.detail)
        return Response(status_code=400, content=result.reason + "\n", media_type="text/plain")
    assert result.device is not None or not result.records
    if result.device is None:
        return Response(status_code=200, content=result.answer if protocol == "owntracks" else b"")
    res = await ingestor.submit(protocol, result.device, raw, result.records, remote, unique=unique)
    if not res.accepted:
        ingestor.count(f"{protocol}_rejected_unknown_device")
        return Response(status_code=400, content="unknown_device\n", media_type="text/plain")
    body = result.answer if protocol == "owntracks" else b""
    return Response(status_code=200, content=body, media_type="application/json" if body else None)


async def _body(request: Request) -> bytes | None:
    """The request body, or None when it exceeds :data:`MAX_BODY_BYTES`."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > MAX_BODY_BYTES:
        return None
    chunks, n = [], 0
    async for chunk in request.stream():
        n += len(chunk)
        if n > MAX_BODY_BYTES:
            return None
        chunks.append(chunk)
    return b"".join(chunks)


def device_app(ingestor: Ingestor, executor: Executor, speed_unit: str = "kn") -> FastAPI:
    """The OsmAnd / OwnTracks device endpoint."""
    app = FastAPI(
        title="iotnav device endpoint (OsmAnd, OwnTracks)", docs_url=None, redoc_url=None, openapi_url=None
    )

    @app.post("/owntracks")
    async def owntracks_http(request: Request) -> Response:
        body = await _body(request)
        remote = request.client.host if request.client else "?"
        if body is None:
            return Response(status_code=413)
        result = owntracks.decode(
            body, user=request.headers.get("x-limit-u"), device=request.headers.get("x-limit-d")
        )
        return await _store(ingestor, executor, "owntracks", result, body, remote)

    @app.api_route("/{path:path}", methods=["GET", "POST", "PUT"])
    async def osmand_http(request: Request, path: str) -> Response:
        body = await _body(request)
        remote = request.client.host if request.client else "?"
        if body is None:
            return Response(status_code=413)
        query = request.url.query
        now = time.time()
        if request.headers.get("content-type", "").split(";")[0].strip() == "application/json":
            result: Decoded | Rejected = osmand.decode_json(body, now)
        else:
            try:
                form = body.decode("ascii")
            except UnicodeDecodeError:
                form = ""
            result = osmand.decode_query(query, now, speed_unit, body=form)
        raw = f"{request.method} /{path}?{query}\n".encode() + body
        timed = b"timestamp" in query.encode() or b"timestamp" in body
        return await _store(ingestor, executor, "osmand", result, raw, remote, unique=not timed)

    return app


# --- API ----------------------------------------------------------------------------------


_ISO_SECONDS: dict[int, str] = {}  # whole second -> "YYYY-MM-DDTHH:MM:SS" (the live socket's hot path)


def iso(t: float | None) -> str | None:
    """ISO 8601 UTC of ``t`` (s since 1970), millisecond resolution (truncated, as ``isoformat``).

    The text of each whole second is cached: the same as
    ``datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")`` with ``Z``, which
    rounds ``t`` to microseconds half to even first, at a fraction of its cost.
    """
    if t is None:
        return None
    if not 0.0 <= t < 4102444800.0:
        return datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    frac, whole = math.modf(t)
    sec, us = int(whole), round(frac * 1e6)
    if us >= 1_000_000:
        sec, us = sec + 1, us - 1_000_000
    head = _ISO_SECONDS.get(sec)
    if head is None:
        if len(_ISO_SECONDS) >= 100_000:
            _ISO_SECONDS.clear()
        head = _ISO_SECONDS[sec] = datetime.fromtimestamp(sec, UTC).strftime("%Y-%m-%dT%H:%M:%S")
    return f"{head}.{us // 1000:03d}Z"


def parse_iso(s: str, name: str) -> float:
    """Seconds since 1970 UTC from an ISO 8601 string (naive: UTC); 400 if unreadable."""
    try:
        dt = datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        raise HTTPException(400, f"{name}: {s!r} is not an ISO 8601 time") from None
    return (dt if dt.tzinfo else dt.replace(tzinfo=UTC)).timestamp()


class DeviceIn(BaseModel):
    """A device to create (Traccar field names)."""

    name: str = Field(min_length=1, max_length=256)
    uniqueId: str = Field(min_length=1, max_length=128)
    disabled: bool = False
    attributes: dict[str, Any] = Field(default_factory=dict)


class DeviceUpdate(BaseModel):
    """Fields of a device to change (Traccar sends the whole object; absent fields are kept)."""

    id: int | None = None
    name: str | None = Field(default=None, min_length=1, max_length=256)
    uniqueId: str | None = Field(default=None, min_length=1, max_length=128)
    disabled: bool | None = None
    attributes: dict[str, Any] | None = None


class GeofenceIn(BaseModel):
    """A geofence (Traccar field names); ``area`` in Traccar's text form, latitude first."""

    id: int | None = None
    name: str = Field(min_length=1, max_length=256)
    description: str | None = None
    area: str = Field(min_length=1, max_length=100_000)
    attributes: dict[str, Any] = Field(default_factory=dict)


def _geofence_json(r: Any) -> dict[str, Any]:
    return {
        "id": r.id,
        "name": r.name,
        "description": r.description,
        "area": r.area,
        "attributes": r.attributes or {},
    }


def _device_json(r: Any) -> dict[str, Any]:
    return {
        "id": r.id,
        "name": r.name,
        "uniqueId": r.unique_id,
        "status": "unknown",
        "disabled": bool(r.disabled),
        "lastUpdate": iso(r.last_update),
        "attributes": r.attributes or {},
    }


def _position_json(r: Any, protocol: str | None) -> dict[str, Any]:
    attrs = dict(r.attributes or {})
    attrs["engine"] = r.engine
    return {
        "id": r.id,
        "deviceId": r.device_id,
        "protocol": protocol,
        "serverTime": iso(r.server_time),
        "deviceTime": iso(r.fix_time),
        "fixTime": iso(r.fix_time),
        "valid": bool(r.valid),
        "latitude": r.latitude,
        "longitude": r.longitude,
        "altitude": r.altitude if r.altitude is not None else 0.0,
        "speed": r.speed_mps / KNOT_MPS if r.speed_mps is not None else 0.0,
        "course": math.degrees(r.course_rad) if r.course_rad is not None else 0.0,
        "accuracy": r.accuracy_m if r.accuracy_m is not None else 0.0,
        "attributes": attrs,
    }


def api_app(db: sa.engine.Engine, ingestor: Ingestor) -> FastAPI:
    """The Traccar-compatible API."""
    app = FastAPI(
        title="iotnav API",
        description="Traccar-compatible subset: devices and positions. Bearer tokens (read / admin).",
        version="0.1",
    )
    bearer = HTTPBearer(auto_error=False)

    def scope_of(creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> str:
        if creds is None:
            raise HTTPException(401, "bearer token required", headers={"WWW-Authenticate": "Bearer"})
        with db.connect() as conn:
            scope = conn.execute(
                sa.select(api_tokens.c.scope).where(
                    api_tokens.c.token_sha256 == token_digest(creds.credentials)
                )
            ).scalar()
        if scope is None:
            ingestor.count("api_rejected_token")
            raise HTTPException(401, "invalid token", headers={"WWW-Authenticate": "Bearer"})
        return str(scope)

    def admin(scope: Annotated[str, Depends(scope_of)]) -> str:
        if scope != "admin":
            raise HTTPException(403, "admin scope required")
        return scope

    Read = Annotated[str, Depends(scope_of)]
    Admin = Annotated[str, Depends(admin)]

    @app.get("/api/devices")
    def list_devices(
        _: Read,
        uniqueId: Annotated[list[str] | None, Query()] = None,
        id: Annotated[list[int] | None, Query()] = None,
    ) -> list[dict[str, Any]]:
        q = sa.select(devices).order_by(devices.c.id)
        if uniqueId:
            q = q.where(devices.c.unique_id.in_(uniqueId))
        if id:
            q = q.where(devices.c.id.in_(id))
        with db.connect() as conn:
            return [_device_json(r) for r in conn.execute(q)]

    @app.post("/api/devices")
    def create_device(_: Admin, dev: DeviceIn) -> dict[str, Any]:
        try:
            with db.begin() as conn:
                new_id = inserted_id(
                    conn.execute(
                        devices.insert().values(
                            unique_id=dev.uniqueId,
                            name=dev.name,
                            disabled=dev.disabled,
                            attributes=dev.attributes,
                            created_at=time.time(),
                        )
                    )
                )
                row = conn.execute(sa.select(devices).where(devices.c.id == new_id)).one()
        except IntegrityError:
            raise HTTPException(400, f"uniqueId {dev.uniqueId!r} already exists") from None
        return _device_json(row)

    @app.put("/api/devices/{device_id}")
    def update_device(_: Admin, device_id: int, dev: DeviceUpdate) -> dict[str, Any]:
        values: dict[str, Any] = {}
        if dev.name is not None:
            values["name"] = dev.name
        if dev.uniqueId is not None:
            values["unique_id"] = dev.uniqueId
        if dev.disabled is not None:
            values["disabled"] = dev.disabled
        if dev.attributes is not None:
            values["attributes"] = dev.attributes
        try:
            with db.begin() as conn:
                if values:
                    conn.execute(devices.update().where(devices.c.id == device_id).values(**values))
                row = conn.execute(sa.select(devices).where(devices.c.id == device_id)).first()
        except IntegrityError:
            raise HTTPException(400, f"uniqueId {dev.uniqueId!r} already exists") from None
        if row is None:
            raise HTTPException(404, f"no device {device_id}")
        return _device_json(row)

    @app.delete("/api/devices/{device_id}", status_code=204)
    def delete_device(_: Admin, device_id: int) -> Response:
        with db.begin() as conn:
            n = conn.execute(devices.delete().where(devices.c.id == device_id)).rowcount
        if not n:
            raise HTTPException(404, f"no device {device_id}")
        return Response(status_code=204)

    def _clean_engine(conn: sa.Connection, device_id: int) -> str:
        """The engine whose rows are a device's clean positions, when the request names none.

        The service's engine for devices that send fixes. A device that streams raw GNSS + IMU
        (protocol ``iotnav_raw``) is fused by its own engine (:mod:`iotnav.service.raw_ingest`:
        pipeline by default, per group or device): its latest rows of an engine other than
        ``none`` say which.
        """
        protocol = conn.execute(sa.select(devices.c.protocol).where(devices.c.id == device_id)).scalar()
        return _fused_engine(conn, device_id) if protocol == RAW_PROTOCOL else ingestor.engine_name

    def _fused_engine(conn: sa.Connection, device_id: int) -> str:
        """The engine of a raw GNSS + IMU device's latest rows other than ``none`` (:func:`_clean_engine`)."""
        p = positions
        fused = conn.execute(
            sa.select(p.c.engine)
            .where(p.c.device_id == device_id, p.c.engine != NO_ENGINE)
            .order_by(p.c.id.desc())
            .limit(1)
        ).scalar()
        return str(fused) if fused is not None else ingestor.engine_name

    def _rows(device_id: int, engine: str | None, from_: str, to: str) -> list[Any]:
        t0, t1 = parse_iso(from_, "from"), parse_iso(to, "to")
        p = positions
        with db.connect() as conn:
            eng = engine or _clean_engine(conn, device_id)
            q = sa.select(p).where(
                p.c.device_id == device_id, p.c.engine == eng, p.c.fix_time >= t0, p.c.fix_time <= t1
            )
            return list(conn.execute(q.order_by(p.c.fix_time, p.c.id)))

    @app.get("/api/positions")
    def list_positions(
        _: Read,
        deviceId: int | None = None,
        from_: Annotated[str | None, Query(alias="from")] = None,
        to: str | None = None,
        engine: str | None = None,
    ) -> list[dict[str, Any]]:
        """Positions of ``deviceId`` with ``from`` <= fixTime <= ``to`` (ISO 8601), in time order.

        Without ``from``/``to`` the latest position of ``deviceId`` (or of every device).
        ``engine`` selects the rows: by default each device's clean positions (the service's
        engine, or the engine that fuses a raw GNSS + IMU device: :func:`_clean_engine`),
        ``none`` for the fixes as sent.
        """
        p = positions

        def latest(conn: sa.Connection, eng: str, device: int | None) -> dict[int, Any]:
            newest = sa.select(p.c.device_id, sa.func.max(p.c.fix_time).label("t")).where(p.c.engine == eng)
            if device is not None:
                newest = newest.where(p.c.device_id == device)
            sub = newest.group_by(p.c.device_id).subquery()
            q = sa.select(p).join(sub, sa.and_(p.c.device_id == sub.c.device_id, p.c.fix_time == sub.c.t))
            first: dict[int, Any] = {}
            for r in conn.execute(q.where(p.c.engine == eng).order_by(p.c.device_id, p.c.id)):
                first.setdefault(r.device_id, r)  # one per device if two share the latest time
            return first

        with db.connect() as conn:
            protocols = dict(conn.execute(sa.select(devices.c.id, devices.c.protocol)).all())
            if from_ is None and to is None:
                if engine is not None:
                    found = latest(conn, engine, deviceId)
                else:
                    found = latest(conn, ingestor.engine_name, deviceId)
                    for d, proto in protocols.items():
                        if proto == RAW_PROTOCOL and deviceId in (None, d):
                            found.pop(d, None)
                            found.update(latest(conn, _fused_engine(conn, d), d))
                rows = [found[d] for d in sorted(found)]
        if from_ is not None or to is not None:
            if deviceId is None or from_ is None or to is None:
                raise HTTPException(400, "deviceId, from and to are required together")
            rows = _rows(deviceId, engine, from_, to)
        return [_position_json(r, protocols.get(r.device_id)) for r in rows]

    @app.get("/api/iotnav/track")
    def track(
        _: Read,
        deviceId: int,
        from_: Annotated[str, Query(alias="from")],
        to: str,
        format: str = "geojson",
        engine: str | None = None,
    ) -> Response:
        """iotnav's own: a device's track as GeoJSON, GPX, KML or CSV (:func:`iotnav.io.export.export_track`).

        ``engine=none`` gives the fixes as the device sent them (raw), the default the
        service's engine output (clean).
        """
        import tempfile

        import pandas as pd

        from iotnav.io.export import FORMATS, export_track

        if format not in FORMATS:
            raise HTTPException(400, f"format {format!r}: expected one of {', '.join(FORMATS)}")
        rows = _rows(deviceId, engine, from_, to)
        df = pd.DataFrame(
            {
                "utc": [r.fix_time for r in rows],
                "lat": [r.latitude for r in rows],
                "lon": [r.longitude for r in rows],
                "height": [r.altitude if r.altitude is not None else math.nan for r in rows],
            }
        )
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / f"track.{format}"
            export_track(df, out, format, name=f"device {deviceId}")
            content = out.read_bytes()
        media = {"geojson": "application/geo+json", "gpx": "application/gpx+xml", "csv": "text/csv"}
        return Response(content, media_type=media.get(format, "application/vnd.google-earth.kml+xml"))

    def _area(text: str) -> str:
        try:
            parse_area(text)
        except ValueError as exc:
            raise HTTPException(400, f"area: {exc}") from None
        return text

    @app.get("/api/geofences")
    def list_geofences(_: Read) -> list[dict[str, Any]]:
        with db.connect() as conn:
            return [_geofence_json(r) for r in conn.execute(sa.select(geofences).order_by(geofences.c.id))]

    @app.post("/api/geofences")
    def create_geofence(_: Admin, g: GeofenceIn) -> dict[str, Any]:
        with db.begin() as conn:
            new_id = inserted_id(
                conn.execute(
                    geofences.insert().values(
                        name=g.name, description=g.description, area=_area(g.area), attributes=g.attributes
                    )
                )
            )
            return _geofence_json(conn.execute(sa.select(geofences).where(geofences.c.id == new_id)).one())

    @app.put("/api/geofences/{geofence_id}")
    def update_geofence(_: Admin, geofence_id: int, g: GeofenceIn) -> dict[str, Any]:
        with db.begin() as conn:
            n = conn.execute(
                geofences.update()
                .where(geofences.c.id == geofence_id)
                .values(name=g.name, description=g.description, area=_area(g.area), attributes=g.attributes)
            ).rowcount
            if not n:
                raise HTTPException(404, f"no geofence {geofence_id}")
            return _geofence_json(
                conn.execute(sa.select(geofences).where(geofences.c.id == geofence_id)).one()
            )

    @app.delete("/api/geofences/{geofence_id}", status_code=204)
    def delete_geofence(_: Admin, geofence_id: int) -> Response:
        with db.begin() as conn:
            n = conn.execute(geofences.delete().where(geofences.c.id == geofence_id)).rowcount
        if not n:
            raise HTTPException(404, f"no geofence {geofence_id}")
        return Response(status_code=204)

    # --- Traccar reports: route, trips, stops, events (issue 18) ---------------------------
    def _period(
        device_ids: list[str] | None, from_: str | None, to: str | None
    ) -> tuple[list[int], float, float]:
        """Device ids (``deviceId`` repeatable, as in Traccar) and the period, s; 400 when unusable."""
        if not device_ids:
            raise HTTPException(400, "deviceId is required (repeat it for several devices)")
        if from_ is None or to is None:
            raise HTTPException(400, "from and to are required (ISO 8601)")
        bad = [d for d in device_ids if not d.strip().isdigit()]
        if bad:
            raise HTTPException(400, f"deviceId: {bad[0]!r} is not a device id")
        t0, t1 = parse_iso(from_, "from"), parse_iso(to, "to")
        if t1 < t0:
            raise HTTPException(400, f"to ({to}) is before from ({from_})")
        return list(dict.fromkeys(int(d) for d in device_ids)), t0, t1

    def _report_rows(device_ids: list[str] | None, from_: str | None, to: str | None) -> dict[int, list[Any]]:
        """The clean rows of each device over ``from`` .. ``to`` (:func:`_period`)."""
        ids, _, _ = _period(device_ids, from_, to)
        return {d: _rows(d, None, str(from_), str(to)) for d in ids}

    def _segments(
        device_ids: list[str] | None, from_: str | None, to: str | None, kind: str
    ) -> list[dict[str, Any]]:
        """Trips or stops of the clean rows (:func:`iotnav.tracker.describe`, Traccar's units)."""
        import pandas as pd

        from iotnav.tracker import describe

        out: list[dict[str, Any]] = []
        by_dev = _report_rows(device_ids, from_, to)
        with db.connect() as conn:
            names = dict(conn.execute(sa.select(devices.c.id, devices.c.name)).all())
        for dev, rows in by_dev.items():
            if not rows:
                continue
            speed = np.array([math.nan if r.speed_mps is None else r.speed_mps for r in rows])
            course = np.array([0.0 if r.course_rad is None else r.course_rad for r in rows])
            # accuracy_m is the 2D RMS radius hypot(std_north, std_east) (Ingestor._output_row)
            std = np.array([math.nan if r.accuracy_m is None else r.accuracy_m / math.sqrt(2) for r in rows])
            track = pd.DataFrame(
                {
                    "t": [r.fix_time for r in rows],
                    "lat": [r.latitude for r in rows],
                    "lon": [r.longitude for r in rows],
                    "vn": speed * np.cos(course),
                    "ve": speed * np.sin(course),
                    "static": [bool((r.attributes or {}).get("static", False)) for r in rows],
                    "std_north": std,
                    "std_east": std,
                }
            )
            table = describe(track, engine_events=[]).trips
            for rec in table[table["kind"] == kind].to_dict("records"):
                s = SimpleNamespace(**{str(k): v for k, v in rec.items()})
                common = {
                    "deviceId": dev,
                    "deviceName": names.get(dev),
                    "startTime": iso(s.t_start),
                    "endTime": iso(s.t_end),
                    "duration": round(s.duration_s * 1000.0),
                }
                if kind == "stop":
                    out.append({**common, "latitude": s.lat_start, "longitude": s.lon_start})
                    continue
                avg = s.distance_m / s.duration_s if s.duration_s > 0 else 0.0
                out.append(
                    {
                        **common,
                        "distance": s.distance_m,
                        "averageSpeed": avg / KNOT_MPS,
                        "maxSpeed": s.max_speed_mps / KNOT_MPS if math.isfinite(s.max_speed_mps) else 0.0,
                        "startLat": s.lat_start,
                        "startLon": s.lon_start,
                        "endLat": s.lat_end,
                        "endLon": s.lon_end,
                    }
                )
        return out

    DeviceIds = Annotated[list[str] | None, Query()]
    From = Annotated[str | None, Query(alias="from")]

    @app.get("/api/reports/route")
    def report_route(
        _: Read, from_: From = None, to: str | None = None, deviceId: DeviceIds = None
    ) -> list[dict[str, Any]]:
        """The clean positions of each ``deviceId`` over ``from`` .. ``to``, as ``/api/positions``."""
        by_dev = _report_rows(deviceId, from_, to)
        with db.connect() as conn:
            protocols = dict(conn.execute(sa.select(devices.c.id, devices.c.protocol)).all())
        return [_position_json(r, protocols.get(d)) for d, rows in by_dev.items() for r in rows]

    @app.get("/api/reports/trips")
    def report_trips(
        _: Read, from_: From = None, to: str | None = None, deviceId: DeviceIds = None
    ) -> list[dict[str, Any]]:
        """Trips (Traccar's fields: times ISO 8601, ``duration`` ms, ``distance`` m, speeds knots)."""
        return _segments(deviceId, from_, to, "trip")

    @app.get("/api/reports/stops")
    def report_stops(
        _: Read, from_: From = None, to: str | None = None, deviceId: DeviceIds = None
    ) -> list[dict[str, Any]]:
        """Stops (Traccar's fields: ``latitude``/``longitude`` the stop's median, ``duration`` ms)."""
        return _segments(deviceId, from_, to, "stop")

    @app.get("/api/reports/events")
    def report_events(
        _: Read,
        from_: From = None,
        to: str | None = None,
        deviceId: DeviceIds = None,
        type: Annotated[list[str] | None, Query()] = None,
    ) -> list[dict[str, Any]]:
        """Stored events of each ``deviceId`` with ``from`` <= eventTime <= ``to``; ``type`` (repeatable)
        keeps those types (absent or ``allEvents``: every type)."""
        ids, t0, t1 = _period(deviceId, from_, to)
        e = events
        q = sa.select(e).where(e.c.device_id.in_(ids), e.c.event_time >= t0, e.c.event_time <= t1)
        if type and "allEvents" not in type:
            q = q.where(e.c.type.in_(type))
        with db.connect() as conn:
            rows = conn.execute(q.order_by(e.c.event_time, e.c.id)).all()
        return [
            {
                "id": r.id,
                "type": r.type,
                "eventTime": iso(r.event_time),
                "deviceId": r.device_id,
                "positionId": 0,
                "geofenceId": int((r.attributes or {}).get("geofenceId", 0) or 0),
                "attributes": r.attributes or {},
            }
            for r in rows
        ]

    sockets: set[asyncio.Queue[dict[str, Any]]] = set()
    loop_holder: list[asyncio.AbstractEventLoop] = []

    def broadcast(protocol: str, rows: list[dict[str, Any]]) -> None:
        """Ingestor listener (database thread): queue the positions for every open socket."""
        if sockets and loop_holder:
            send({"positions": [_position_json(SimpleNamespace(id=None, **r), protocol) for r in rows]})

    def send(msg: dict[str, Any]) -> None:
        """Queue ``msg`` for every open socket (from any thread; the alerts send ``{"events": ...}``)."""
        if not sockets or not loop_holder:
            return

        def deliver() -> None:
            for q in list(sockets):
                if q.full():  # a client too slow to read: drop, counted (back-pressure on it only)
                    ingestor.count("socket_dropped")
                else:
                    q.put_nowait(msg)

        loop_holder[0].call_soon_threadsafe(deliver)

    ingestor.listeners.append(broadcast)
    app.state.socket_send = send

    @app.websocket("/api/socket")
    async def live(ws: WebSocket, token: str | None = None) -> None:
        """Live positions as Traccar's socket sends them: ``{"positions": [...]}`` per stored message.

        The bearer token comes in the ``Authorization`` header or, for browsers, ``?token=``;
        a missing or wrong one closes the socket with code 1008 (policy violation).
        """
        header = ws.headers.get("authorization", "")
        given = header[7:] if header.lower().startswith("bearer ") else token
        ok = False
        if given:
            with db.connect() as conn:
                ok = (
                    conn.execute(
                        sa.select(api_tokens.c.id).where(api_tokens.c.token_sha256 == token_digest(given))
                    ).first()
                    is not None
                )
        if not ok:
            ingestor.count("api_rejected_token")
            await ws.close(code=1008)
            return
        await ws.accept()
        if not loop_holder:
            loop_holder.append(asyncio.get_running_loop())
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(maxsize=1000)
        sockets.add(queue)

        async def pump() -> None:
            while True:
                await ws.send_json(await queue.get())

        sender = asyncio.create_task(pump())
        try:
            while (await ws.receive())["type"] != "websocket.disconnect":
                pass  # the client says nothing we use; this notices it leaving
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            sender.cancel()
            sockets.discard(queue)

    @app.get("/api/server")
    def server_info(_: Read) -> dict[str, Any]:
        """iotnav's own: engine in use and counters (rejections by reason, duplicates)."""
        return {
            "engine": ingestor.engine_name,
            "engineRequested": ingestor.engine_requested,
            "registrationOpen": ingestor.registration_open,
            "counts": dict(ingestor.counts),
        }

    return app


__all__ = ["NO_ENGINE", "api_app", "device_app"]
