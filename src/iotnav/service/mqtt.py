"""MQTT subscriber (paho-mqtt): OwnTracks over MQTT, acknowledged after commit.

The service subscribes to ``owntracks/+/+`` (configurable) with QoS 1 on a persistent session
(``clean_session = False`` and a fixed client id), so the broker keeps the messages that
arrive while the service is down and delivers them when it is back. Acknowledgements are
manual: the PUBACK of a message is sent only once its records are committed (on the single
database thread, so in the order the messages arrived, as MQTT requires). A message the
service stored before (redelivered because the PUBACK was lost) is acknowledged without being
stored again. A message the decoder rejects is acknowledged (it would otherwise come back
forever), logged and counted. When storing fails the message is not acknowledged; the broker
redelivers it when the connection is re-established (paho reconnects on its own after a
broker restart; after a storage failure the subscriber reconnects on purpose).
"""

from __future__ import annotations

import contextlib
import logging
import socket
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

from iotnav.service.ingest import Ingestor, IngestResult
from iotnav.service.protocols import owntracks
from iotnav.service.protocols.common import Rejected

log = logging.getLogger("iotnav.service.mqtt")


@dataclass(frozen=True)
class MqttSettings:
    """Broker URL (``mqtt://host:port``), client id of the persistent session, topic filter."""

    url: str
    client_id: str = "iotnav-serve"
    topic: str = "owntracks/+/+"


class MqttSubscriber:
    """Runs a paho client on its own network thread; storing goes through ``executor``."""

    def __init__(self, settings: MqttSettings, ingestor: Ingestor, executor: Executor) -> None:
        import paho.mqtt.client as mqtt

        self.settings = settings
        self.ingestor = ingestor
        self.executor = executor
        u = urlparse(settings.url)
        if u.scheme not in ("mqtt", "tcp") or not u.hostname:
            raise ValueError(f"MQTT URL {settings.url!r}: expected mqtt://host[:port]")
        self.host, self.port = u.hostname, u.port or 1883
        self.client = mqtt.Client(
            callback_api_version=mqtt.CallbackAPIVersion.VERSION2,
            client_id=settings.client_id,
            clean_session=False,
            protocol=mqtt.MQTTv311,
            manual_ack=True,
        )
        if u.username:
            self.client.username_pw_set(u.username, u.password)
        self.client.reconnect_delay_set(1, 30)
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message

    def start(self) -> None:
        """Connect (in the background; retried until the broker answers) and start the network thread."""
        self.client.connect_async(self.host, self.port, keepalive=30)
        self.client.loop_start()

    def stop(self) -> None:
        """Disconnect and stop the network thread."""
        self.client.disconnect()
        self.client.loop_stop()

    def _on_connect(self, client: Any, _userdata: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if reason.is_failure:
            log.warning("mqtt %s:%d: connection refused (%s)", self.host, self.port, reason)
            return
        client.subscribe(self.settings.topic, qos=1)
        log.warning("mqtt %s:%d: subscribed to %s", self.host, self.port, self.settings.topic)

    def _on_message(self, client: Any, _userdata: Any, msg: Any) -> None:
        result = owntracks.decode(bytes(msg.payload), topic=msg.topic)
        if isinstance(result, Rejected) or result.device is None:
            reason = result.reason if isinstance(result, Rejected) else "no_device"
            self.ingestor.count(f"mqtt_rejected_{reason}")
            log.warning("mqtt %s: rejected (%s)", msg.topic, reason)
            client.ack(msg.mid, msg.qos)
            return
        fut = self.executor.submit(
            self.ingestor.ingest, "owntracks", result.device, bytes(msg.payload), result.records, msg.topic
        )
        fut.add_done_callback(lambda f: self._stored(f, msg))

    def _stored(self, fut: Future[IngestResult], msg: Any) -> None:
        exc = fut.exception()
        if exc is not None:
            self.ingestor.count("mqtt_errors")
            log.error("mqtt %s: storing failed (%s); not acknowledged, reconnecting", msg.topic, exc)
            sock = self.client.socket()
            if isinstance(sock, socket.socket):  # the network thread sees the loss, reconnects: redelivery
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
            return
        if not fut.result().accepted:
            self.ingestor.count("mqtt_rejected_unknown_device")
        self.client.ack(msg.mid, msg.qos)
