"""A precision landing, end to end: marker scene -> detections over Zenoh -> FlightBridge -> autopilot -> touchdown.

:func:`run_landing_check` flies one landing and measures how far from the
marker the vehicle touched down. The autopilot is the fake flight controller
(in this process; its truth gives the camera's pose) or a real one at
``url`` (ArduCopter SITL; then the camera's pose is the autopilot's own
ATTITUDE and LOCAL_POSITION_NED, and the vehicle is armed and taken off in
GUIDED first). ``kgadapt flight land-check`` (kgadapt.sim.cli) runs it from the command line.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.landing_targets import CameraModel
from kgadapt.onboard.flight.mavlink import LinkSettings
from kgadapt.onboard.flight.mavlink_commands import CommandOutcome
from kgadapt.onboard.flight.site import SiteMarkers
from kgadapt.shared.errors import FlightLinkError
from kgadapt.sim.landing_scene import MarkerScene, fake_pose, horizontal_error, link_pose, run_detections

log = logging.getLogger(__name__)

CHECK_CAMERA = CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480)
CUSTOM = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


@dataclass(frozen=True, kw_only=True)
class LandingCheckSettings:
    rate_hz: float = 1.0  # detections a second
    marker_north: float = 2.5  # m from where LAND starts
    marker_east: float = 2.0
    marker_size_m: float = 0.5
    sizes_known: bool = True  # a site marker file gives the marker's size: the target goes with its position
    rangefinder: bool = True  # the (fake) vehicle has a downward rangefinder
    noise_px: float = 0.5  # detector corner noise (standard deviation, pixels)
    hold_s: float = 1.5
    resend_hz: float = 10.0
    alt_m: float = 10.0
    timeout_s: float = 60.0
    reboot_first: bool = False  # reboot the autopilot on the ground, then take off (the fake starts on the ground)
    url: str | None = None  # a real autopilot (SITL); None = the fake flight controller
    fake: dict = field(default_factory=dict)  # FakeFCSettings overrides (e.g. a faster LAND_SPEED for tests)


@dataclass(frozen=True)
class LandingResult:
    error_m: float  # horizontal distance from the marker at touchdown
    landed: bool
    acquired: bool | None  # the autopilot acquired the target (known for the fake)
    seconds: float
    detections: int
    targets_sent: int
    targets_resent: int
    streams_back_s: float | None = None  # after the reboot: from the reboot command to every stream sent at once
    origin_back_s: float | None = None  # ... and to LOCAL_POSITION_NED (ArduPilot sends it once its EKF has an origin)
    max_gap_s: float | None = None  # longest time without a LANDING_TARGET from the target's acquisition to touchdown

    def as_dict(self) -> dict:
        return self.__dict__.copy()


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_landing_check(session, settings: LandingCheckSettings, *, robot: str = "landcheck") -> LandingResult:
    from kgadapt.onboard.flight.flight import BridgeSettings, CameraIntrinsics, FlightBridge
    from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState

    s = settings
    fc = None
    if s.url is None:
        port = _free_udp_port()
        url = f"udpin:127.0.0.1:{port}"
        fc = FakeFlightController(
            FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=2.0, sys_status_hz=0, battery_hz=0,
                           extended_state_hz=0, rangefinder=s.rangefinder, drain_pct_per_min=0.0, **s.fake),
            VehicleState(mode="LOITER") if s.reboot_first else
            VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=s.alt_m),
        )
    else:
        url = s.url
    cam = CHECK_CAMERA
    bridge = FlightBridge(BridgeSettings(
        robot=robot, intrinsics=CameraIntrinsics(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy), camera=cam,
        markers=SiteMarkers(site="check", sizes_m={7: s.marker_size_m}) if s.sizes_known else None,
        link=LinkSettings(url=url), hold_s=s.hold_s, resend_hz=s.resend_hz,
    ))
    stop = threading.Event()
    publisher: threading.Thread | None = None
    started = time.monotonic()
    try:
        bridge.setup(session)
        if fc is not None:
            fc.setup()
        link = bridge.link
        link.wait_for_heartbeat(10)
        _wait(lambda: link.state.position_ned is not None and link.state.attitude is not None, 10, "position")
        streams_back_s, origin_back_s = _reboot(link) if s.reboot_first else (None, None)
        if fc is None or s.reboot_first:
            _take_off(link, s.alt_m)
        start = link.state.position_ned
        scene = MarkerScene(cam, north=start[0] + s.marker_north, east=start[1] + s.marker_east,
                            size_m=s.marker_size_m)
        pose = fake_pose(fc) if fc is not None else link_pose(link)
        publisher = threading.Thread(
            target=run_detections, args=(session, robot, scene, pose),
            kwargs=dict(rate_hz=s.rate_hz, stop=stop, noise_px=s.noise_px),
            name="landing-check-detections", daemon=True)
        publisher.start()
        started = time.monotonic()
        outcome = link.command(mavlink2.MAV_CMD_DO_SET_MODE, CUSTOM, 9, label="LAND")
        if outcome is not CommandOutcome.ACCEPTED:
            raise FlightLinkError(f"the autopilot did not take LAND: {outcome.value}")
        landed = _wait(lambda: link.state.landed_state == "ON_GROUND", s.timeout_s, "touchdown", fail=False)
        final = fc.vehicle.position_ned if fc is not None else link.state.position_ned
        landed_at = time.time()
        if fc is not None:  # the fake says when its estimator acquired the target, and what it received
            acquired_at = next((t for t, text in fc.text_times if text == "PrecLand: Init Complete"), None)
            times = [m.time for m in fc.received("LANDING_TARGET")]
        else:  # a real autopilot: from the first target sent
            times = list(bridge.sent_times)
            acquired_at = times[0] if times else None
        return LandingResult(
            error_m=horizontal_error(scene.north, scene.east, final), landed=bool(landed),
            acquired=(fc.precland.counters["acquired"] > 0) if fc is not None else None,
            seconds=time.monotonic() - started, detections=bridge.counters["detections"],
            targets_sent=bridge.counters["targets_sent"], targets_resent=bridge.counters["targets_resent"],
            streams_back_s=streams_back_s, origin_back_s=origin_back_s,
            max_gap_s=_max_gap(times, acquired_at, landed_at),
        )
    finally:
        stop.set()
        if publisher is not None:
            publisher.join(timeout=5)
        bridge.shutdown()
        if fc is not None:
            fc.shutdown()


def _max_gap(times: list[float], start: float | None, end: float) -> float | None:
    """The longest interval without a LANDING_TARGET between ``start`` and ``end`` (None: never started)."""
    if start is None:
        return None
    inside = [start, *(t for t in times if start < t < end), end]
    return max(b - a for a, b in zip(inside, inside[1:]))


def _reboot(link) -> tuple[float, float]:
    """Reboot the autopilot (on the ground); seconds until the link saw it and every stream it sends at once
    came back, and until LOCAL_POSITION_NED came back (ArduPilot: once its EKF has an origin again)."""
    # The link sees a reboot by the autopilot's clock going back: let it run past what a restart shows first.
    _wait(lambda: (link.state.boot_ms or 0) > 2000, 10, "2 s of autopilot uptime")
    reboots = link.state.reboots
    started = time.monotonic()
    outcome = link.command(mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, label="reboot")
    if outcome is not CommandOutcome.ACCEPTED:
        raise FlightLinkError(f"the autopilot refused to reboot: {outcome.value}")
    # Not DISTANCE_SENSOR (not on every vehicle); HOME_POSITION and LOCAL_POSITION_NED come once there is an origin.
    later = {"DISTANCE_SENSOR", "HOME_POSITION", "LOCAL_POSITION_NED"}
    wanted = {name for name, _ in link.settings.stream_rates if name not in later}
    _wait(lambda: link.state.reboots > reboots, 30, "reboot seen")
    _wait(lambda: wanted <= set(dict(link.state.heard)), 30, "every stream after the reboot")
    at_once = time.monotonic() - started
    _wait(lambda: link.state.position_ned is not None, 120, "a local position after the reboot")
    return at_once, time.monotonic() - started


def _take_off(link, alt_m: float) -> None:
    """GUIDED, arm, take off to ``alt_m`` (a real autopilot: each command acknowledged)."""
    for label, command, params in (
        ("GUIDED", mavlink2.MAV_CMD_DO_SET_MODE, (CUSTOM, 4)),
        ("arm", mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (1,)),
        ("take-off", mavlink2.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, alt_m)),
    ):
        deadline = time.monotonic() + 60  # SITL refuses arming until its EKF has settled
        while (outcome := link.command(command, *params, label=label)) is not CommandOutcome.ACCEPTED:
            if time.monotonic() > deadline:
                raise FlightLinkError(f"the autopilot refused {label}: {outcome.value}")
            time.sleep(2)
    _wait(lambda: (link.state.alt_rel_m or 0) > alt_m - 0.3, 60, f"climb to {alt_m} m")


def _wait(condition, timeout: float, what: str, *, fail: bool = True):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    if fail:
        raise FlightLinkError(f"landing check: no {what} within {timeout:g} s")
    return None
