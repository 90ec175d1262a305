"""A fake flight controller that speaks real MAVLink 2 over UDP (or TCP/serial).

It stands in for the autopilot in tests and the demo: it sends HEARTBEAT
(armed flag, ArduCopter custom mode), SYS_STATUS (main-loop load),
BATTERY_STATUS and EXTENDED_SYS_STATE (landed state) at an autopilot's usual
stream rates (changed by MAV_CMD_SET_MESSAGE_INTERVAL, acknowledged), runs a scripted final descent (mode LAND, landed state LANDING,
then ON_GROUND and disarmed), can be paused to simulate a lost link (nothing
sent, everything received dropped) and resumed, and records what it receives
(LANDING_TARGET, HEARTBEAT, ...) so tests can assert on it.

Run it alone with ``kgadapt flight fake-fc --url udpout:127.0.0.1:14550``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass, replace

from pymavlink.dialects.v20 import common as mavlink2

from onboard.mavlink import (
    COPTER_MODE_NUMBERS,
    LANDED_STATE_NUMBERS,
    UINT16_MAX,
    Endpoint,
    PacketParser,
    is_mavlink2,
    new_mavlink,
    open_transport,
)
from shared.errors import FlightLinkError

log = logging.getLogger(__name__)

_RECORD_LIMIT = 10_000  # per message type: a long demo run must not grow without bound


@dataclass(frozen=True, kw_only=True)
class FakeFCSettings:
    """Where the fake autopilot talks and how often it streams each message (Hz)."""

    url: str = "udpout:127.0.0.1:14550"
    system_id: int = 1
    component_id: int = mavlink2.MAV_COMP_ID_AUTOPILOT1
    heartbeat_hz: float = 1.0
    sys_status_hz: float = 2.0
    battery_hz: float = 1.0
    extended_state_hz: float = 1.0
    cells: int = 4  # battery cells in series (voltage = cells x per-cell voltage)
    drain_pct_per_min: float = 1.0  # battery drain while armed


@dataclass(frozen=True, kw_only=True)
class VehicleState:
    """What the fake autopilot reports."""

    armed: bool = False
    mode: str = "LOITER"  # an ArduCopter mode name
    landed_state: str = "ON_GROUND"  # UNDEFINED, ON_GROUND, IN_AIR, TAKEOFF, LANDING
    battery_pct: float = 90.0
    load_pct: float = 22.0  # main-loop load, percent

    def __post_init__(self) -> None:
        if self.mode not in COPTER_MODE_NUMBERS:
            raise FlightLinkError(f"unknown ArduCopter mode {self.mode!r}; known: {', '.join(COPTER_MODE_NUMBERS)}")
        if self.landed_state not in LANDED_STATE_NUMBERS:
            raise FlightLinkError(
                f"unknown landed state {self.landed_state!r}; known: {', '.join(LANDED_STATE_NUMBERS)}"
            )
        if not 0 <= self.battery_pct <= 100 or not 0 <= self.load_pct <= 100:
            raise FlightLinkError(f"battery_pct and load_pct must be 0..100, not {self.battery_pct}, {self.load_pct}")


@dataclass(frozen=True)
class Received:
    """One message the fake autopilot received."""

    time: float  # epoch seconds
    type: str
    fields: dict
    src_system: int
    src_component: int
    mavlink2: bool


class FakeFlightController:
    """A MAVLink 2 autopilot stand-in. ``setup()`` starts streaming, ``shutdown()`` stops."""

    def __init__(self, settings: FakeFCSettings = FakeFCSettings(), vehicle: VehicleState = VehicleState()) -> None:
        self.settings = settings
        self.endpoint = Endpoint.parse(settings.url)
        self._vehicle = vehicle
        self._lock = threading.Condition()
        self._received: dict[str, collections.deque[Received]] = {}
        self._paused = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._transport = None
        self._mav = None
        self._landing_until: float | None = None
        self.sent: collections.Counter[str] = collections.Counter()
        self._send_lock = threading.Lock()
        self._defaults = {"HEARTBEAT": settings.heartbeat_hz, "SYS_STATUS": settings.sys_status_hz,
                          "BATTERY_STATUS": settings.battery_hz, "EXTENDED_SYS_STATE": settings.extended_state_hz}
        self._periods: dict[str, float] = {}
        for name in self._defaults:
            self._restore_default(name)

    # -- lifecycle

    def setup(self) -> None:
        """Open the link and start streaming; raise FlightLinkError if the URL cannot be opened."""
        self._transport = open_transport(self.endpoint, timeout=5.0)
        self._parser = PacketParser(datagram=self._transport.datagram)
        self._mav = new_mavlink(self._transport, system_id=self.settings.system_id,
                                component_id=self.settings.component_id)
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._send_loop, name="fake-fc-send", daemon=True),
            threading.Thread(target=self._read_loop, name="fake-fc-read", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        log.info("fake flight controller %d/%d on %s", self.settings.system_id, self.settings.component_id,
                 self.endpoint.url)

    def shutdown(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads = []
        transport, self._transport = self._transport, None
        if transport is not None:
            transport.close()

    def __enter__(self) -> "FakeFlightController":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    @property
    def local_port(self) -> int:
        """The UDP port the fake autopilot's socket is bound to."""
        return self._transport.local_address[1]  # type: ignore[union-attr]

    # -- the script

    @property
    def vehicle(self) -> VehicleState:
        with self._lock:
            return self._vehicle

    @property
    def battery_v(self) -> float:
        """The pack voltage reported for the current charge (3.3 V empty .. 4.2 V full per cell)."""
        return round(self.settings.cells * (3.3 + 0.9 * self.vehicle.battery_pct / 100.0), 3)

    def set(self, **changes: object) -> VehicleState:
        """Change what is reported (armed, mode, landed_state, battery_pct, load_pct) from the next message on."""
        with self._lock:
            self._vehicle = replace(self._vehicle, **changes)  # type: ignore[arg-type]
            self._landing_until = None if "landed_state" in changes else self._landing_until
            return self._vehicle

    def land(self, descent_s: float) -> None:
        """Scripted final descent: LAND and LANDING now, ON_GROUND and disarmed after ``descent_s``."""
        with self._lock:
            self._vehicle = replace(self._vehicle, mode="LAND", landed_state="LANDING")
            self._landing_until = time.monotonic() + descent_s

    def pause(self) -> None:
        """Go silent both ways, as if the radio link were cut."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    # -- what we received

    def received(self, kind: str | None = None) -> list[Received]:
        """Messages received so far, of one type or all, oldest first."""
        with self._lock:
            if kind is not None:
                return list(self._received.get(kind, ()))
            return sorted((m for q in self._received.values() for m in q), key=lambda m: m.time)

    def clear_received(self) -> None:
        with self._lock:
            self._received.clear()

    def wait_for(self, kind: str, count: int = 1, timeout: float = 5.0) -> list[Received]:
        """Block until ``count`` messages of ``kind`` were received; raise FlightLinkError after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while len(self._received.get(kind, ())) < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    have = len(self._received.get(kind, ()))
                    raise FlightLinkError(f"fake flight controller got {have} of {count} {kind} within {timeout:g} s")
                self._lock.wait(left)
            return list(self._received[kind])

    # -- threads

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            transport = self._transport
            if transport is None:
                return
            try:
                chunk = transport.read(0.1)
            except Exception as exc:
                log.error("fake flight controller read failed: %s", exc)
                self._stop.wait(0.5)
                continue
            if chunk is None or self._paused.is_set():
                continue
            data, source = chunk
            messages = self._parser.feed(data)
            if messages:
                transport.accept_source(source)
            now = time.time()
            with self._lock:
                for message in messages:
                    record = Received(
                        time=now, type=message.get_type(),
                        fields={k: v for k, v in message.to_dict().items() if k != "mavpackettype"},
                        src_system=message.get_srcSystem(), src_component=message.get_srcComponent(),
                        mavlink2=is_mavlink2(message),
                    )
                    self._received.setdefault(record.type, collections.deque(maxlen=_RECORD_LIMIT)).append(record)
                self._lock.notify_all()
            for message in messages:
                if message.get_type() == "COMMAND_LONG" and message.target_system in (0, self.settings.system_id):
                    self._handle_command(message)

    def _send_loop(self) -> None:
        senders = {"HEARTBEAT": self._send_heartbeat, "SYS_STATUS": self._send_sys_status,
                   "BATTERY_STATUS": self._send_battery, "EXTENDED_SYS_STATE": self._send_extended_state}
        due = {name: time.monotonic() for name in senders}
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            self._advance(now - last)
            last = now
            with self._lock:
                periods = dict(self._periods)
            for name, send in senders.items():
                period = periods.get(name)
                if period is None or now < due[name]:
                    continue
                due[name] = max(due[name] + period, now)
                if not self._paused.is_set():
                    try:
                        send()
                    except FlightLinkError as exc:  # udpin before anyone spoke to us
                        log.debug("fake flight controller: %s", exc)
            waits = [due[n] for n in senders if periods.get(n) is not None]
            self._stop.wait(min(0.1, max(0.0, min(waits, default=now + 0.1) - time.monotonic())))

    def stream_rate(self, name: str) -> float | None:
        """The rate (Hz) at which ``name`` is streamed now; None if it is off."""
        with self._lock:
            period = self._periods.get(name)
        return None if period is None else 1.0 / period

    def _handle_command(self, message) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL changes a stream's rate, as an autopilot does; others are refused."""
        result = mavlink2.MAV_RESULT_UNSUPPORTED
        if message.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            kind = mavlink2.mavlink_map.get(int(message.param1))
            name = kind.msgname if kind is not None else None
            if name in self._defaults:
                interval_us = message.param2
                with self._lock:
                    if interval_us == -1:
                        self._periods.pop(name, None)
                    elif interval_us == 0:
                        self._restore_default(name)
                    elif interval_us > 0:
                        self._periods[name] = interval_us / 1e6
                result = mavlink2.MAV_RESULT_ACCEPTED
        try:
            self._send(self._mav.command_ack_encode(  # type: ignore[union-attr]
                message.command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent(),
            ))
        except FlightLinkError as exc:
            log.debug("fake flight controller: no COMMAND_ACK: %s", exc)

    def _restore_default(self, name: str) -> None:
        hz = self._defaults[name]
        if hz > 0:
            self._periods[name] = 1.0 / hz
        else:
            self._periods.pop(name, None)

    def _advance(self, elapsed: float) -> None:
        with self._lock:
            v = self._vehicle
            if self._landing_until is not None and time.monotonic() >= self._landing_until:
                self._landing_until = None
                v = replace(v, landed_state="ON_GROUND", armed=False)
            if v.armed and self.settings.drain_pct_per_min > 0:
                v = replace(v, battery_pct=max(0.0, v.battery_pct - self.settings.drain_pct_per_min * elapsed / 60.0))
            self._vehicle = v

    def _send(self, message) -> None:
        if self._transport is None or not self._transport.can_send:
            return
        with self._send_lock:  # the reader thread acknowledges commands while the sender streams
            self._mav.send(message)  # type: ignore[union-attr]
            self.sent[message.get_type()] += 1

    def _send_heartbeat(self) -> None:
        v = self.vehicle
        base_mode = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_STABILIZE_ENABLED
        if v.armed:
            base_mode |= mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink2.MAV_STATE_ACTIVE if v.armed else mavlink2.MAV_STATE_STANDBY
        self._send(self._mav.heartbeat_encode(  # type: ignore[union-attr]
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode,
            COPTER_MODE_NUMBERS[v.mode], status,
        ))

    def _send_sys_status(self) -> None:
        v = self.vehicle
        self._send(self._mav.sys_status_encode(  # type: ignore[union-attr]
            0, 0, 0, int(round(v.load_pct * 10)), int(round(self.battery_v * 1000)), -1,
            int(round(v.battery_pct)), 0, 0, 0, 0, 0, 0,
        ))

    def _send_battery(self) -> None:
        v = self.vehicle
        cell_mv = int(round(self.battery_v * 1000 / self.settings.cells))
        voltages = [cell_mv] * self.settings.cells + [UINT16_MAX] * (10 - self.settings.cells)
        self._send(self._mav.battery_status_encode(  # type: ignore[union-attr]
            0, mavlink2.MAV_BATTERY_FUNCTION_ALL, mavlink2.MAV_BATTERY_TYPE_LIPO, 2500, voltages,
            -1, -1, -1, int(round(v.battery_pct)),
        ))

    def _send_extended_state(self) -> None:
        v = self.vehicle
        self._send(self._mav.extended_sys_state_encode(  # type: ignore[union-attr]
            mavlink2.MAV_VTOL_STATE_UNDEFINED, LANDED_STATE_NUMBERS[v.landed_state],
        ))
