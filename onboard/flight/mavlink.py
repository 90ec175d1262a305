"""The MAVLink link to the flight controller: our own transport, MAVLink 2, common dialect.

pymavlink's ``mavutil`` picks the protocol version and dialect from process-wide
environment variables (``MAVLINK20``, ``MAVLINK_DIALECT``) and even writes
``os.environ`` when imported. This module never imports it: it drives its own
``MAVLink`` object from ``pymavlink.dialects.v20.common`` (MAVLink 2 by
construction) over its own sockets or serial port, so importing it changes
nothing for anyone else in the process.

Endpoints (``Endpoint.parse``)::

    udpin:HOST:PORT     listen for the flight controller (or a router) on UDP; replies go to
                        the last address a valid MAVLink message came from
    udpout:HOST:PORT    send to HOST:PORT over UDP; replies come back to our ephemeral port
    tcp:HOST:PORT       TCP client (e.g. SITL on tcp:127.0.0.1:5760); reconnects when dropped
    /dev/ttyX[:BAUD]    serial port, raw 8N1 (default 57600 baud); also serial:/dev/ttyX:BAUD

:class:`FlightLink` reads HEARTBEAT, SYS_STATUS, BATTERY_STATUS and
EXTENDED_SYS_STATE of the first autopilot it hears (or of ``target_system``)
into a :class:`FlightState` (asking for those streams with
MAV_CMD_SET_MESSAGE_INTERVAL each time the link comes up), says when the link is lost (no heartbeat for
``heartbeat_timeout_s``) and when it comes back, sends our own HEARTBEAT as an
onboard controller at 1 Hz, and sends LANDING_TARGET on request.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import re
import select
import socket
import struct
import termios
import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Callable, Protocol

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.geometry import Vector, vector
from kgadapt.shared import messages
from kgadapt.shared.errors import FlightLinkError

if TYPE_CHECKING:  # imported where used: mavlink_commands is the link's helper
    from kgadapt.onboard.flight.mavlink_commands import CommandOutcome

log = logging.getLogger(__name__)

UINT16_MAX = 65535
LINK_UP = "link_up"              # first heartbeat from the flight controller
LINK_LOST = "link_lost"          # no heartbeat for heartbeat_timeout_s
LINK_RESTORED = "link_restored"  # a heartbeat again after a loss

_READ_TIMEOUT_S = 0.1  # how often blocked readers look at the stop flag
_TICK_S = 0.05         # heartbeat-timeout resolution

# ---------------------------------------------------------------- endpoints

_HOST_PORT = re.compile(r"^(?P<host>[A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:.]+\]):(?P<port>\d{1,5})$")
_SERIAL = re.compile(r"^(?P<device>/dev/[A-Za-z0-9_./\-]+?)(?::(?P<baud>\d+))?$")
_BAUDS = {int(name[1:]): getattr(termios, name) for name in dir(termios) if re.fullmatch(r"B\d+", name)}


@dataclass(frozen=True)
class Endpoint:
    """Where the flight controller is: parsed from a URL, checked, no I/O."""

    url: str
    kind: str  # "udpin" | "udpout" | "tcp" | "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    @classmethod
    def parse(cls, url: str) -> "Endpoint":
        """Parse ``udpin:``, ``udpout:``, ``tcp:``, ``/dev/ttyX:BAUD``; raise FlightLinkError naming a bad URL."""
        if not isinstance(url, str) or not url.strip():
            raise FlightLinkError(f"bad flight controller URL {url!r}: empty")
        text = url.strip()
        scheme, sep, rest = text.partition(":")
        if text.startswith("/dev/") or scheme == "serial":
            match = _SERIAL.match(text if text.startswith("/dev/") else rest)
            if not match:
                raise FlightLinkError(f"bad flight controller URL {url!r}: use /dev/DEVICE[:BAUD]")
            baud = int(match["baud"] or 57600)
            if baud not in _BAUDS:
                raise FlightLinkError(f"bad flight controller URL {url!r}: baud rate {baud} is not supported")
            return cls(url=text, kind="serial", device=match["device"], baud=baud)
        kind = {"udp": "udpin", "udpin": "udpin", "udpout": "udpout", "tcp": "tcp"}.get(scheme)
        if not sep or kind is None:
            raise FlightLinkError(
                f"bad flight controller URL {url!r}: use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT "
                "or /dev/DEVICE[:BAUD]"
            )
        match = _HOST_PORT.match(rest)
        if not match or not 0 < int(match["port"]) < 65536:
            raise FlightLinkError(f"bad flight controller URL {url!r}: expected {scheme}:HOST:PORT with a port 1-65535")
        return cls(url=text, kind=kind, host=match["host"].strip("[]"), port=int(match["port"]))


# ---------------------------------------------------------------- transports
# Each transport: open(timeout), read(timeout) -> (bytes, source) or None, write(bytes), close().
# ``datagram`` says whether one read is one or more whole MAVLink packets (UDP) or a byte stream.


class Transport(Protocol):
    """What the link reads from and writes to: UDP, TCP or a serial port."""

    datagram: bool

    def open(self, timeout: float) -> None: ...
    def read(self, timeout: float) -> tuple[bytes, object] | None: ...
    def accept_source(self, source: object) -> None: ...
    @property
    def can_send(self) -> bool: ...
    def write(self, data: bytes) -> None: ...
    def close(self) -> None: ...


class _UdpTransport:
    datagram = True

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        self._sock: socket.socket | None = None
        # udpout: fixed; udpin: the last source a valid message came from (see accept_source).
        self._peer: tuple[Any, ...] | None = None  # a socket address

    def open(self, timeout: float) -> None:
        ep = self._endpoint
        try:
            infos = socket.getaddrinfo(ep.host, ep.port, type=socket.SOCK_DGRAM)
            family, _, _, _, address = infos[0]
            sock = socket.socket(family, socket.SOCK_DGRAM)
            if ep.kind == "udpin":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(address)
            else:
                sock.bind(("::" if family == socket.AF_INET6 else "0.0.0.0", 0))
                self._peer = address
        except OSError as exc:
            raise FlightLinkError(f"cannot open flight controller link {ep.url}: {exc}") from exc
        sock.settimeout(_READ_TIMEOUT_S)
        self._sock = sock

    @property
    def local_address(self) -> tuple[Any, ...]:
        assert self._sock is not None
        address: tuple[Any, ...] = self._sock.getsockname()
        return address

    def read(self, timeout: float) -> tuple[bytes, object] | None:
        sock = self._sock
        if sock is None:
            return None
        try:
            data, source = sock.recvfrom(65535)
        except (socket.timeout, BlockingIOError):
            return None
        except OSError:
            if self._sock is None:  # closed under us by shutdown
                return None
            raise
        return data, source

    def accept_source(self, source: object) -> None:
        if self._endpoint.kind == "udpin" and isinstance(source, tuple):  # recvfrom's address
            self._peer = source

    @property
    def can_send(self) -> bool:
        return self._peer is not None

    def write(self, data: bytes) -> None:
        if self._sock is None or self._peer is None:
            raise FlightLinkError(f"no flight controller heard yet on {self._endpoint.url}: nowhere to send")
        try:
            self._sock.sendto(data, self._peer)
        except OSError as exc:
            raise FlightLinkError(f"send on {self._endpoint.url} failed: {exc}") from exc

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()


class _TcpTransport:
    datagram = False
    _RETRY_S = 1.0

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        self._sock: socket.socket | None = None
        self._closed = False
        self._next_retry = 0.0
        self._lock = threading.Lock()

    def open(self, timeout: float) -> None:
        self._sock = self._connect(timeout)

    def _connect(self, timeout: float) -> socket.socket:
        ep = self._endpoint
        try:
            sock = socket.create_connection((ep.host, ep.port), timeout=timeout)
        except OSError as exc:
            raise FlightLinkError(f"cannot connect to flight controller at {ep.url}: {exc}") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(_READ_TIMEOUT_S)
        return sock

    def read(self, timeout: float) -> tuple[bytes, object] | None:
        sock = self._sock
        if sock is None:
            self._maybe_reconnect()
            return None
        try:
            data = sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return None
        except OSError as exc:
            data = b""
            if not self._closed:
                log.warning("flight controller link %s: %s", self._endpoint.url, exc)
        if not data:  # peer closed: drop the socket, reconnect later
            self._drop(sock)
            return None
        return data, None

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            if self._sock is sock:
                self._sock = None
        sock.close()
        self._next_retry = time.monotonic() + self._RETRY_S

    def _maybe_reconnect(self) -> None:
        if self._closed or time.monotonic() < self._next_retry:
            time.sleep(_READ_TIMEOUT_S)
            return
        try:
            sock = self._connect(self._RETRY_S)
        except FlightLinkError:
            self._next_retry = time.monotonic() + self._RETRY_S
            return
        with self._lock:
            if self._closed:
                sock.close()
                return
            self._sock = sock
        log.info("flight controller link %s reconnected", self._endpoint.url)

    def accept_source(self, source: object) -> None:
        pass

    @property
    def can_send(self) -> bool:
        return self._sock is not None

    def write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            raise FlightLinkError(f"flight controller link {self._endpoint.url} is not connected")
        try:
            sock.sendall(data)
        except OSError as exc:
            raise FlightLinkError(f"send on {self._endpoint.url} failed: {exc}") from exc

    def close(self) -> None:
        with self._lock:
            self._closed = True
            sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()


class _SerialTransport:
    """A tty in raw 8N1 mode through termios: no pyserial needed."""

    datagram = False

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        self._fd: int | None = None
        self._write_lock = threading.Lock()

    def open(self, timeout: float) -> None:
        ep = self._endpoint
        try:
            fd = os.open(ep.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as exc:
            raise FlightLinkError(f"cannot open serial port {ep.url}: {exc}") from exc
        try:
            iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(fd)
            speed = _BAUDS[ep.baud]
            # raw: no echo, no line editing, no CR/LF translation, no flow control
            iflag = 0
            oflag = 0
            lflag = 0
            cflag = (cflag & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | getattr(termios, "CRTSCTS", 0)))
            cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
            cc[termios.VMIN] = 0
            cc[termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
        except (OSError, termios.error) as exc:
            os.close(fd)
            raise FlightLinkError(f"cannot configure serial port {ep.url} (is it a tty?): {exc}") from exc
        self._fd = fd

    def read(self, timeout: float) -> tuple[bytes, object] | None:
        fd = self._fd
        if fd is None:
            return None
        try:
            ready, _, _ = select.select([fd], [], [], timeout)
            if not ready:
                return None
            data = os.read(fd, 4096)
        except (BlockingIOError, InterruptedError):
            return None
        except (OSError, ValueError) as exc:
            if self._fd is None:
                return None
            raise FlightLinkError(f"serial port {self._endpoint.url} failed: {exc}") from exc
        return (data, None) if data else None

    def accept_source(self, source: object) -> None:
        pass

    @property
    def can_send(self) -> bool:
        return self._fd is not None

    def write(self, data: bytes) -> None:
        fd = self._fd
        if fd is None:
            raise FlightLinkError(f"serial port {self._endpoint.url} is not open")
        view = memoryview(data)
        with self._write_lock:
            try:
                while view:
                    try:
                        view = view[os.write(fd, view):]
                    except BlockingIOError:
                        select.select([], [fd], [], 0.1)
            except OSError as exc:
                raise FlightLinkError(f"send on {self._endpoint.url} failed: {exc}") from exc

    def close(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def open_transport(endpoint: Endpoint, timeout: float) -> Transport:
    """Open the transport for ``endpoint`` (bounded by ``timeout``); raise FlightLinkError."""
    kinds: dict[str, Callable[[Endpoint], Transport]] = {
        "udpin": _UdpTransport, "udpout": _UdpTransport, "tcp": _TcpTransport, "serial": _SerialTransport}
    transport = kinds[endpoint.kind](endpoint)
    transport.open(timeout)
    return transport


class _Writer:
    """The file-like object pymavlink's MAVLink.send writes packed bytes to."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    def write(self, data: bytes) -> None:
        self.transport.write(bytes(data))


