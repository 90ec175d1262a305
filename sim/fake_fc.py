"""A fake flight controller that speaks real MAVLink 2 and behaves like ArduCopter where the project relies on it.

It stands in for the autopilot in tests and the demo. Each behaviour below
follows ArduPilot's own code (read in ArduPilot/ardupilot, master, 2024-2025;
no code copied) and has a test in ``tests/flight/test_fake_fc_ardupilot.py``:

- **Streams** (libraries/GCS_MAVLink/GCS_Common.cpp, ``GCS_MAVLINK::set_message_interval``):
  MAV_CMD_SET_MESSAGE_INTERVAL with an interval sets a stream's rate, ``-1``
  stops it, ``0`` restores its default; a message it cannot stream gets
  MAV_RESULT_FAILED. Rates set this way are not kept: after a reboot every
  stream is back at its default (the ``*_hz`` settings play ArduCopter's
  ``SRn_*`` parameters; ArduCopter's own defaults stream nothing but
  HEARTBEAT on a companion port until asked). A stream given a new interval is
  first sent one interval later, not at once (``set_ap_message_interval``
  allocates its bucket with ``last_sent_ms = now``; re-asking for the same
  interval leaves its schedule alone): BATTERY_STATUS at 1 Hz is back about
  2.2 s after the first heartbeat of a reboot, as on SITL.
- **Streams that need an origin** (GCS_Common.cpp ``send_home_position``: nothing
  until ``AP::ahrs().home_is_set()``; ``send_local_position``: nothing while
  ``get_relative_position_NED_origin`` fails, i.e. before the EKF has an origin):
  after a reboot HOME_POSITION comes back ``home_after_reboot_s`` and
  LOCAL_POSITION_NED ``origin_after_reboot_s`` after boot (ArduCopter SITL: 19 s
  and 41 s), however early they were asked for; the others at once.
- **Commands acknowledged or refused** (GCS_Common.cpp ``handle_command_long_packet``,
  ``handle_preflight_reboot``; ArduCopter/GCS_Mavlink.cpp; ArduCopter/mode.cpp
  ``Mode::allows_arming``; ArduCopter/takeoff.cpp ``Mode::do_user_takeoff``):
  every COMMAND_LONG gets a COMMAND_ACK; unknown commands UNSUPPORTED; arming
  refused (FAILED) in LAND, RTL and AUTO, disarming refused in the air; take-off
  only in GUIDED, armed and on the ground; a reboot refused while armed and
  acknowledged before the autopilot goes silent (``reboot_s``, 2.2 s as measured
  on SITL), after which ``time_boot_ms`` restarts from 0.
- **Landed state and modes** (ArduCopter/GCS_Mavlink.cpp ``GCS_MAVLINK_Copter::landed_state``;
  ArduCopter/mode_land.cpp; ArduCopter/land_detector.cpp): ON_GROUND once landed,
  LANDING while in LAND (or RTL's final descent), TAKEOFF while climbing after a
  take-off, else IN_AIR; LAND descends at ``LAND_SPEED`` (0.5 m/s) below
  ``LAND_ALT_LOW`` (10 m) and faster above, and disarms on touchdown.
- **Precision landing** (libraries/AC_PrecLand/AC_PrecLand_MAVLink.cpp
  ``AC_PrecLand_MAVLink::handle_msg`` and ``update``; AC_PrecLand.cpp
  ``construct_pos_meas_using_rangefinder``, ``run_estimator``,
  ``check_ekf_init_timeout``, ``target_acquired``), with ``PLND_TYPE=1`` and
  ``PLND_EST_TYPE=1``: a LANDING_TARGET with ``position_valid=1`` counts only in
  MAV_FRAME_BODY_FRD with ``distance > 0`` (other frames are refused once with a
  text); angles become the line of sight ``(-tan(angle_y), tan(angle_x), 1)``;
  a measurement needs a height: the rangefinder's or the message's ``distance``
  — angles alone without either are not acquired; a line of sight is usable
  for 1 s; the estimator needs a measurement at least every 0.5 s for 2 s
  before the target counts as acquired ("Init Failed" otherwise), and the
  target is lost 2 s after the last measurement. LAND then steers over the
  target and does not descend while farther than ``PLND_XY_DIST_MAX`` (2.5 m).
- **The vehicle leans to move** (AC_PosControl.cpp ``accel_to_lean_angles``:
  pitch ``atan(-a_forward / g)``, roll ``atan(a_right cos(pitch) / g)``): LAND's
  correction towards the target accelerates at most ``xy_accel_ms2`` and the
  reported attitude follows the acceleration, so between two frames a second
  apart the marker moves across the image by many of its sides (what broke a
  steadiness rule kept in the image on SITL).

The estimator is a two-state Kalman filter per axis with AC_PrecLand's model
(PosVelEKF.cpp: predicted with the vehicle's change of velocity and
``PLND_ACC_P_NSE``; measurement variance ``(0.01 z + 0.02)^2``; a measurement
whose NIS is 3 or more is rejected, unless 3 in a row were), written from the
textbook, not from ArduPilot's generated code.

Simplified (documented, not relied on): ``PLND_LAG`` (measurements are taken as of
now) and the retry logic (``PLND_STRICT``) are not modelled, and the vehicle moves
kinematically with an acceleration limit (no wind, no attitude lag; tilt only from
LAND's horizontal acceleration, or when set).

Run it alone with ``kgadapt flight fake-fc --url udpout:127.0.0.1:14550``.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.geometry import body_to_ned
from kgadapt.onboard.flight.mavlink import (
    COPTER_MODE_NUMBERS,
    COPTER_MODES,
    LANDED_STATE_NUMBERS,
    UINT16_MAX,
    Endpoint,
    PacketParser,
    is_mavlink2,
    new_mavlink,
    open_transport,
)
from kgadapt.shared.errors import FlightLinkError

log = logging.getLogger(__name__)

_RECORD_LIMIT = 2_000  # per message type: bounded, and full within the soak's 5-minute warm-up for the 15 Hz streams
_STEP_S = 0.02  # physics and precision-landing update period (ArduCopter runs precland at 400 Hz)

# AC_PrecLand constants (AC_PrecLand.cpp, AC_PrecLand_MAVLink.cpp)
LOS_VALID_MS = 1000  # AC_PrecLand_MAVLink::update: a line of sight older than this is dropped
EKF_INIT_TIME_MS = 2000
EKF_INIT_SENSOR_MIN_UPDATE_MS = 500
LANDING_TARGET_TIMEOUT_MS = 2000

_ARMING_REFUSED_IN = {"LAND", "RTL", "AUTO", "SMART_RTL", "AUTO_RTL"}  # Mode::allows_arming false from a GCS


@dataclass(frozen=True, kw_only=True)
class FakeFCSettings:
    """Where the fake autopilot talks, how often it streams each message by default (Hz), what it carries."""

    url: str = "udpout:127.0.0.1:14550"
    system_id: int = 1
    component_id: int = mavlink2.MAV_COMP_ID_AUTOPILOT1
    heartbeat_hz: float = 1.0
    sys_status_hz: float = 2.0
    battery_hz: float = 1.0
    extended_state_hz: float = 1.0
    attitude_hz: float = 0.0  # 0: not streamed until asked (ArduCopter's default on a companion port)
    global_position_hz: float = 0.0
    local_position_hz: float = 0.0
    rangefinder_hz: float = 0.0
    home_hz: float = 0.0
    cells: int = 4  # battery cells in series (voltage = cells x per-cell voltage)
    drain_pct_per_min: float = 1.0  # battery drain while armed
    rangefinder: bool = True  # a downward rangefinder (RNGFND1_ORIENT=25)
    rangefinder_max_m: float = 40.0
    precland: bool = True  # PLND_ENABLED=1, PLND_TYPE=1 (MAVLink), PLND_EST_TYPE=1
    plnd_xy_dist_max_m: float = 2.5
    plnd_accel_noise: float = 2.5  # PLND_ACC_P_NSE
    land_speed_ms: float = 0.5  # LAND_SPEED 50 cm/s
    land_alt_low_m: float = 10.0  # LAND_ALT_LOW; above it LAND descends at descent_fast_ms
    descent_fast_ms: float = 1.5  # WPNAV_SPEED_DN
    climb_ms: float = 2.5  # WPNAV_SPEED_UP
    xy_speed_ms: float = 2.0  # how fast LAND repositions over the target
    xy_accel_ms2: float = 2.5  # ... accelerating at most this (WPNAV_ACCEL 250 cm/s/s): the vehicle leans to move
    rtl_speed_ms: float = 5.0
    reboot_s: float = 2.2  # silence during a reboot (ArduCopter SITL: 2.2 s heartbeat gap)
    home_after_reboot_s: float = 19.0  # HOME_POSITION only once home is set again (SITL: 19 s after a reboot)
    origin_after_reboot_s: float = 41.0  # LOCAL_POSITION_NED only once the EKF has an origin (SITL: 41 s)
    home: tuple[float, float, float] = (47.397742, 8.545594, 488.0)  # lat, lon, alt AMSL (m)
    # (command, attempts): answer that command TEMPORARILY_REJECTED while its COMMAND_LONG's confirmation
    # (the sender's attempt count) is below attempts, as a busy autopilot may.
    temporarily_reject: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True, kw_only=True)
class VehicleState:
    """What the fake autopilot reports (and where the vehicle is: NED metres from home, yaw rad)."""

    armed: bool = False
    mode: str = "LOITER"  # an ArduCopter mode name
    landed_state: str = "ON_GROUND"  # UNDEFINED, ON_GROUND, IN_AIR, TAKEOFF, LANDING
    battery_pct: float = 90.0
    load_pct: float = 22.0  # main-loop load, percent
    north: float = 0.0
    east: float = 0.0
    alt: float | None = None  # m above home; None: 10 m if in the air, else 0
    yaw: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in COPTER_MODE_NUMBERS:
            raise FlightLinkError(f"unknown ArduCopter mode {self.mode!r}; known: {', '.join(COPTER_MODE_NUMBERS)}")
        if self.landed_state not in LANDED_STATE_NUMBERS:
            raise FlightLinkError(
                f"unknown landed state {self.landed_state!r}; known: {', '.join(LANDED_STATE_NUMBERS)}"
            )
        if not 0 <= self.battery_pct <= 100 or not 0 <= self.load_pct <= 100:
            raise FlightLinkError(f"battery_pct and load_pct must be 0..100, not {self.battery_pct}, {self.load_pct}")
        if self.alt is None:
            object.__setattr__(self, "alt", 0.0 if self.landed_state in ("ON_GROUND", "UNDEFINED") else 10.0)
        if not 0 <= self.alt < 10_000:
            raise FlightLinkError(f"alt must be 0..10000 m above home, not {self.alt}")

    @property
    def position_ned(self) -> tuple[float, float, float]:
        return (self.north, self.east, -float(self.alt or 0.0))


@dataclass(frozen=True)
class Received:
    """One message the fake autopilot received."""

    time: float  # epoch seconds
    type: str
    fields: dict
    src_system: int
    src_component: int
    mavlink2: bool


@dataclass
class PrecLandState:
    """What the fake's AC_PrecLand knows (times in ms of the fake's boot clock)."""

    los_body: tuple[float, float, float] | None = None
    los_ms: int = -10**9
    distance: float = 0.0
    consumed_ms: int = -10**9
    initialized: bool = False
    init_ms: int = 0
    last_update_ms: int = -10**9
    acquired: bool = False
    target_ne: tuple[float, float] | None = None  # where the estimator puts the target, NE metres from home
    axes: list = field(default_factory=list)  # one _Axis per N and E: the estimator's state
    outliers: int = 0
    counters: dict = field(default_factory=lambda: collections.Counter())


class _Axis:
    """One axis of the target estimator: the target's position and velocity relative to the vehicle.

    A textbook two-state Kalman filter with the model of AC_PrecLand's PosVelEKF (predicted
    with the vehicle's change of velocity, position measurements with their variance).
    """

    def __init__(self, pos: float, pos_var: float, vel: float, vel_var: float) -> None:
        self.x = [pos, vel]
        self.p = [[pos_var, 0.0], [0.0, vel_var]]

    def predict(self, dt: float, dvel: float, dvel_noise: float) -> None:
        (p00, p01), (_, p11) = self.p
        self.x = [self.x[0] + dt * self.x[1], self.x[1] + dvel]
        self.p = [[p00 + dt * (2 * p01 + dt * p11), p01 + dt * p11], [p01 + dt * p11, p11 + dvel_noise ** 2]]

    def nis(self, z: float, r: float) -> float:
        return (z - self.x[0]) ** 2 / (self.p[0][0] + r)

    def fuse(self, z: float, r: float) -> None:
        (p00, p01), (_, p11) = self.p
        s = p00 + r
        k0, k1 = p00 / s, p01 / s
        innovation = z - self.x[0]
        self.x = [self.x[0] + k0 * innovation, self.x[1] + k1 * innovation]
        self.p = [[(1 - k0) * p00, (1 - k0) * p01], [(1 - k0) * p01, p11 - k1 * p01]]


class FakeFlightController:
    """A MAVLink 2 autopilot stand-in. ``setup()`` starts streaming, ``shutdown()`` stops."""

    def __init__(self, settings: FakeFCSettings = FakeFCSettings(), vehicle: VehicleState = VehicleState()) -> None:
        self.settings = settings
        self.endpoint = Endpoint.parse(settings.url)
        self._boot_vehicle = vehicle
        self._vehicle = vehicle
        self._lock = threading.Condition()
        self._received: dict[str, collections.deque[Received]] = {}
        self._counts: collections.Counter[str] = collections.Counter()  # all ever received (the deques are capped)
        self._paused = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._transport = None
        self._mav = None
        self._scripted_descent_ms: float | None = None
        self._takeoff_alt: float | None = None
        self.sent: collections.Counter[str] = collections.Counter()
        self.sent_times: dict[str, collections.deque[float]] = {}  # per message type: when each was sent (epoch s)
        self.texts: list[str] = []  # STATUSTEXTs sent, like "PrecLand: Init Failed"
        self.text_times: list[tuple[float, str]] = []  # ... with when (epoch s)
        self._send_lock = threading.Lock()
        self._defaults = {
            "HEARTBEAT": settings.heartbeat_hz, "SYS_STATUS": settings.sys_status_hz,
            "BATTERY_STATUS": settings.battery_hz, "EXTENDED_SYS_STATE": settings.extended_state_hz,
            "ATTITUDE": settings.attitude_hz, "GLOBAL_POSITION_INT": settings.global_position_hz,
            "LOCAL_POSITION_NED": settings.local_position_hz, "DISTANCE_SENSOR": settings.rangefinder_hz,
            "HOME_POSITION": settings.home_hz,
        }
        self._periods: dict[str, float] = {}
        for name in self._defaults:
            self._restore_default(name)
        self._boot_mono = time.monotonic()
        self._home_at = self._origin_at = self._boot_mono  # powered on ready: home and origin known
        self._first_due: dict[str, float] = {}  # stream -> when a newly set interval first sends it
        self._rebooting_until: float | None = None
        self.reboots = 0
        self.precland = PrecLandState()
        self._drop_commands = 0
        self._velocity = (0.0, 0.0)  # NE m/s over the last step, and its change: what the estimator predicts with
        self._dvel = (0.0, 0.0)

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
    def boot_ms(self) -> int:
        return int((time.monotonic() - self._boot_mono) * 1000)

    @property
    def battery_v(self) -> float:
        """The pack voltage reported for the current charge (3.3 V empty .. 4.2 V full per cell)."""
        return round(self.settings.cells * (3.3 + 0.9 * self.vehicle.battery_pct / 100.0), 3)

    def set(self, **changes: object) -> VehicleState:
        """Change what is reported (armed, mode, landed_state, battery_pct, load_pct, position) from now on."""
        with self._lock:
            self._vehicle = replace(self._vehicle, **changes)  # type: ignore[arg-type]
            if "landed_state" in changes:
                self._scripted_descent_ms = None
            return self._vehicle

    def land(self, descent_s: float) -> None:
        """Scripted final descent: LAND and LANDING now, touch down (ON_GROUND, disarmed) after ``descent_s``."""
        with self._lock:
            v = self._vehicle
            self._vehicle = replace(v, mode="LAND", landed_state="LANDING")
            self._scripted_descent_ms = max(0.01, float(v.alt or 0.0)) / max(descent_s, 1e-3)

    def reboot(self) -> None:
        """Reboot now, as MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN would (without the armed check)."""
        with self._lock:
            self._rebooting_until = time.monotonic() + self.settings.reboot_s

    def pause(self) -> None:
        """Go silent both ways, as if the radio link were cut."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    @property
    def rebooting(self) -> bool:
        return self._rebooting_until is not None

    def set_stream(self, name: str, hz: float | None) -> None:
        """Stream ``name`` at ``hz`` (None: stop it), as if the autopilot had been told so."""
        with self._lock:
            if hz is None:
                self._periods.pop(name, None)
            else:
                self._periods[name] = 1.0 / hz

    def drop_commands(self, count: int) -> None:
        """Let the next ``count`` COMMAND_LONGs go unanswered, as if lost on the radio."""
        with self._lock:
            self._drop_commands = count

    def stream_rate(self, name: str) -> float | None:
        """The rate (Hz) at which ``name`` is streamed now; None if it is off."""
        with self._lock:
            period = self._periods.get(name)
        return None if period is None else 1.0 / period

    # -- what we received

    def received(self, kind: str | None = None) -> list[Received]:
        """Messages received so far, of one type or all, oldest first."""
        with self._lock:
            if kind is not None:
                return list(self._received.get(kind, ()))
            return sorted((m for q in self._received.values() for m in q), key=lambda m: m.time)

    def received_count(self, kind: str) -> int:
        """How many messages of ``kind`` arrived since start (``received()`` keeps only the last 10,000)."""
        with self._lock:
            return self._counts[kind]

    def clear_received(self) -> None:
        with self._lock:
            self._received.clear()
            self._counts.clear()

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
            if chunk is None or self._paused.is_set() or self._rebooting_until is not None:
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
                    self._counts[record.type] += 1
                self._lock.notify_all()
            for message in messages:
                kind = message.get_type()
                if kind == "COMMAND_LONG" and message.target_system in (0, self.settings.system_id):
                    self._handle_command(message)
                elif kind == "LANDING_TARGET":
                    self._handle_landing_target(message)

    def _send_loop(self) -> None:
        senders = {"HEARTBEAT": self._send_heartbeat, "SYS_STATUS": self._send_sys_status,
                   "BATTERY_STATUS": self._send_battery, "EXTENDED_SYS_STATE": self._send_extended_state,
                   "ATTITUDE": self._send_attitude, "GLOBAL_POSITION_INT": self._send_global_position,
                   "LOCAL_POSITION_NED": self._send_local_position, "DISTANCE_SENSOR": self._send_distance,
                   "HOME_POSITION": self._send_home}
        due = {name: time.monotonic() for name in senders}
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            self._advance(now - last, now)
            last = now
            with self._lock:
                periods = dict(self._periods)
                first_due, self._first_due = self._first_due, {}
            due.update(first_due)
            silent = self._paused.is_set() or self._rebooting_until is not None
            for name, send in senders.items():
                period = periods.get(name)
                if period is None or now < due[name]:
                    continue
                due[name] = max(due[name] + period, now)
                if not silent:
                    try:
                        send()
                    except FlightLinkError as exc:  # udpin before anyone spoke to us
                        log.debug("fake flight controller: %s", exc)
            waits = [due[n] for n in senders if periods.get(n) is not None]
            self._stop.wait(min(_STEP_S, max(0.0, min(waits, default=now + _STEP_S) - time.monotonic())))

    # -- commands (GCS_Common.cpp handle_command_long_packet and the handlers it calls)

    def _handle_command(self, message) -> None:
        command = message.command
        with self._lock:
            if self._drop_commands > 0:
                self._drop_commands -= 1
                return
        handlers = {
            mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mavlink2.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            mavlink2.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink2.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            mavlink2.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink2.MAV_CMD_NAV_LAND: lambda m: self._cmd_set_mode_name("LAND"),
            mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: self._cmd_reboot,
        }
        handler = handlers.get(command)
        busy = dict(self.settings.temporarily_reject).get(command, 0)
        if message.confirmation < busy:
            self._ack(message, mavlink2.MAV_RESULT_TEMPORARILY_REJECTED)
            return
        result = mavlink2.MAV_RESULT_UNSUPPORTED if handler is None else handler(message)
        self._ack(message, result)
        if command == mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and result == mavlink2.MAV_RESULT_ACCEPTED:
            self.reboot()  # the ack goes out before the autopilot goes silent

    def _ack(self, message, result: int) -> None:
        try:
            self._send(self._mav.command_ack_encode(  # type: ignore[union-attr]
                message.command, result, 0, 0, message.get_srcSystem(), message.get_srcComponent(),
            ))
        except FlightLinkError as exc:
            log.debug("fake flight controller: no COMMAND_ACK: %s", exc)

    def _cmd_set_message_interval(self, message) -> int:
        kind = mavlink2.mavlink_map.get(int(message.param1))
        name = kind.msgname if kind is not None else None
        if name not in self._defaults:
            return mavlink2.MAV_RESULT_FAILED  # set_mavlink_message_id_interval: no such stream here
        interval_us = int(message.param2)
        with self._lock:
            before = self._periods.get(name)
            if interval_us == -1:
                self._periods.pop(name, None)
            elif interval_us == 0:
                self._restore_default(name)
            else:
                self._periods[name] = min(max(interval_us, 1000), 60_000_000) / 1e6
            period = self._periods.get(name)
            if period is not None and period != before:  # a new bucket: first sent one interval from now
                self._first_due[name] = time.monotonic() + period
        return mavlink2.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, message) -> int:
        kind = mavlink2.mavlink_map.get(int(message.param1))
        sender = {"HOME_POSITION": self._send_home, "EXTENDED_SYS_STATE": self._send_extended_state,
                  "ATTITUDE": self._send_attitude}.get(kind.msgname if kind is not None else "")
        if sender is None:
            return mavlink2.MAV_RESULT_FAILED
        sender()
        return mavlink2.MAV_RESULT_ACCEPTED

    def _cmd_arm_disarm(self, message) -> int:
        v = self.vehicle
        if message.param1 == 1.0:
            if v.mode in _ARMING_REFUSED_IN:
                return mavlink2.MAV_RESULT_FAILED
            self.set(armed=True)
            return mavlink2.MAV_RESULT_ACCEPTED
        if message.param1 == 0.0:
            if v.landed_state != "ON_GROUND" and int(message.param2) != 21196:  # 21196: forced
                return mavlink2.MAV_RESULT_FAILED
            self.set(armed=False)
            return mavlink2.MAV_RESULT_ACCEPTED
        return mavlink2.MAV_RESULT_DENIED

    def _cmd_set_mode(self, message) -> int:
        if not int(message.param1) & mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mavlink2.MAV_RESULT_UNSUPPORTED
        name = COPTER_MODES.get(int(message.param2))
        return mavlink2.MAV_RESULT_FAILED if name is None else self._cmd_set_mode_name(name)

    def _cmd_set_mode_name(self, name: str) -> int:
        with self._lock:
            v = self._vehicle
            landed = v.landed_state
            if v.alt > 0 and name in ("LAND",):
                landed = "LANDING"
            elif v.alt > 0 and landed == "LANDING":
                landed = "IN_AIR"
            self._vehicle = replace(v, mode=name, landed_state=landed)
        return mavlink2.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, message) -> int:
        v = self.vehicle
        if v.mode != "GUIDED" or not v.armed or v.landed_state != "ON_GROUND" or not message.param7 > 0:
            return mavlink2.MAV_RESULT_FAILED
        with self._lock:
            self._takeoff_alt = float(message.param7)
            self._vehicle = replace(self._vehicle, landed_state="TAKEOFF")
        return mavlink2.MAV_RESULT_ACCEPTED

    def _cmd_reboot(self, message) -> int:
        if message.param1 not in (1.0, 3.0):
            return mavlink2.MAV_RESULT_UNSUPPORTED
        if self.vehicle.armed:
            return mavlink2.MAV_RESULT_FAILED  # refuse reboot when armed
        return mavlink2.MAV_RESULT_ACCEPTED

    def _restore_default(self, name: str) -> None:
        hz = self._defaults[name]
        if hz > 0:
            self._periods[name] = 1.0 / hz
        else:
            self._periods.pop(name, None)

    # -- precision landing (AC_PrecLand_MAVLink::handle_msg)

    def _handle_landing_target(self, message) -> None:
        p = self.precland
        if not self.settings.precland:
            return
        p.counters["received"] += 1
        if message.position_valid == 1:
            if message.frame != mavlink2.MAV_FRAME_BODY_FRD:
                p.counters["frame_unsupported"] += 1
                if p.counters["frame_unsupported"] == 1:
                    self._text("Plnd: Frame not supported ")
                return
            if not message.distance > 0:
                p.counters["no_distance"] += 1
                return
            los = (message.x / message.distance, message.y / message.distance, message.z / message.distance)
        else:
            x, y = -math.tan(message.angle_y), math.tan(message.angle_x)
            norm = math.sqrt(x * x + y * y + 1.0)
            los = (x / norm, y / norm, 1.0 / norm)
        with self._lock:
            p.distance = float(message.distance)
            p.los_body = los
            p.los_ms = self.boot_ms

    def _precland_update(self, v: VehicleState, now_ms: int, dt: float, dvel: tuple[float, float],
                         vel: tuple[float, float]) -> None:
        """One AC_PrecLand::update (run_estimator, KALMAN_FILTER): predict, fuse a new line of sight, timers."""
        p = self.precland
        if p.los_body is not None and now_ms - p.los_ms > LOS_VALID_MS:
            p.los_body = None
        if p.initialized and p.axes:  # predict with the vehicle's change of velocity (PLND_ACC_P_NSE 2.5)
            for axis, dv in zip(p.axes, dvel):
                axis.predict(dt, -dv, self.settings.plnd_accel_noise * dt)
        if p.los_body is not None and p.los_ms != p.consumed_ms:
            p.consumed_ms = p.los_ms
            measured = self._measure(v, p.los_body, p.distance)
            if measured is None:
                p.counters["no_height"] += 1
            else:
                p.counters["measurements"] += 1
                rel_n, rel_e, down = measured
                r = (down * 0.01 + 0.02) ** 2  # the measurement variance AC_PrecLand gives a still vehicle
                if not p.initialized:
                    self._text("PrecLand: Target Found")
                    p.axes = [_Axis(rel_n, r, -vel[0], 4.0), _Axis(rel_e, r, -vel[1], 4.0)]
                    p.initialized, p.init_ms, p.last_update_ms, p.outliers = True, now_ms, now_ms, 0
                elif max(p.axes[0].nis(rel_n, r), p.axes[1].nis(rel_e, r)) < 3.0 or p.outliers >= 3:
                    p.axes[0].fuse(rel_n, r)
                    p.axes[1].fuse(rel_e, r)
                    p.outliers, p.last_update_ms = 0, now_ms
                else:
                    p.outliers += 1
                    p.counters["outliers"] += 1
        if now_ms - p.last_update_ms > LANDING_TARGET_TIMEOUT_MS:  # target_acquired()
            if p.acquired:
                self._text("PrecLand: Target Lost")
            p.initialized = p.acquired = False
        if not p.acquired and p.initialized:  # check_ekf_init_timeout()
            if now_ms - p.last_update_ms > EKF_INIT_SENSOR_MIN_UPDATE_MS:
                p.initialized = False
                p.counters["init_failed"] += 1
                self._text("PrecLand: Init Failed")
            elif now_ms - p.init_ms > EKF_INIT_TIME_MS:
                p.acquired = True
                p.counters["acquired"] += 1
                self._text("PrecLand: Init Complete")
        if p.acquired and p.axes:
            p.target_ne = (v.north + p.axes[0].x[0], v.east + p.axes[1].x[0])

    def _measure(self, v: VehicleState, los_body: tuple, distance: float) -> tuple[float, float, float] | None:
        """construct_pos_meas_using_rangefinder: the target relative to the vehicle (NED), None without a height."""
        los_ned = body_to_ned((v.roll, v.pitch, v.yaw), los_body)
        if los_body[2] <= 0 or los_ned[2] <= 0:
            return None  # not pointing down the approach vector
        height = self._rangefinder_m(v)
        if distance > 0:
            dist = distance
        elif height is not None and height > 0:
            dist = height / los_ned[2]
        else:
            return None  # angles alone, no rangefinder: ArduPilot cannot place the target
        return (los_ned[0] * dist, los_ned[1] * dist, los_ned[2] * dist)

    def _rangefinder_m(self, v: VehicleState) -> float | None:
        if not self.settings.rangefinder:
            return None
        tilt = math.cos(v.roll) * math.cos(v.pitch)
        slant = float(v.alt) / max(tilt, 0.1)
        return slant if 0.2 <= slant <= self.settings.rangefinder_max_m else None

    # -- the vehicle

    def _advance(self, elapsed: float, now: float) -> None:
        with self._lock:
            if self._rebooting_until is not None:
                if now >= self._rebooting_until:
                    self._boot()
                return
            v = self._vehicle
            if v.armed and self.settings.drain_pct_per_min > 0:
                v = replace(v, battery_pct=max(0.0, v.battery_pct - self.settings.drain_pct_per_min * elapsed / 60.0))
            vel = self._velocity
            if self.settings.precland:
                self._precland_update(v, self.boot_ms, elapsed, self._dvel, vel)
            moved = self._fly(v, elapsed)
            if elapsed > 0:
                new_vel = ((moved.north - v.north) / elapsed, (moved.east - v.east) / elapsed)
                self._dvel = (new_vel[0] - vel[0], new_vel[1] - vel[1])
                self._velocity = new_vel
            self._vehicle = moved

    def _fly(self, v: VehicleState, dt: float) -> VehicleState:
        """Kinematic ArduCopter: take-off in GUIDED, LAND (with precision landing), RTL."""
        alt = float(v.alt)
        if v.landed_state == "TAKEOFF" and self._takeoff_alt is not None:
            alt = min(self._takeoff_alt, alt + self.settings.climb_ms * dt)
            v = replace(v, alt=alt, landed_state="IN_AIR" if alt >= self._takeoff_alt else "TAKEOFF")
            if alt >= self._takeoff_alt:
                self._takeoff_alt = None
            return v
        landing = v.mode == "LAND" or (v.mode == "RTL" and math.hypot(v.north, v.east) < 0.5)
        if v.mode == "RTL" and not landing and alt > 0:
            d = math.hypot(v.north, v.east)
            speed = min(self.settings.rtl_speed_ms, 2.0 * d)  # home, slowing on the way in (no overshoot)
            north, east, roll, pitch = self._move(v, (-v.north / d * speed, -v.east / d * speed), dt)
            return replace(v, north=north, east=east, roll=roll, pitch=pitch)
        if not landing or alt <= 0 or v.landed_state == "ON_GROUND":
            return v
        descend = True
        p = self.precland
        want = (0.0, 0.0)  # LAND without a target holds its position
        if self.settings.precland and p.acquired and p.target_ne is not None:
            dn, de = p.target_ne[0] - v.north, p.target_ne[1] - v.east
            d = math.hypot(dn, de)
            if d > 1e-9:
                speed = min(self.settings.xy_speed_ms, 2.0 * d)  # towards the target, slowing on the way in
                want = (dn / d * speed, de / d * speed)
            descend = not (self.settings.plnd_xy_dist_max_m > 0 and d > self.settings.plnd_xy_dist_max_m)
        north, east, roll, pitch = self._move(v, want, dt)
        if self._scripted_descent_ms is not None:
            speed = self._scripted_descent_ms
        else:
            speed = self.settings.land_speed_ms if alt <= self.settings.land_alt_low_m else self.settings.descent_fast_ms
        if descend:
            alt = max(0.0, alt - speed * dt)
        if alt <= 0.0:  # land_detector: touchdown, then disarm (ArduCopter disarms after LAND completes)
            self._scripted_descent_ms = None
            return replace(v, north=north, east=east, alt=0.0, landed_state="ON_GROUND", armed=False, roll=0.0,
                           pitch=0.0)
        return replace(v, north=north, east=east, alt=alt, landed_state="LANDING", roll=roll, pitch=pitch)

    def _move(self, v: VehicleState, want: tuple[float, float], dt: float) -> tuple[float, float, float, float]:
        """One step towards velocity ``want`` (NE m/s) within the acceleration limit: position and lean angles.

        The lean follows the acceleration as AC_PosControl's accel_to_lean_angles turns one into the other.
        """
        vn, ve = self._velocity
        an, ae = (want[0] - vn) / max(dt, 1e-6), (want[1] - ve) / max(dt, 1e-6)
        accel = math.hypot(an, ae)
        limit = self.settings.xy_accel_ms2
        if accel > limit > 0:
            an, ae = an * limit / accel, ae * limit / accel
        vn, ve = vn + an * dt, ve + ae * dt
        forward = an * math.cos(v.yaw) + ae * math.sin(v.yaw)
        right = -an * math.sin(v.yaw) + ae * math.cos(v.yaw)
        pitch = math.atan(-forward / 9.80665)
        roll = math.atan(right * math.cos(pitch) / 9.80665)
        return v.north + vn * dt, v.east + ve * dt, roll, pitch

    def _boot(self) -> None:
        """The end of a reboot: clock from 0, streams at their defaults, vehicle as at power-on."""
        self._rebooting_until = None
        self._boot_mono = time.monotonic()
        self._home_at = self._boot_mono + self.settings.home_after_reboot_s
        self._origin_at = self._boot_mono + self.settings.origin_after_reboot_s
        self.reboots += 1
        for name in self._defaults:
            self._restore_default(name)
        v = self._vehicle
        self._vehicle = replace(self._boot_vehicle, north=v.north, east=v.east, alt=0.0, armed=False,
                                landed_state="ON_GROUND", yaw=v.yaw, battery_pct=v.battery_pct)
        self.precland = PrecLandState()
        self._takeoff_alt = self._scripted_descent_ms = None
        self._velocity = self._dvel = (0.0, 0.0)

    # -- sending

    def _text(self, text: str) -> None:
        self.texts.append(text)
        self.text_times.append((time.time(), text))
        try:
            self._send(self._mav.statustext_encode(mavlink2.MAV_SEVERITY_INFO, text.encode()))  # type: ignore[union-attr]
        except Exception as exc:
            log.debug("fake flight controller: no STATUSTEXT: %s", exc)

    def _send(self, message) -> None:
        if self._transport is None or not self._transport.can_send:
            return
        with self._send_lock:  # the reader thread acknowledges commands while the sender streams
            self._mav.send(message)  # type: ignore[union-attr]
            self.sent[message.get_type()] += 1
            self.sent_times.setdefault(message.get_type(), collections.deque(maxlen=256)).append(time.time())

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

    def _send_attitude(self) -> None:
        v = self.vehicle
        self._send(self._mav.attitude_encode(self.boot_ms, v.roll, v.pitch, v.yaw, 0.0, 0.0, 0.0))  # type: ignore[union-attr]

    def _latlon(self, v: VehicleState) -> tuple[int, int]:
        lat0, lon0, _ = self.settings.home
        lat = lat0 + math.degrees(v.north / 6378137.0)
        lon = lon0 + math.degrees(v.east / (6378137.0 * math.cos(math.radians(lat0))))
        return int(round(lat * 1e7)), int(round(lon * 1e7))

    def _send_global_position(self) -> None:
        v = self.vehicle
        lat, lon = self._latlon(v)
        self._send(self._mav.global_position_int_encode(  # type: ignore[union-attr]
            self.boot_ms, lat, lon, int(round((self.settings.home[2] + v.alt) * 1000)), int(round(v.alt * 1000)),
            0, 0, 0, int(round(math.degrees(v.yaw) % 360 * 100)),
        ))

    def _send_local_position(self) -> None:
        if time.monotonic() < self._origin_at:
            return  # send_local_position: no position relative to an origin yet
        v = self.vehicle
        n, e, d = v.position_ned
        vn, ve = self._velocity
        self._send(self._mav.local_position_ned_encode(self.boot_ms, n, e, d, vn, ve, 0.0))  # type: ignore[union-attr]

    def _send_distance(self) -> None:
        if not self.settings.rangefinder:
            return
        v = self.vehicle
        rng = self._rangefinder_m(v)
        max_cm = int(self.settings.rangefinder_max_m * 100)
        cm = max_cm + 1 if rng is None else int(round(rng * 100))  # out of range, as ArduPilot reports it
        self._send(self._mav.distance_sensor_encode(  # type: ignore[union-attr]
            self.boot_ms, 20, max_cm, min(cm, UINT16_MAX), mavlink2.MAV_DISTANCE_SENSOR_LASER, 0,
            mavlink2.MAV_SENSOR_ROTATION_PITCH_270, 0,
        ))

    def _send_home(self) -> None:
        if time.monotonic() < self._home_at:
            return  # send_home_position: home not set yet
        lat0, lon0, alt0 = self.settings.home
        self._send(self._mav.home_position_encode(  # type: ignore[union-attr]
            int(round(lat0 * 1e7)), int(round(lon0 * 1e7)), int(round(alt0 * 1000)), 0.0, 0.0, 0.0,
            (1.0, 0.0, 0.0, 0.0), 0.0, 0.0, 0.0,
        ))
