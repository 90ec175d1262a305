"""One flight on real ArduCopter SITL, the robot started as the README starts it; prints what was measured.

``test_sitl.py`` runs this module inside a network namespace of its own
(``ip netns exec NS python -m tests.flight.sitl_flight ...``): SITL binds its
TCP ports on every address, and the knowledge service its Zenoh router on
127.0.0.1:7447, so a namespace keeps both away from anything else on the
machine. What it starts there, each a real process:

- ``kgadapt knowledge load knowledge/models`` and ``kgadapt knowledge serve``
  (a store of its own): the camera's intrinsics (and the site) in the graph;
- ``kgadapt flight bridge --url udpin:...`` with nothing but the robot and the
  camera's name: what it knows comes from the graph, as on the README's robot;
- SITL (``arducopter``), its SERIAL1 a UDP client towards the bridge, through
  :class:`Relay`, which forwards every datagram both ways and notes when each
  message passed (the LANDING_TARGETs that reached ArduPilot, the streams that
  reached the bridge);
- :class:`GroundStation`, on SITL's TCP 5760 (SITL starts simulating only once
  something connects there): mode, arming, take-off, LAND, reboot, and
  SIM_STATE, the simulated vehicle's true attitude and position.

Detections of one marker of the site (on the ground, ``--north``/``--east`` m
from where LAND starts) are projected from that true pose through the graph's
intrinsics (:class:`kgadapt.sim.landing_scene.MarkerScene`, with corner noise)
and published over Zenoh as the detector publishes them. The landing error is
the true horizontal distance from the marker when ArduCopter disarms.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mav

from tests.support import REPO, Child

ROBOT = "quad1"  # the README's robot (knowledge serve's default)
CAMERA = "camera"  # the camera component of knowledge/models/components/cameras.rpsl
CAMERA_SIZE = (640, 480)  # its resolution there
SITE_FILE = REPO / "knowledge" / "models" / "sites" / "demo.site"
HOME = (-35.363261, 149.165230, 584.0, 0.0)  # lat, lon, alt AMSL (m), heading: ArduPilot's usual SITL home
EARTH_RADIUS_M = 6378137.0
PARAMS = {  # sim_vehicle.py would load Tools/autotest/default_params/copter.parm; the binary alone needs the frame
    "FRAME_CLASS": 1, "FRAME_TYPE": 1,
    "PLND_ENABLED": 1, "PLND_TYPE": 1, "PLND_EST_TYPE": 1, "PLND_YAW_ALIGN": 0, "PLND_LAG": 0.05,
    "PLND_XY_DIST_MAX": 2.5, "LAND_SPEED": 50,
    # What the pre-arm checks want of a vehicle that was set up: accelerometers calibrated (offsets and scales off
    # their defaults), compass offsets cancelling SITL's simulated magnetometer offset, a battery monitor.
    **{f"INS_ACC{n}{kind}_{axis}": value for n in ("", "2") for kind, value in (("OFFS", 0.001), ("SCAL", 1.001))
       for axis in "XYZ"},
    **{f"COMPASS_OFS{n}_{axis}": value for n in ("", "2", "3") for axis, value in zip("XYZ", (5, 13, -18))},
    "BATT_MONITOR": 4,
}
RANGEFINDER = {"RNGFND1_TYPE": 100, "RNGFND1_ORIENT": 25, "RNGFND1_MIN": 0.2, "RNGFND1_MAX": 40}
CUSTOM = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
GUIDED, LAND = 4, 9  # ArduCopter custom modes
KGADAPT = [sys.executable, "-m", "kgadapt", "--log-level", "INFO"]


def log(*parts: object) -> None:
    print(time.strftime("%H:%M:%S"), *parts, file=sys.stderr, flush=True)


class Relay:
    """SITL's SERIAL1 (a UDP client) <-> the bridge's udpin port, every datagram forwarded and its messages noted."""

    def __init__(self, bridge_port: int) -> None:
        self.to_bridge = ("127.0.0.1", bridge_port)
        self.sitl_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sitl_side.bind(("127.0.0.1", 0))
        self.port = self.sitl_side.getsockname()[1]
        self.bridge_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.bridge_side.bind(("127.0.0.1", 0))
        self.sitl_address: tuple[str, int] | None = None
        self.targets: list[tuple[float, object]] = []  # (monotonic, LANDING_TARGET) bridge -> ArduPilot
        self.to_bridge_log: list[tuple[float, str, int]] = []  # (monotonic, type, SITL's port) ArduPilot -> bridge
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="relay", daemon=True)

    def setup(self) -> None:
        self._thread.start()

    def shutdown(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sitl_side.close()
        self.bridge_side.close()

    def _run(self) -> None:
        from_sitl = mav.MAVLink(None)
        from_bridge = mav.MAVLink(None)
        from_sitl.robust_parsing = from_bridge.robust_parsing = True
        while not self._stop.is_set():
            ready, _, _ = select.select([self.sitl_side, self.bridge_side], [], [], 0.2)
            for sock in ready:
                data, address = sock.recvfrom(65536)
                now = time.monotonic()
                if sock is self.sitl_side:
                    self.sitl_address = address
                    self.bridge_side.sendto(data, self.to_bridge)
                    with self.lock:
                        self.to_bridge_log.extend((now, m.get_type(), address[1]) for m in _parse(from_sitl, data))
                elif self.sitl_address is not None:
                    self.sitl_side.sendto(data, self.sitl_address)
                    with self.lock:
                        self.targets.extend((now, m) for m in _parse(from_bridge, data)
                                            if m.get_type() == "LANDING_TARGET")


def _parse(parser: mav.MAVLink, data: bytes) -> list:
    try:
        return [m for m in (parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]
    except mav.MAVError:
        return []


@dataclass
class Truth:
    """The simulated vehicle's attitude and position (SIM_STATE) in NED metres from an origin on the ground."""

    origin: tuple[float, float, float] | None = None  # lat, lon (deg), alt AMSL (m) of the ground at home
    last: object | None = None

    def ned(self, msg=None) -> tuple[float, float, float] | None:
        msg = msg or self.last
        if msg is None or self.origin is None:
            return None
        lat0, lon0, alt0 = self.origin
        # lat_int/lon_int: the float lat/lon fields carry degE7 in 24 bits, about 0.3 m steps
        north = math.radians(msg.lat_int / 1e7 - lat0) * EARTH_RADIUS_M
        east = math.radians(msg.lon_int / 1e7 - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
        return north, east, -(msg.alt - alt0)

    def pose(self):
        msg = self.last
        position = self.ned(msg)
        if position is None:
            return None
        return (msg.roll, msg.pitch, msg.yaw), position


@dataclass
class GroundStation:
    """A MAVLink ground station on SITL's TCP 5760 (system 255): commands with their acks, and what it hears."""

    address: tuple[str, int] = ("127.0.0.1", 5760)
    truth: Truth = field(default_factory=Truth)
    armed: bool | None = None
    mode: int | None = None
    boot_ms: int = 0
    heard: list[tuple[float, str]] = field(default_factory=list)  # (monotonic, type) of every message
    texts: list[tuple[float, str]] = field(default_factory=list)
    acks: dict[int, int] = field(default_factory=dict)
    sock: socket.socket | None = None

    def __post_init__(self) -> None:
        self.lock = threading.Lock()
        self.mav = mav.MAVLink(self, srcSystem=255, srcComponent=190)
        self.mav.robust_parsing = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def write(self, data: bytes) -> None:  # pymavlink's file interface
        sock = self.sock
        if sock is not None:
            try:
                sock.sendall(data)
            except OSError:
                pass

    def connect(self, sitl: subprocess.Popen, timeout: float = 30.0) -> None:
        """Connect (again) and wait for a heartbeat; SITL listens again after each reboot."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if sitl.poll() is not None:
                raise RuntimeError(f"SITL exited with status {sitl.returncode} (see sitl.log)")
            self.close()
            try:
                self.sock = socket.create_connection(self.address, timeout=1.0)
            except OSError:
                time.sleep(0.05)
                continue
            self.sock.settimeout(0.2)
            self._stop.clear()
            start = len(self.heard)
            self._thread = threading.Thread(target=self._read, args=(self.sock,), name="gcs", daemon=True)
            self._thread.start()
            if self.wait(lambda: any(t == "HEARTBEAT" for _, t in self.heard[start:]), 3.0):
                return
        raise RuntimeError(f"no heartbeat from SITL on {self.address} within {timeout:g} s")

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def _read(self, sock: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            if not data:
                return
            now = time.monotonic()
            try:
                messages = self.mav.parse_buffer(data) or []
            except mav.MAVError:
                continue
            for m in messages:
                self._note(now, m)

    def _note(self, now: float, m) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA" or m.get_srcSystem() != 1 or m.get_srcComponent() != 1:
            return
        with self.lock:
            self.heard.append((now, kind))
        if kind == "SIM_STATE":
            self.truth.last = m
        elif kind == "HEARTBEAT":
            self.armed = bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = m.custom_mode
        elif kind == "STATUSTEXT":
            self.texts.append((now, m.text))
            log("SITL says:", m.text)
        elif kind == "COMMAND_ACK":
            self.acks[m.command] = m.result
        elif hasattr(m, "time_boot_ms"):
            self.boot_ms = m.time_boot_ms

    def command(self, command: int, *params: float, what: str, timeout: float = 60.0) -> None:
        """Send until ACCEPTED (SITL refuses arming until its estimate has settled); fail after ``timeout``."""
        deadline = time.monotonic() + timeout
        result = None
        while time.monotonic() < deadline:
            self.acks.pop(command, None)
            padded = (list(params) + [0.0] * 7)[:7]
            self.mav.command_long_send(1, 1, command, 0, *padded)
            if self.wait(lambda: command in self.acks, 1.0):
                result = self.acks[command]
                if result == mav.MAV_RESULT_ACCEPTED:
                    return
            time.sleep(1.0)
        raise RuntimeError(f"SITL did not accept {what} within {timeout:g} s (last result {result})")

    def stream(self, message_id: int, hz: float) -> None:
        self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, 1e6 / hz, what=f"message {message_id} at {hz} Hz",
                     timeout=10.0)

    @staticmethod
    def wait(condition, timeout: float, poll: float = 0.02):
        deadline = time.monotonic() + timeout
        while True:
            value = condition()
            if value or time.monotonic() >= deadline:
                return value
            time.sleep(poll)

    def first_heard_after(self, t0: float, kinds) -> dict[str, float]:
        first: dict[str, float] = {}
        with self.lock:
            for t, kind in self.heard:
                if t >= t0 and kind in kinds and kind not in first:
                    first[kind] = t
        return first


def site_marker(marker_id: int) -> float:
    """The printed size of ``marker_id`` as the site model in knowledge/models says it."""
    from kgadapt.onboard.flight.site import load_site

    size = load_site(SITE_FILE).size_of(marker_id)
    if size is None:
        raise SystemExit(f"{SITE_FILE} has no marker {marker_id}")
    return size


def intrinsics_from_graph(session):
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.onboard.flight.landing_targets import CameraModel

    rows = KnowledgeClient(session, ROBOT).query("camera_intrinsics", {"camera": CAMERA}, wait_s=15.0)
    width, height = CAMERA_SIZE
    return CameraModel(**{k: float(rows[0][k]) for k in ("fx", "fy", "cx", "cy")}, width=width, height=height)


def start_sitl(binary: str, workdir: Path, relay_port: int, rangefinder: bool) -> subprocess.Popen:
    params = {**PARAMS, **(RANGEFINDER if rangefinder else {"RNGFND1_TYPE": 0})}
    defaults = workdir / "kgadapt.parm"
    defaults.write_text("".join(f"{k} {v}\n" for k, v in params.items()))
    # -w (not --wipe): SITL drops -w from the command line it re-executes on a reboot, so parameters survive it.
    argv = [binary, "--model", "quad", "--speedup", "1", "-I0", "-w", "--home", ",".join(map(str, HOME)),
            "--defaults", str(defaults), "--serial1", f"udpclient:127.0.0.1:{relay_port}"]
    return subprocess.Popen(argv, cwd=workdir, stdin=subprocess.DEVNULL, stdout=open(workdir / "sitl.log", "w"),
                            stderr=subprocess.STDOUT)


def reboot_on_the_ground(gcs: GroundStation, sitl: subprocess.Popen, relay: Relay, bridge_streams: list[str]) -> dict:
    """Reboot ArduPilot; per stream the bridge asks for: when it reached the bridge and when ArduPilot first sent it.

    Times are from the first heartbeat after the reboot. "ArduPilot sent it" is the ground station's first copy
    (it asks for every one of them at once on its own link), so a stream ArduPilot cannot send yet (no origin)
    is told apart from one the bridge failed to ask for again.
    """
    gcs.wait(lambda: gcs.boot_ms > 5000, 60)
    gcs.wait(lambda: {"ATTITUDE", "HEARTBEAT"} <= {t for _, t, _ in relay.to_bridge_log}, 30)
    old_port = relay.sitl_address[1] if relay.sitl_address else None  # the restarted SITL sends from a new port
    sent = time.monotonic()
    gcs.command(mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, what="reboot", timeout=10)
    time.sleep(0.5)  # SITL re-executes itself right after its ack
    gcs.connect(sitl, timeout=60)
    ids = {name: getattr(mav, f"MAVLINK_MSG_ID_{name}") for name in bridge_streams}
    for name, message_id in ids.items():  # ask at once for all, without waiting on each ack
        gcs.mav.command_long_send(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, message_id, 2e5, 0, 0, 0, 0, 0)
    gcs.wait(lambda: set(bridge_streams) <= {k for _, k, port in relay.to_bridge_log if port != old_port}, 90)
    with relay.lock:
        first_heartbeat = min(t for t, k, port in relay.to_bridge_log if k == "HEARTBEAT" and port != old_port)
        last_old = max(t for t, k, port in relay.to_bridge_log if k == "HEARTBEAT" and port == old_port)
    with relay.lock:
        at_bridge: dict[str, float] = {}
        for t, kind, port in relay.to_bridge_log:
            if port != old_port and kind in ids and kind not in at_bridge:
                at_bridge[kind] = t
    at_gcs = gcs.first_heard_after(first_heartbeat, set(ids))
    streams = {}
    for name in bridge_streams:
        back = at_bridge.get(name)
        by_fc = min(x for x in (at_gcs.get(name), back) if x is not None) if back or at_gcs.get(name) else None
        streams[name] = {
            "back_s": None if back is None else round(back - first_heartbeat, 2),
            "ardupilot_first_s": None if by_fc is None else round(by_fc - first_heartbeat, 2),
            "after_ardupilot_s": None if back is None or by_fc is None else round(back - by_fc, 2),
        }
    return {"command_to_heartbeat_s": round(first_heartbeat - sent, 2), "silence_s": round(first_heartbeat - last_old, 2),
            "streams": streams}


def fly(args: argparse.Namespace) -> dict:
    from kgadapt.shared import session as zsession
    from kgadapt.sim.landing_scene import MarkerScene, run_detections

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    env = {"KGADAPT_STORE": f"embedded:{workdir / 'store'}", "XDG_DATA_HOME": str(workdir / "data")}
    children: list[Child] = []
    relay = sitl = session = None
    gcs = GroundStation()
    stop = threading.Event()
    publisher: threading.Thread | None = None
    result: dict = {"rate_hz": args.rate, "rangefinder": args.rangefinder, "bridge_args": args.bridge_arg}
    try:
        load = Child([*KGADAPT, "knowledge", "load", "knowledge/models"], "load", workdir, env=env)
        load.process.wait(timeout=120)
        assert load.process.returncode == 0, load.stderr()
        service = Child([*KGADAPT, "knowledge", "serve"], "service", workdir, env=env)
        children.append(service)
        service.wait_ready(60)
        bridge_port = _free_udp_port()
        bridge = Child([*KGADAPT, "flight", "bridge", "--robot", ROBOT, "--url", f"udpin:127.0.0.1:{bridge_port}",
                        *args.bridge_arg], "bridge", workdir, env=env)
        children.append(bridge)
        bridge.wait_ready(60)
        relay = Relay(bridge_port)
        relay.setup()
        sitl = start_sitl(args.sitl, workdir, relay.port, args.rangefinder)
        gcs.connect(sitl, timeout=60)
        log("SITL up")
        session = zsession.open_session(zsession.settings_from_env().with_defaults(
            mode="peer", connect=[zsession.DEFAULT_ENDPOINT]))
        camera = intrinsics_from_graph(session)
        if args.reboot_first:
            streams = ["ATTITUDE", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYS_STATUS", "BATTERY_STATUS",
                       "EXTENDED_SYS_STATE", "HOME_POSITION"] + (["DISTANCE_SENSOR"] if args.rangefinder else [])
            result["reboot"] = reboot_on_the_ground(gcs, sitl, relay, streams)
            log("reboot:", result["reboot"])
        gcs.stream(mav.MAVLINK_MSG_ID_SIM_STATE, 50)
        gcs.wait(lambda: gcs.truth.last is not None, 10)
        time.sleep(1.0)  # at rest: its altitude is the ground's
        rest = gcs.truth.last
        gcs.truth.origin = (rest.lat_int / 1e7, rest.lon_int / 1e7, rest.alt)
        for what, command, params in (("GUIDED", mav.MAV_CMD_DO_SET_MODE, (CUSTOM, GUIDED)),
                                      ("arming", mav.MAV_CMD_COMPONENT_ARM_DISARM, (1,)),
                                      ("take-off", mav.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, args.alt))):
            gcs.command(command, *params, what=what, timeout=120)
        if not gcs.wait(lambda: -(gcs.truth.ned() or (0, 0, 0))[2] > args.alt - 0.3, 60):
            raise RuntimeError(f"no climb to {args.alt} m")
        time.sleep(2.0)  # let it settle at altitude
        north, east, _ = gcs.truth.ned()
        size = site_marker(args.marker_id)
        scene = MarkerScene(camera, north=north + args.north, east=east + args.east, size_m=size,
                            marker_id=args.marker_id)
        published: dict = {}

        def publish() -> None:
            published.update(run_detections(session, ROBOT, scene, gcs.truth.pose, rate_hz=args.rate, stop=stop,
                                            noise_px=args.noise_px))

        publisher = threading.Thread(target=publish, name="detections", daemon=True)
        publisher.start()
        land_at = time.monotonic()
        gcs.command(mav.MAV_CMD_DO_SET_MODE, CUSTOM, LAND, what="LAND", timeout=10)
        log("LAND")
        landed = gcs.wait(lambda: gcs.armed is False, args.timeout, poll=0.05)
        touchdown = time.monotonic()
        final = gcs.truth.ned()
        result.update(
            landed=bool(landed), seconds=round(touchdown - land_at, 1),
            error_m=round(math.hypot(final[0] - scene.north, final[1] - scene.east), 3),
            offset_ne_m=[round(final[0] - scene.north, 3), round(final[1] - scene.east, 3)],
            marker={"id": args.marker_id, "size_m": size, "north": round(args.north, 2), "east": round(args.east, 2)},
            **_targets(relay, gcs, land_at, touchdown),
        )
        stop.set()
        publisher.join(timeout=5)
        result["detections"] = published  # sent, and frames with the marker out of the camera's view
        result["bridge"] = bridge.stderr().strip().splitlines()[-1]  # its last counters line
        return result
    finally:
        stop.set()
        if publisher is not None:
            publisher.join(timeout=5)
        gcs.close()
        if session is not None:
            session.close()
        if sitl is not None:
            sitl.terminate()
            sitl.wait(timeout=10)
        if relay is not None:
            relay.shutdown()
        for child in reversed(children):
            child.stop()
        result["load_average"] = os.getloadavg()


def _targets(relay: Relay, gcs: GroundStation, land_at: float, touchdown: float) -> dict:
    """What the LANDING_TARGETs that reached ArduPilot were, and ArduPilot's own word on them."""
    with relay.lock:
        targets = [(t, m) for t, m in relay.targets if land_at - 5 <= t <= touchdown]
    texts = [(round(t - land_at, 2), text) for t, text in gcs.texts if t >= land_at - 5]
    found = [t for t, text in gcs.texts if t >= land_at and "Target Found" in text]

    def max_gap(since: float | None) -> float | None:
        times = [t for t, _ in targets if since is not None and t >= since]
        if since is None or not times:
            return None
        return round(max([b - a for a, b in zip(times, times[1:])] + [touchdown - times[-1]]), 2)

    def gaps_over(since: float | None, limit: float = 1.0) -> list:
        """Where the gaps over ``limit`` lie: [from, to] in s after LAND (to: touchdown for the last)."""
        times = [t for t, _ in targets if since is not None and t >= since] + [touchdown]
        return [[round(a - land_at, 2), round(b - land_at, 2)] for a, b in zip(times, times[1:]) if b - a > limit]

    first = targets[0][0] if targets else None
    positioned = sum(1 for _, m in targets if m.position_valid)
    with_distance = sum(1 for _, m in targets if m.distance > 0)
    return {
        "targets": len(targets), "targets_positioned": positioned, "targets_with_distance": with_distance,
        "first_target_s": None if first is None else round(first - land_at, 2),
        "acquired_s": round(found[0] - land_at, 2) if found else None,
        "max_gap_after_acquired_s": max_gap(found[0] if found else None),
        "max_gap_after_first_target_s": max_gap(first),
        "statustext": texts,
        "gaps_over_1s": gaps_over(found[0] if found else None),
    }


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sitl", required=True, help="the arducopter binary (built for --board sitl)")
    parser.add_argument("--workdir", required=True)
    parser.add_argument("--rate", type=float, default=15.0, help="detections a second")
    parser.add_argument("--rangefinder", action="store_true", help="SITL's downward rangefinder")
    parser.add_argument("--reboot-first", action="store_true", help="reboot ArduPilot on the ground first")
    parser.add_argument("--marker-id", type=int, default=33, help="a marker of the site model")
    parser.add_argument("--north", type=float, default=2.5)
    parser.add_argument("--east", type=float, default=2.0)
    parser.add_argument("--alt", type=float, default=10.0)
    parser.add_argument("--noise-px", type=float, default=0.5)
    parser.add_argument("--timeout", type=float, default=150.0, help="seconds from LAND to disarmed")
    parser.add_argument("--bridge-arg", action="append", default=[], help="an argument for kgadapt flight bridge")
    args = parser.parse_args(argv)
    result = fly(args)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