class PacketParser:
    """Bytes in, MAVLink messages out; bad bytes counted, never raised.

    A datagram holds whole packets, so each datagram gets a fresh parser: a
    truncated or forged header cannot swallow the next good packet. A byte
    stream (TCP, serial) keeps one parser that resynchronises on its own.
    """

    def __init__(self, *, datagram: bool) -> None:
        self._datagram = datagram
        self._stream = self._new()
        self.bad = 0

    @staticmethod
    def _new() -> mavlink2.MAVLink:
        parser = mavlink2.MAVLink(None, 0, 0)
        parser.robust_parsing = True  # bad bytes become BAD_DATA messages instead of exceptions
        return parser

    def feed(self, data: bytes) -> list[mavlink2.MAVLink_message]:
        parser = self._new() if self._datagram else self._stream
        try:
            messages = parser.parse_buffer(data) or []
        except Exception as exc:  # noqa: BLE001 - pymavlink raises MAVError, struct.error, IndexError on odd input
            self.bad += 1
            log.debug("dropped undecodable MAVLink bytes (%d): %s", len(data), exc)
            if not self._datagram:
                self._stream = self._new()
            return []
        good = []
        for message in messages:
            kind = message.get_type()
            if kind == "BAD_DATA":
                self.bad += 1
            elif not kind.startswith("UNKNOWN"):
                good.append(message)
        return good


