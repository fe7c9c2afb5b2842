"""Byte transports opened from a connection string (issue 4: ``udpin:``, ``udpout:``,
``tcp:``, serial device). Pure sockets; no MAVLink knowledge here.

Accepted forms (``//`` after the scheme is allowed, as MAVSDK writes it):
  udpin:HOST:PORT    bind and listen; replies go to the last sender (PX4 SITL onboard link)
  udp:HOST:PORT      same as udpin (mavutil's convention)
  udpout:HOST:PORT   send to HOST:PORT from an ephemeral port; receive the replies
  tcp:HOST:PORT      TCP client
  serial:DEVICE:BAUD, DEVICE:BAUD, DEVICE,BAUD or DEVICE (57600 baud)  e.g. /dev/ttyUSB0:921600
"""

from __future__ import annotations

import logging
import math
import select
import socket
import struct
import sys
import time
from dataclasses import dataclass

from .errors import ConnectionStringError

__all__ = ["Endpoint", "parse_connection_string", "open_transport", "Transport", "UdpTransport", "TcpTransport", "SerialTransport"]

log = logging.getLogger(__name__)

_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") and struct.calcsize("P") == 8 else None
"""Linux SO_TIMESTAMPNS (= SCM_TIMESTAMPNS; not exported by Python's socket module): the
kernel stamps each datagram's arrival (CLOCK_REALTIME, struct timespec of two int64)."""
_TIMESPEC = struct.Struct("@qq")


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string."""

    scheme: str  # "udpin" | "udpout" | "tcp" | "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600

    def __str__(self) -> str:
        if self.scheme == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.scheme}:{self.host}:{self.port}"


def parse_connection_string(url: str) -> Endpoint:
    """Parse a connection string (see module docstring); raises ConnectionStringError."""
    text = url.strip()
    scheme, sep, rest = text.partition(":")
    scheme = scheme.lower()
    if sep and scheme in ("udpin", "udp", "udpout", "tcp"):
        rest = rest[2:] if rest.startswith("//") else rest
        host, _, port_s = rest.rpartition(":")
        try:
            port = int(port_s)
        except ValueError:
            raise ConnectionStringError(f"bad port in connection string {url!r}") from None
        if not (0 <= port < 65536) or (port == 0 and scheme != "udpin"):
            raise ConnectionStringError(f"port out of range in connection string {url!r}")
        host = host or ("0.0.0.0" if scheme in ("udpin", "udp") else "127.0.0.1")
        return Endpoint("udpin" if scheme == "udp" else scheme, host, port)
    if scheme == "serial" and sep:
        rest = rest[2:] if rest.startswith("//") else rest
        text = rest
    if text.startswith("/") or text.upper().startswith("COM"):
        for s in (",", ":"):
            dev, s_, baud_s = text.rpartition(s)
            if s_ and baud_s.isdigit():
                return Endpoint("serial", device=dev, baud=int(baud_s))
        return Endpoint("serial", device=text)
    raise ConnectionStringError(f"unknown connection string {url!r} (use udpin:, udpout:, tcp: or a serial device)")


class Transport:
    """Moves bytes. ``recv`` returns one chunk (a whole datagram for UDP) or None on timeout."""

    is_datagram = False

    def send(self, data: bytes) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def recv(self, timeout_s: float) -> bytes | None:  # pragma: no cover - interface
        raise NotImplementedError

    def fileno(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def _wait_readable(self, timeout_s: float) -> bool:
        r, _, _ = select.select([self], [], [], max(0.0, timeout_s))
        return bool(r)


class UdpTransport(Transport):
    """udpin: bind and answer the last sender; udpout: fixed peer, ephemeral local port."""

    is_datagram = True

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.follow_sender = True
        """udpin: answer whoever sent the last datagram. A signing port turns this off and
        calls ``accept_sender`` only for datagrams with a valid signature, so an intruder's
        datagram cannot divert the replies (docs/security.md)."""
        self.last_sender: tuple[str, int] | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        if endpoint.scheme == "udpin":
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((endpoint.host, endpoint.port))
            self.peer: tuple[str, int] | None = None
        else:
            self._sock.bind(("0.0.0.0" if endpoint.host not in ("127.0.0.1", "localhost") else "127.0.0.1", 0))
            self.peer = (socket.gethostbyname(endpoint.host), endpoint.port)
        self._sock.setblocking(False)
        self.last_rx_monotonic_s = math.nan
        """``time.monotonic()`` of the last datagram's arrival at the socket: the kernel's
        timestamp where available (Linux), so the wait for this process to read it counts;
        else when ``recv`` read it."""
        self._kernel_stamps = False
        if _SO_TIMESTAMPNS is not None:
            try:
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self._kernel_stamps = True
            except OSError:
                pass

    @property
    def local_address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def send(self, data: bytes) -> bool:
        if self.peer is None:
            return False  # udpin before anyone spoke to us: nobody to answer
        try:
            self._sock.sendto(data, self.peer)
            return True
        except OSError as exc:  # e.g. ECONNREFUSED from an earlier ICMP, buffer full
            log.debug("udp send to %s failed: %s", self.peer, exc)
            return False

    def recv(self, timeout_s: float) -> bytes | None:
        while True:
            try:
                if self._kernel_stamps:
                    data, anc, _flags, addr = self._sock.recvmsg(65535, 64)
                else:
                    data, anc, addr = *self._sock.recvfrom(65535), ()
            except BlockingIOError:
                if timeout_s <= 0 or not self._wait_readable(timeout_s):
                    return None
                timeout_s = 0.0
                continue
            except OSError as exc:  # ICMP port unreachable surfaces here on Linux
                log.debug("udp recv: %s", exc)
                if timeout_s <= 0:
                    return None
                continue
            now = time.monotonic()
            self.last_rx_monotonic_s = now
            for level, kind, cdata in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(cdata) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(cdata)
                    self.last_rx_monotonic_s = now - min(max(0.0, time.time() - (sec + nsec * 1e-9)), 60.0)
            self.last_sender = addr
            if self.endpoint.scheme == "udpin" and self.follow_sender:
                self.peer = addr
            return data

    def accept_sender(self) -> None:
        """udpin: answer the sender of the last datagram from now on."""
        if self.endpoint.scheme == "udpin" and self.last_sender is not None:
            self.peer = self.last_sender

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()


class TcpTransport(Transport):
    """TCP client (e.g. PX4 SITL's or a router's TCP port)."""

    def __init__(self, endpoint: Endpoint, connect_timeout_s: float = 5.0) -> None:
        self.endpoint = endpoint
        try:
            self._sock = socket.create_connection((endpoint.host, endpoint.port), timeout=connect_timeout_s)
        except OSError as exc:
            raise ConnectionStringError(f"cannot connect to {endpoint}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.setblocking(False)

    def send(self, data: bytes) -> bool:
        try:
            self._sock.sendall(data)
            return True
        except (BlockingIOError, OSError) as exc:
            log.debug("tcp send failed: %s", exc)
            return False

    def recv(self, timeout_s: float) -> bytes | None:
        if not self._wait_readable(timeout_s):
            return None
        try:
            data = self._sock.recv(65535)
        except (BlockingIOError, OSError):
            return None
        return data or None

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()


class SerialTransport(Transport):
    """A serial device through pyserial (imported only when used)."""

    def __init__(self, endpoint: Endpoint) -> None:
        import serial  # pyserial, a declared test/runtime extra

        self.endpoint = endpoint
        try:
            self._port = serial.Serial(endpoint.device, endpoint.baud, timeout=0)
        except (serial.SerialException, OSError) as exc:
            raise ConnectionStringError(f"cannot open {endpoint}: {exc}") from exc

    def send(self, data: bytes) -> bool:
        try:
            self._port.write(data)
            return True
        except Exception as exc:
            log.debug("serial write failed: %s", exc)
            return False

    def recv(self, timeout_s: float) -> bytes | None:
        if not self._wait_readable(timeout_s):
            return None
        data = self._port.read(4096)
        return data or None

    def fileno(self) -> int:
        return self._port.fileno()

    def close(self) -> None:
        self._port.close()


def open_transport(url: str | Endpoint) -> Transport:
    """Open the transport a connection string names."""
    ep = url if isinstance(url, Endpoint) else parse_connection_string(url)
    if ep.scheme in ("udpin", "udpout"):
        try:
            return UdpTransport(ep)
        except OSError as exc:
            raise ConnectionStringError(f"cannot open {ep}: {exc}") from exc
    if ep.scheme == "tcp":
        return TcpTransport(ep)
    return SerialTransport(ep)
