"""One MAVLink endpoint: a transport, a codec and an optional tlog. Both sides use it:
the controller's ``VehicleLink`` runs it in a receive thread, the mock vehicle polls it
from its own loop. Every packet sent or received (bad data excepted) goes to the tlog."""

from __future__ import annotations

import logging
import threading
import time

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
        return self.send_timed(msg)[0]

    def send_timed(self, msg: Message) -> tuple[bytes, float]:
        """``send``, also returning ``time.monotonic()`` just after the packet was handed to
        the transport (before the tlog write): when it went on the wire."""
        with self._tx_lock:
            packet = self.codec.encode(msg)
            self.transport.send(packet)
            sent_monotonic_s = time.monotonic()
            self.n_sent += 1
        if self.tlog is not None:
            self.tlog.write(packet)
        return packet, sent_monotonic_s

    MAX_DATAGRAM_BYTES = 1400
    """``send_many`` fills datagrams up to this (below a 1500-byte Ethernet MTU with IP/UDP
    headers, so a link leaving loopback is never fragmented)."""

    def send_many(self, msgs: list[Message]) -> list[bytes]:
        """Encode and send ``msgs`` in order. On a datagram transport consecutive packets
        share a datagram up to ``MAX_DATAGRAM_BYTES`` (PX4 packs its UDP datagrams the same
        way; every MAVLink parser reads several packets from one datagram), so a traffic set
        of N reports costs a few datagrams instead of N. Returns the packets."""
        if not msgs:
            return []
        packets: list[bytes] = []
        with self._tx_lock:
            encode, transport = self.codec.encode, self.transport
            if not transport.is_datagram:
                for msg in msgs:
                    packet = encode(msg)
                    packets.append(packet)
                    transport.send(packet)
            else:
                limit = self.MAX_DATAGRAM_BYTES
                chunk: list[bytes] = []
                size = 0
                for msg in msgs:
                    packet = encode(msg)
                    packets.append(packet)
                    n = len(packet)
                    if chunk and size + n > limit:
                        transport.send(b"".join(chunk))
                        chunk, size = [], 0
                    chunk.append(packet)
                    size += n
                if chunk:
                    transport.send(b"".join(chunk))
            self.n_sent += len(packets)
        if self.tlog is not None:
            self.tlog.write_many(packets)
        return packets

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
        out = (self.codec.decode_datagram(data, getattr(self.transport, "last_rx_monotonic_s", None))
               if self.transport.is_datagram else self.codec.decode(data))
        if self.codec.signing is not None and any(r.signature == "valid" for r in out):
            accept = getattr(self.transport, "accept_sender", None)
            if accept is not None:
                accept()
        good = [r.raw for r in out if not isinstance(r.msg, BadData)]
        self.n_bad += len(out) - len(good)
        self.n_received += len(good)
        if self.tlog is not None:
            self.tlog.write_many(good)
        return out

    def fileno(self) -> int:
        return self.transport.fileno()

    def close(self) -> None:
        self.transport.close()