def new_mavlink(transport: Transport, *, system_id: int, component_id: int) -> mavlink2.MAVLink:
    """A MAVLink 2 encoder writing to ``transport`` as (system_id, component_id)."""
    return mavlink2.MAVLink(_Writer(transport), srcSystem=system_id, srcComponent=component_id)


def is_mavlink2(message: mavlink2.MAVLink_message) -> bool:
    """Whether a received message came as a MAVLink 2 packet."""
    buf = message.get_msgbuf()
    return bool(buf) and buf[0] == mavlink2.PROTOCOL_MARKER_V2


# ---------------------------------------------------------------- modes and states

# ArduCopter flight modes (custom_mode numbers), ArduPilot's documented values.
COPTER_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL",
    7: "CIRCLE", 9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD",
    17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB", 20: "GUIDED_NOGPS", 21: "SMART_RTL", 22: "FLOWHOLD",
    23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID", 26: "AUTOROTATE", 27: "AUTO_RTL", 28: "TURTLE",
}
COPTER_MODE_NUMBERS = {name: number for number, name in COPTER_MODES.items()}
_COPTER_TYPES = {
    getattr(mavlink2, name) for name in (
        "MAV_TYPE_QUADROTOR", "MAV_TYPE_COAXIAL", "MAV_TYPE_HELICOPTER", "MAV_TYPE_HEXAROTOR",
        "MAV_TYPE_OCTOROTOR", "MAV_TYPE_TRICOPTER", "MAV_TYPE_DODECAROTOR", "MAV_TYPE_DECAROTOR",
    ) if hasattr(mavlink2, name)
}
# PX4 packs main mode in bits 16-23 and sub mode (for AUTO) in bits 24-31 of custom_mode.
_PX4_MAIN = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD",
             7: "STABILIZED", 8: "RATTITUDE", 9: "SIMPLE", 10: "TERMINATION"}
_PX4_AUTO = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND",
             8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF"}

LANDED_STATES = {
    mavlink2.MAV_LANDED_STATE_UNDEFINED: "UNDEFINED",
    mavlink2.MAV_LANDED_STATE_ON_GROUND: "ON_GROUND",
    mavlink2.MAV_LANDED_STATE_IN_AIR: "IN_AIR",
    mavlink2.MAV_LANDED_STATE_TAKEOFF: "TAKEOFF",
    mavlink2.MAV_LANDED_STATE_LANDING: "LANDING",
}
LANDED_STATE_NUMBERS = {name: number for number, name in LANDED_STATES.items()}
_AUTOPILOTS = {mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", mavlink2.MAV_AUTOPILOT_PX4: "px4",
               mavlink2.MAV_AUTOPILOT_GENERIC: "generic"}


def mode_name(autopilot: int, vehicle_type: int, base_mode: int, custom_mode: int) -> str:
    """A readable flight mode from a HEARTBEAT's autopilot, type and mode fields."""
    if base_mode & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        if autopilot == mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA and vehicle_type in _COPTER_TYPES:
            return COPTER_MODES.get(custom_mode, f"MODE_{custom_mode}")
        if autopilot == mavlink2.MAV_AUTOPILOT_PX4:
            main = _PX4_MAIN.get((custom_mode >> 16) & 0xFF, f"MODE_{custom_mode}")
            sub = (custom_mode >> 24) & 0xFF
            return f"{main}.{_PX4_AUTO.get(sub, sub)}" if main == "AUTO" and sub else main
    return f"MODE_{custom_mode}"


# What each stream tells: the FlightState fields it owns. A stream not heard within its timeout
# makes its fields unknown (None); HEARTBEAT's fields follow the link instead.
STREAM_FIELDS: dict[str, tuple[str, ...]] = {
    "HEARTBEAT": ("armed", "mode"),
    "SYS_STATUS": ("onboard_load",),
    "BATTERY_STATUS": ("battery_pct", "battery_v"),
    "EXTENDED_SYS_STATE": ("landed_state",),
    "ATTITUDE": ("attitude", "rates"),
    "GLOBAL_POSITION_INT": ("alt_rel_m", "alt_amsl_m", "lat_deg", "lon_deg"),
    "LOCAL_POSITION_NED": ("position_ned", "velocity_ned"),
    "DISTANCE_SENSOR": ("rangefinder_m",),
    "HOME_POSITION": ("home",),
}


