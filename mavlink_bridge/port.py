"""One MAVLink endpoint: a transport, a codec and an optional tlog. Both sides use it:
the controller's ``VehicleLink`` runs it in a receive thread, the mock vehicle polls it
from its own loop. Every packet sent or received (bad data excepted) goes to the tlog."""

from __future__ import annotations

import logging
import threading

from .codec import MavCodec
from .messages import BadData, Message, Received
from .signing import SigningConfig
from .tlog import TlogWriter
from .transport import Transport, open_transport

__all__ = ["MavlinkPort"]

log = logging.getLogger(__name__)


class MavlinkPort:
    def __init__(
        self,
        transport: Transport,
        source_system: int,
        source_component: int,
        tlog: TlogWriter | None = None,
        name: str = "",
        signing: SigningConfig | None = None,
    ) -> None:
        self.transport = transport
        self.codec = MavCodec(source_system, source_component, signing)
        if signing is not None and hasattr(transport, "follow_sender"):
            transport.follow_sender = False  # only a validly signed datagram may become the peer
        self.tlog = tlog
        self.name = name or str(getattr(transport, "endpoint", "port"))
        self._tx_lock = threading.Lock()
        self.n_sent = 0
        self.n_received = 0
        self.n_bad = 0
        self.n_datagrams = 0

    @classmethod
    def open(
        cls,
        url: str,
        source_system: int,
        source_component: int,
        tlog: TlogWriter | None = None,
        signing: SigningConfig | None = None,
    ) -> "MavlinkPort":
        """Open ``url``; with ``signing`` every packet sent is signed and every packet
        received carries its signature status (``Received.signature``)."""
        return cls(open_transport(url), source_system, source_component, tlog, name=url, signing=signing)

    @property
    def signing(self) -> SigningConfig | None:
        return self.codec.signing

    @property
    def source_system(self) -> int:
        return self.codec.source_system

    @property
    def source_component(self) -> int:
        return self.codec.source_component

    def send(self, msg: Message) -> bytes:
        """Encode and send ``msg``; returns the packet (also when the transport had no peer)."""
        with self._tx_lock:
            packet = self.codec.encode(msg)
            self.transport.send(packet)
            self.n_sent += 1
        if self.tlog is not None:
            self.tlog.write(packet)
        return packet

    def send_raw(self, data: bytes) -> None:
        """Send raw bytes (tests use it to inject garbage)."""
        with self._tx_lock:
            self.transport.send(data)

    def recv(self, timeout_s: float) -> list[Received]:
        """Messages from at most one transport read (one datagram), waiting up to ``timeout_s``.
        Returns [] on timeout; bad bytes come back as ``BadData``."""
        data = self.transport.recv(timeout_s)
        if data is None:
            return []
        self.n_datagrams += 1
        out = self.codec.decode_datagram(data) if self.transport.is_datagram else self.codec.decode(data)
        if self.codec.signing is not None and any(r.signature == "valid" for r in out):
            accept = getattr(self.transport, "accept_sender", None)
            if accept is not None:
                accept()
        for r in out:
            if isinstance(r.msg, BadData):
                self.n_bad += 1
            else:
                self.n_received += 1
                if self.tlog is not None:
                    self.tlog.write(r.raw)
        return out

    def fileno(self) -> int:
        return self.transport.fileno()

    def close(self) -> None:
        self.transport.close()