@dataclass(frozen=True, kw_only=True)
class FlightState:
    """What we know about the flight controller; None = unknown (not heard, or not heard within its timeout)."""

    time: float  # epoch seconds of the last change
    link: bool = False
    armed: bool | None = None
    mode: str | None = None
    landed_state: str | None = None  # UNDEFINED, ON_GROUND, IN_AIR, TAKEOFF, LANDING
    battery_pct: float | None = None
    battery_v: float | None = None
    onboard_load: float | None = None  # flight controller main-loop load, percent
    alt_rel_m: float | None = None  # above home (GLOBAL_POSITION_INT.relative_alt)
    alt_amsl_m: float | None = None  # above mean sea level (GLOBAL_POSITION_INT.alt)
    lat_deg: float | None = None
    lon_deg: float | None = None
    attitude: tuple[float, float, float] | None = None  # roll, pitch, yaw, rad
    rates: tuple[float, float, float] | None = None  # roll, pitch, yaw rates, rad/s
    position_ned: tuple[float, float, float] | None = None  # m from the EKF origin (LOCAL_POSITION_NED)
    velocity_ned: tuple[float, float, float] | None = None  # m/s
    rangefinder_m: float | None = None  # downward rangefinder, within its valid range
    home: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m AMSL
    heard: tuple[tuple[str, float], ...] = ()  # (stream, epoch seconds last heard) for every stream now valid
    boot_ms: int | None = None  # the autopilot's time since boot, from the last message that carries it
    reboots: int = 0  # autopilot reboots seen since our start
    missing: tuple[str, ...] = ()  # streams asked for that do not arrive
    refused: tuple[str, ...] = ()  # the last commands the autopilot refused or did not acknowledge
    rejected: int = 0  # COMMAND_ACKs that rejected a command (temporary rejections retried and accepted included)
    system_id: int | None = None
    autopilot: str | None = None
    last_heartbeat: float | None = None  # epoch seconds
    event: str | None = None  # the link event this snapshot was made for, if any

    def discrete(self) -> tuple[object, ...]:
        """The fields whose change is news at once (the rest is published periodically)."""
        return (self.link, self.armed, self.mode, self.landed_state, self.reboots)

    def last_heard(self, stream: str) -> float | None:
        return dict(self.heard).get(stream)

    def as_message(self, *, angles_only: bool | None = None) -> messages.FlightState:
        """This state as a ``flight_state`` wire message (``angles_only``: the bridge's, absent = no news)."""
        return messages.FlightState(
            time=self.time, link=self.link, armed=self.armed, mode=self.mode,
            landed_state=self.landed_state, battery_pct=self.battery_pct, battery_v=self.battery_v,
            onboard_load=self.onboard_load, alt_rel_m=self.alt_rel_m, alt_amsl_m=self.alt_amsl_m,
            lat_deg=self.lat_deg, lon_deg=self.lon_deg,
            attitude=list(self.attitude) if self.attitude else None,
            rates=list(self.rates) if self.rates else None,
            position_ned=list(self.position_ned) if self.position_ned else None,
            velocity_ned=list(self.velocity_ned) if self.velocity_ned else None,
            rangefinder_m=self.rangefinder_m, home=list(self.home) if self.home else None,
            heard=dict(self.heard) or None, boot_ms=self.boot_ms, reboots=self.reboots,
            missing=list(self.missing) or None, refused=list(self.refused) or None,
            rejected=self.rejected or None, angles_only=angles_only,
            system_id=self.system_id, autopilot=self.autopilot,
            last_heartbeat=self.last_heartbeat, event=self.event,
        )


@dataclass(frozen=True, kw_only=True)
class LandingTarget:
    """One LANDING_TARGET: angles from the image centre, optionally a position (body FRD or local NED)."""

    time: float  # epoch seconds of the frame the target was seen in (or the time it was predicted for)
    angle_x: float  # rad, + to the right of the image centre
    angle_y: float  # rad, + below the image centre
    size_x: float = 0.0  # rad
    size_y: float = 0.0  # rad
    distance: float = 0.0  # m, 0 = unknown
    target_num: int = 0
    position: tuple[float, float, float] | None = None  # m in ``frame``; sets position_valid=1
    frame: int = mavlink2.MAV_FRAME_BODY_FRD  # ArduPilot: BODY_FRD; PX4: LOCAL_NED

    def __post_init__(self) -> None:
        for name in ("time", "angle_x", "angle_y", "size_x", "size_y", "distance"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise FlightLinkError(f"LANDING_TARGET field {name} must be a finite number, not {value!r}")
        if self.time < 0:
            raise FlightLinkError(f"LANDING_TARGET time must not be negative, not {self.time!r}")
        if self.position is not None and (
            len(self.position) != 3 or not all(math.isfinite(float(v)) for v in self.position)
        ):
            raise FlightLinkError(f"LANDING_TARGET position must be three finite numbers, not {self.position!r}")
        if self.frame not in (mavlink2.MAV_FRAME_BODY_FRD, mavlink2.MAV_FRAME_LOCAL_NED):
            raise FlightLinkError(f"LANDING_TARGET frame must be BODY_FRD (12) or LOCAL_NED (1), not {self.frame}")


# ---------------------------------------------------------------- the link

AUTOPILOT_REBOOTED = "autopilot_rebooted"  # time since boot went backwards, or a new autopilot system id

DEFAULT_STREAM_RATES: tuple[tuple[str, float], ...] = (
    ("SYS_STATUS", 2.0), ("BATTERY_STATUS", 1.0), ("EXTENDED_SYS_STATE", 2.0), ("ATTITUDE", 20.0),
    ("GLOBAL_POSITION_INT", 5.0), ("LOCAL_POSITION_NED", 10.0), ("DISTANCE_SENSOR", 10.0),
    ("HOME_POSITION", 0.5),
)


@dataclass(frozen=True, kw_only=True)
class LinkSettings:
    """How to reach the flight controller and how we appear to it."""

    url: str
    system_id: int = 1  # a companion computer shares the vehicle's system id ...
    component_id: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER  # ... with its own component id
    target_system: int | None = None  # the autopilot to follow; None = the first one heard
    heartbeat_timeout_s: float = 3.0
    heartbeat_period_s: float = 1.0
    open_timeout_s: float = 5.0
    # Asked of the autopilot with MAV_CMD_SET_MESSAGE_INTERVAL whenever the link comes up, after a
    # reboot and whenever one stops: ArduCopter does not stream EXTENDED_SYS_STATE by default, and
    # this spares us its SRn_* stream parameters.
    stream_rates: tuple[tuple[str, float], ...] = DEFAULT_STREAM_RATES
    stream_timeout_periods: float = 3.0  # a stream is stopped after this many of its periods unheard ...
    stream_timeout_min_s: float = 1.0  # ... and never sooner than this
    reboot_gap_s: float = 1.8  # an autopilot heartbeat gap longer than this: ask for every stream again
    stream_retry_max_s: float = 30.0  # a stream that does not come is asked for again, backing off to this
    commands: Any = None  # retries of acknowledged commands (None: the defaults)

    def stream_timeout(self, name: str, hz: float) -> float:
        return max(self.stream_timeout_min_s, self.stream_timeout_periods / hz)


StateListener = Callable[[FlightState], None]

# Messages that carry the autopilot's time since boot: a jump back means it rebooted.
_BOOT_TIME_FIELD = {"ATTITUDE": "time_boot_ms", "GLOBAL_POSITION_INT": "time_boot_ms",
                    "LOCAL_POSITION_NED": "time_boot_ms", "DISTANCE_SENSOR": "time_boot_ms",
                    "SYSTEM_TIME": "time_boot_ms"}
_BOOT_BACKWARDS_MS = 100  # a router may reorder a little; a reboot restarts the clock from 0


class FlightLink:
    """The adapter: reads the flight controller's state, sends our heartbeat, commands and landing targets.

    ``setup()`` opens the transport and starts three threads (reader, ticker,
    commands); listeners registered with :meth:`on_state` run on the reader
    and ticker threads and must return quickly (hand work to a queue).
    """

    def __init__(self, settings: LinkSettings) -> None:
        from kgadapt.onboard.flight.mavlink_commands import CommandSender, CommandSettings

        self.settings = settings
        self.endpoint = Endpoint.parse(settings.url)
        if settings.heartbeat_timeout_s <= 0 or settings.heartbeat_period_s <= 0:
            raise FlightLinkError(f"flight link {settings.url}: heartbeat period and timeout must be positive")
        self._streams: dict[str, tuple[int, float, float]] = {}  # name -> (message id, Hz, timeout s)
        for name, hz in settings.stream_rates:
            msg_id = getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None)
            if msg_id is None or not hz > 0 or name not in STREAM_FIELDS:
                raise FlightLinkError(f"flight link {settings.url}: cannot request {name} at {hz} Hz "
                                      f"(streams: {', '.join(n for n in STREAM_FIELDS if n != 'HEARTBEAT')})")
            self._streams[name] = (msg_id, hz, settings.stream_timeout(name, hz))
        self._streams_wanted = threading.Event()  # set when the link comes up: ask for our streams
        self._transport: Transport | None = None
        self._mav: mavlink2.MAVLink | None = None
        self._send_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._state = FlightState(time=time.time())
        self._fc: tuple[int, int] | None = None  # (system, component) of the autopilot we follow
        self._last_heartbeat_mono: float | None = None
        self._heard_mono: dict[str, float] = {}
        self._asked_mono: dict[str, float] = {}  # stream -> when we last asked for it
        self._retry_s: dict[str, float] = {}  # stream -> current back-off
        self._have_battery_status = False
        self._listeners: list[StateListener] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._heard = threading.Condition(self._state_lock)
        # What the vehicle's pose was when: ATTITUDE (epoch, attitude) and LOCAL_POSITION_NED (epoch, position, velocity)
        # apart, each stamped when it arrived, so pose_at() never gives a position as of an attitude's time.
        self._attitudes: collections.deque[tuple[float, Vector]] = collections.deque(maxlen=256)
        self._positions: collections.deque[tuple[float, Vector, Vector]] = collections.deque(maxlen=128)
        self.counters = {"received": 0, "bad": 0, "sent": 0, "send_errors": 0, "links_lost": 0,
                         "reboots": 0, "stream_requests": 0, "streams_stopped": 0}
        self.commands = CommandSender(settings.commands or CommandSettings(), encoder=lambda: self._mav,
                                      send=self._send, alive=lambda: self.state.link,
                                      on_refusal=lambda r: self._update(
                                          refused=tuple(str(x) for x in list(self.commands.refusals)[-5:])),
                                      on_rejected=lambda: self._update(rejected=self.commands.counters["rejected"]))

    # -- lifecycle

    def setup(self) -> None:
        """Open the transport (bounded by ``open_timeout_s``) and start reading; raise FlightLinkError."""
        if self._transport is not None:
            return
        self._stop.clear()
        self._transport = transport = open_transport(self.endpoint, self.settings.open_timeout_s)
        self._parser = PacketParser(datagram=transport.datagram)
        self._mav = new_mavlink(transport, system_id=self.settings.system_id,
                                component_id=self.settings.component_id)
        self.commands.setup()
        self._threads = [
            threading.Thread(target=self._read_loop, name="mavlink-reader", daemon=True),
            threading.Thread(target=self._tick_loop, name="mavlink-ticker", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        log.info("flight link %s open", self.endpoint.url)

    def shutdown(self) -> None:
        """Stop the threads and close the transport."""
        self._stop.set()
        self.commands.shutdown()
        transport, self._transport = self._transport, None
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads = []
        if transport is not None:
            transport.close()
        with self._state_lock:  # no longer hearing anything; no listener call, we are going away
            self._state = replace(self._state, time=time.time(), link=False, event=None)

    def __enter__(self) -> "FlightLink":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    # -- reading

    @property
    def state(self) -> FlightState:
        """The latest state; a stream's fields older than its timeout are unknown here even between ticks."""
        with self._state_lock:
            state = self._state
            now = time.monotonic()
            stale = [name for name, heard in tuple(self._heard_mono.items())  # a copy: the reader adds to it
                     if name != "HEARTBEAT" and now - heard > self.stream_timeout(name)]
        if not stale:
            return state
        cleared: dict[str, Any] = {f: None for name in stale for f in STREAM_FIELDS[name]}
        if "SYS_STATUS" in stale and "BATTERY_STATUS" not in dict(state.heard):
            cleared.update({f: None for f in STREAM_FIELDS["BATTERY_STATUS"]})
        return replace(state, heard=tuple((k, t) for k, t in state.heard if k not in stale), **cleared)

    def on_state(self, listener: StateListener) -> None:
        """Call ``listener(state)`` on every change of the state (and with every link event)."""
        self._listeners.append(listener)

    def stream_timeout(self, name: str) -> float:
        """Seconds after which ``name``'s fields become unknown."""
        if name == "HEARTBEAT":
            return self.settings.heartbeat_timeout_s
        return self._streams[name][2] if name in self._streams else self.settings.stream_timeout_min_s

    def pose_at(self, when: float, *, within_s: float = 0.25) -> tuple[Vector, Vector | None] | None:
        """(attitude, position_ned or None) at epoch ``when``; None without an attitude heard within ``within_s``.

        The attitude is interpolated between the two samples around ``when`` (20 Hz: a vehicle turning
        at 0.5 rad/s moves a marker 10 m away by 0.12 m in half a period); the position is the nearest
        sample carried to ``when`` with its velocity (10 Hz: 0.1 m at 2 m/s otherwise).
        """
        with self._state_lock:
            attitudes = list(self._attitudes)
            positions = list(self._positions)
        nearest = min(attitudes, key=lambda a: abs(a[0] - when), default=None)
        if nearest is None or abs(nearest[0] - when) > within_s:
            return None
        attitude = nearest[1]
        before = [a for a in attitudes if a[0] <= when]
        after = [a for a in attitudes if a[0] > when]
        if before and after and after[0][0] - before[-1][0] <= within_s:
            (t0, a0), (t1, a1) = before[-1], after[0]
            share = (when - t0) / (t1 - t0)
            attitude = vector(x0 + share * math.remainder(x1 - x0, math.tau) for x0, x1 in zip(a0, a1, strict=True))
        place = min(positions, key=lambda p: abs(p[0] - when), default=None)
        if place is None or abs(place[0] - when) > within_s:
            return attitude, None
        t, position, velocity = place
        return attitude, vector(p + v * (when - t) for p, v in zip(position, velocity, strict=True))

    def wait_for_heartbeat(self, timeout: float) -> FlightState:
        """Block until the link is up; raise FlightLinkError naming the URL after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        with self._heard:
            while not self._state.link:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise FlightLinkError(
                        f"no heartbeat from a flight controller on {self.endpoint.url} within {timeout:g} s"
                    )
                self._heard.wait(left)
            return self._state

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            transport = self._transport
            if transport is None:
                return
            try:
                chunk = transport.read(_READ_TIMEOUT_S)
            except Exception as exc:  # noqa: BLE001 - a failing port must not kill the thread silently
                log.error("flight link %s read failed: %s", self.endpoint.url, exc)
                self._stop.wait(0.5)
                continue
            if chunk is None:
                continue
            data, source = chunk
            messages = self._parser.feed(data)
            self.counters["bad"] = self._parser.bad
            for message in messages:
                self.counters["received"] += 1
                try:
                    if self._handle(message):
                        transport.accept_source(source)
                except Exception:  # one odd message must never stop the reader
                    log.exception("flight link %s: cannot use %s", self.endpoint.url, message.get_type())

    def _handle(self, message: mavlink2.MAVLink_message) -> bool:
        """Fold one message into the state; True if it came from the autopilot we follow."""
        kind = message.get_type()
        src = (message.get_srcSystem(), message.get_srcComponent())
        now = time.monotonic()
        if kind == "HEARTBEAT":
            return self._handle_heartbeat(message, src, now)
        # The autopilot is one component: another of its system (a gimbal, a camera, or our own messages coming
        # back through a router) must neither change the flight state nor where replies go.
        if self._fc is None or src != self._fc:
            return False
        if kind == "COMMAND_ACK":
            # A router may pass on acks meant for a ground station: only ours count.
            if message.target_system in (0, self.settings.system_id) and \
                    message.target_component in (0, self.settings.component_id):
                self.commands.on_ack(message)
            return True
        field = _BOOT_TIME_FIELD.get(kind)
        if field is not None:
            boot_ms = int(getattr(message, field))
            last = self.state.boot_ms
            # One autopilot's messages come in order, so its clock never goes back, unless it restarted.
            # (Not compared with our clock: a reader stalled by a busy machine would look like a reboot.)
            if last is not None and boot_ms + _BOOT_BACKWARDS_MS < last:
                self._rebooted(f"time since boot went back from {last} to {boot_ms} ms")
            self._update(boot_ms=boot_ms)
        changes: dict[str, Any] | None = None
        if kind == "SYS_STATUS":
            changes = {"onboard_load": message.load / 10.0}
            if not self._have_battery_status:
                if message.voltage_battery != UINT16_MAX:
                    changes["battery_v"] = message.voltage_battery / 1000.0
                if message.battery_remaining >= 0:
                    changes["battery_pct"] = float(message.battery_remaining)
        elif kind == "BATTERY_STATUS":
            if message.id != 0:
                return True  # the first battery is the one that flies
            self._have_battery_status = True
            cells = [v for v in message.voltages if v != UINT16_MAX]
            cells += [v for v in getattr(message, "voltages_ext", ()) if v]
            changes = {"battery_v": sum(cells) / 1000.0 if cells else None,
                       "battery_pct": float(message.battery_remaining) if message.battery_remaining >= 0 else None}
        elif kind == "EXTENDED_SYS_STATE":
            changes = {"landed_state": LANDED_STATES.get(message.landed_state, "UNDEFINED")}
        elif kind == "ATTITUDE":
            attitude = (message.roll, message.pitch, message.yaw)
            changes = {"attitude": attitude, "rates": (message.rollspeed, message.pitchspeed, message.yawspeed)}
            with self._state_lock:
                self._attitudes.append((time.time(), attitude))
        elif kind == "GLOBAL_POSITION_INT":
            changes = {"alt_rel_m": message.relative_alt / 1000.0, "alt_amsl_m": message.alt / 1000.0,
                       "lat_deg": message.lat / 1e7, "lon_deg": message.lon / 1e7}
        elif kind == "LOCAL_POSITION_NED":
            position = (message.x, message.y, message.z)
            changes = {"position_ned": position, "velocity_ned": (message.vx, message.vy, message.vz)}
            with self._state_lock:
                self._positions.append((time.time(), position, (message.vx, message.vy, message.vz)))
        elif kind == "DISTANCE_SENSOR":
            if message.orientation != mavlink2.MAV_SENSOR_ROTATION_PITCH_270:
                return True  # only the downward rangefinder gives the height above the pad
            cm = message.current_distance
            valid = message.min_distance <= cm <= message.max_distance and cm > 0
            changes = {"rangefinder_m": cm / 100.0 if valid else None}
        elif kind == "HOME_POSITION":
            changes = {"home": (message.latitude / 1e7, message.longitude / 1e7, message.altitude / 1000.0)}
        if changes is not None:
            self._heard_stream(kind, now, changes)
        return True

    def _handle_heartbeat(self, message: mavlink2.MAVLink_message, src: tuple[int, int], now: float) -> bool:
        if message.autopilot == mavlink2.MAV_AUTOPILOT_INVALID:
            return False  # a GCS, companion or gimbal: not a flight controller
        if self.settings.target_system is not None and src[0] != self.settings.target_system:
            return False
        if self._fc is None:
            self._fc = src
            log.info("flight link %s: following autopilot %d/%d", self.endpoint.url, *src)
        elif src != self._fc:
            last = self._last_heartbeat_mono
            if self.settings.target_system is not None or (last is not None and now - last <= self.settings.reboot_gap_s):
                return False  # another autopilot while ours speaks: not ours
            # Ours went silent and an autopilot with another id speaks: the vehicle came back
            # with a new system id (or was replaced). Follow it, forget what the old one said.
            old, self._fc = self._fc, src
            self._rebooted(f"autopilot {old[0]}/{old[1]} went silent, {src[0]}/{src[1]} speaks")
        last = self._last_heartbeat_mono
        self._last_heartbeat_mono = now
        if last is not None and self.state.link and now - last > self.settings.reboot_gap_s:
            # A gap shorter than the link timeout can still be a reboot (ArduCopter SITL: 2.2 s), which
            # resets every stream to its default: ask again; the streams' timeouts clear what stopped.
            log.warning("flight link %s: heartbeat gap of %.1f s: asking for every stream again",
                        self.endpoint.url, now - last)
            self._streams_wanted.set()
        armed = bool(message.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)
        mode = mode_name(message.autopilot, message.type, message.base_mode, message.custom_mode)
        was_up = self.state.link
        event = None if was_up else (LINK_RESTORED if self.counters["links_lost"] else LINK_UP)
        self._heard_mono["HEARTBEAT"] = now
        self._update(event=event, link=True, armed=armed, mode=mode, system_id=src[0],
                     autopilot=_AUTOPILOTS.get(message.autopilot, str(message.autopilot)),
                     last_heartbeat=time.time(), heard=self._heard_tuple())
        if event:
            self._streams_wanted.set()
            log.log(logging.WARNING if event == LINK_RESTORED else logging.INFO,
                    "flight link %s: %s (autopilot %d/%d)", self.endpoint.url, event, *src)
        return True

    def _heard_stream(self, kind: str, now: float, changes: dict[str, Any]) -> None:
        self._heard_mono[kind] = now
        self._retry_s.pop(kind, None)
        changes["heard"] = self._heard_tuple()
        missing = self.state.missing
        if kind in missing:
            changes["missing"] = tuple(m for m in missing if m != kind)
        self._update(quiet_keys=("heard",), **changes)

    def _heard_tuple(self) -> tuple[tuple[str, float], ...]:
        offset = time.time() - time.monotonic()
        return tuple(sorted((k, round(v + offset, 3)) for k, v in tuple(self._heard_mono.items())))

    def _rebooted(self, why: str) -> None:
        """The autopilot restarted: what it said before is void, and every stream must be asked for again."""
        self.counters["reboots"] += 1
        log.warning("flight link %s: autopilot rebooted (%s): asking for every stream again", self.endpoint.url, why)
        self._heard_mono = {k: v for k, v in self._heard_mono.items() if k == "HEARTBEAT"}
        self._have_battery_status = False
        with self._state_lock:
            self._attitudes.clear()
            self._positions.clear()
        cleared: dict[str, Any] = {f: None for stream, fields in STREAM_FIELDS.items() if stream != "HEARTBEAT" for f in fields}
        self._update(event=AUTOPILOT_REBOOTED, reboots=self.state.reboots + 1, boot_ms=None,
                     heard=self._heard_tuple(), **cleared)
        self._streams_wanted.set()

    def _update(self, *, event: str | None = None, quiet_keys: tuple[str, ...] = (), **changes: Any) -> None:
        with self._state_lock:
            old = self._state
            if not event and all(getattr(old, k) == v for k, v in changes.items() if k not in quiet_keys):
                if not quiet_keys:
                    return
                self._state = replace(old, **changes)  # only "heard" moved: no news for the listeners
                self._heard.notify_all()
                return
            new = replace(old, time=time.time(), event=event, **changes)
            self._state = new
            self._heard.notify_all()
        for listener in list(self._listeners):
            try:
                listener(new)
            except Exception:  # a listener's bug must not stop the reader
                log.exception("flight state listener failed")

    def _tick_loop(self) -> None:
        period = self.settings.heartbeat_period_s
        next_heartbeat = time.monotonic()
        while not self._stop.wait(_TICK_S):
            now = time.monotonic()
            last = self._last_heartbeat_mono
            if self.state.link and last is not None and now - last > self.settings.heartbeat_timeout_s:
                self.counters["links_lost"] += 1
                log.warning("flight link %s: link_lost (no heartbeat for %.1f s)", self.endpoint.url, now - last)
                # Nothing heard is current any more: every stream's fields become unknown with the link.
                self._heard_mono.clear()
                cleared: dict[str, Any] = {f: None for fields in STREAM_FIELDS.values() for f in fields}
                self._update(event=LINK_LOST, link=False, heard=(), **cleared)
            if now >= next_heartbeat:
                next_heartbeat = now + period
                self._send_heartbeat()
            if self._streams_wanted.is_set():
                self._streams_wanted.clear()
                self._request_streams(list(self._streams), now)
            elif self.state.link:
                self._check_streams(now)

    def _check_streams(self, now: float) -> None:
        """Expire the fields of every stream not heard within its timeout; ask again for what does not come."""
        expired: dict[str, Any] = {}
        missing = set(self.state.missing)
        again = []
        for name, (_, _, timeout) in self._streams.items():
            heard = self._heard_mono.get(name)
            if heard is not None and now - heard > timeout:
                self._heard_mono.pop(name, None)
                self.counters["streams_stopped"] += 1
                log.warning("flight link %s: %s stopped (nothing for %.1f s): its fields are unknown",
                            self.endpoint.url, name, now - heard)
                fields = STREAM_FIELDS[name]
                if name == "BATTERY_STATUS":
                    self._have_battery_status = False
                if name == "SYS_STATUS" and not self._have_battery_status:
                    fields += STREAM_FIELDS["BATTERY_STATUS"]
                expired.update({f: None for f in fields})
                missing.add(name)  # it stopped: missing now, and asked for again at once
                again.append(name)
                continue
            if heard is None:
                asked = self._asked_mono.get(name, 0.0)
                if now - asked > max(timeout, self._retry_s.get(name, 0.0)):
                    missing.add(name)
                    again.append(name)
        if expired or missing != set(self.state.missing):
            self._update(missing=tuple(sorted(missing)), heard=self._heard_tuple(), **expired)
        if again:
            for name in again:  # back off: a stream the autopilot lacks (no rangefinder) is not asked for at 10 Hz
                self._retry_s[name] = min(self.settings.stream_retry_max_s, max(1.0, 2 * self._retry_s.get(name, 0.5)))
            self._request_streams(again, now)

    # -- sending

    def _send_heartbeat(self) -> None:
        transport, mav = self._transport, self._mav
        if transport is None or mav is None or not transport.can_send:
            return  # udpin: nobody to talk to until the flight controller speaks
        try:
            self._send(mav.heartbeat_encode(
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                mavlink2.MAV_STATE_ACTIVE,
            ))
        except FlightLinkError as exc:
            log.debug("heartbeat not sent: %s", exc)

    def _request_streams(self, names: list[str], now: float) -> None:
        fc = self._fc
        if fc is None or self._mav is None:
            return
        for name in names:
            msg_id, hz, _ = self._streams[name]
            self._asked_mono[name] = now
            self.counters["stream_requests"] += 1
            self.commands.submit(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz), fc,
                                 label=f"{name} at {hz:g} Hz")

    def command(self, command: int, *params: float, label: str = "", timeout: float | None = 15.0) -> CommandOutcome:
        """Send one COMMAND_LONG to the autopilot and wait for its outcome (a CommandOutcome)."""
        fc = self._fc
        if fc is None:
            raise FlightLinkError(f"no autopilot heard on {self.endpoint.url}: nowhere to send a command")
        return self.commands.submit(command, params, fc, label=label).result(timeout)

    def send_landing_target(self, target: LandingTarget) -> None:
        """Send one LANDING_TARGET (MAVLink 2, vision fiducial, in the target's frame); raise FlightLinkError."""
        if self._mav is None:
            raise FlightLinkError(f"flight link {self.endpoint.url} is not set up")
        x, y, z = target.position or (0.0, 0.0, 0.0)
        message = self._mav.landing_target_encode(
            int(target.time * 1e6), target.target_num if 0 <= target.target_num <= 255 else 0,
            target.frame, target.angle_x, target.angle_y, target.distance,
            target.size_x, target.size_y, x, y, z, (1.0, 0.0, 0.0, 0.0),
            mavlink2.LANDING_TARGET_TYPE_VISION_FIDUCIAL, 1 if target.position is not None else 0,
        )
        self._send(message)

    def _send(self, message: mavlink2.MAVLink_message) -> None:
        with self._send_lock:
            if self._mav is None or self._transport is None:
                raise FlightLinkError(f"flight link {self.endpoint.url} is closed")
            try:
                self._mav.send(message)
            except FlightLinkError:
                self.counters["send_errors"] += 1
                raise
            except (struct.error, ValueError, TypeError) as exc:  # a field out of its wire range
                self.counters["send_errors"] += 1
                raise FlightLinkError(f"cannot pack {message.get_type()} for {self.endpoint.url}: {exc}") from exc
            self.counters["sent"] += 1
