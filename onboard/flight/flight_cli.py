"""``kgadapt flight``: a flight-state monitor, the flight controller's status, and the bridge on its own.

    kgadapt flight monitor --url udpin:0.0.0.0:14550 [--json] [--duration 10]
    kgadapt flight status --url udpin:0.0.0.0:14550 [--json]
    kgadapt flight bridge --robot quad1 --url udpin:0.0.0.0:14550 --fx 600 --fy 600 --cx 320 --cy 240

Long-running commands stop on Ctrl-C or SIGTERM and exit 0. ``flight fake-fc`` and ``flight land-check``,
which drive the stand-ins, are added by :mod:`kgadapt.sim.cli` (the command registry, kgadapt/cli.py).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import TYPE_CHECKING, Any, Callable

from kgadapt.shared.keys import DEFAULT_ROBOT

if TYPE_CHECKING:
    from kgadapt.onboard.flight.mavlink import FlightState, LinkSettings

# Only light imports here: pymavlink and zenoh are imported inside the commands.


def _shown(state: FlightState) -> dict[str, Any]:
    """A flight state's figures for JSON output: its ``flight_state`` message's known fields."""
    import msgspec

    return {k: v for k, v in msgspec.structs.asdict(state.as_message()).items() if v is not None and k != "v"}


def register(
    subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
) -> argparse._SubParsersAction[argparse.ArgumentParser]:
    parser = subparsers.add_parser(
        "flight", help="MAVLink flight controller link: fake autopilot, state monitor, bridge",
        description="MAVLink 2 link to the flight controller (common dialect).",
    )
    sub = parser.add_subparsers(dest="flight_command", metavar="SUBCOMMAND")
    sub.required = True

    monitor = sub.add_parser(
        "monitor", help="print the flight controller's state",
        description="Connect to a flight controller and print its state on every change and once a second.",
    )
    _add_link_arguments(monitor)
    monitor.add_argument("--wait", type=float, default=10.0, metavar="S",
                         help="fail if no heartbeat within S seconds (default 10)")
    monitor.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0: run until stopped)")
    monitor.add_argument("--every", type=float, default=1.0, metavar="S", help="also print every S seconds (default 1)")
    monitor.add_argument("--json", action="store_true", help="print JSON objects, one per line")
    monitor.set_defaults(func=_monitor)

    status = sub.add_parser(
        "status", help="print the flight controller's state once, every field with its age",
        description="Connect, wait for the streams, print the flight state (altitude, attitude, position, "
                    "rangefinder, home, battery, landed state; each with when it was last heard; missing streams "
                    "and refused commands) and exit.",
    )
    _add_link_arguments(status)
    status.add_argument("--wait", type=float, default=10.0, metavar="S", help="fail if no heartbeat within S seconds")
    status.add_argument("--settle", type=float, default=3.0, metavar="S",
                        help="then wait up to S seconds for every stream (default 3)")
    status.add_argument("--json", action="store_true", help="print one JSON object")
    status.set_defaults(func=_status)

    bridge = sub.add_parser(
        "bridge", help="run the flight bridge alone (detections -> LANDING_TARGET, flight_state)",
        description="Follow a detector's detections over Zenoh, send LANDING_TARGET, publish flight_state. "
                    "The onboard agent hosts the same bridge; this runs it on its own.",
    )
    from kgadapt.shared import session as zsession

    _add_link_arguments(bridge)
    bridge.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name, the key namespace (default {DEFAULT_ROBOT})")
    bridge.add_argument("--detector", default="*", help="detector instance to follow (default: any)")
    bridge.add_argument("--target-id", type=int, default=None, help="marker id to land on (default: largest seen)")
    bridge.add_argument("--camera", help="read the intrinsics of this camera component from the knowledge service")
    for name in ("fx", "fy", "cx", "cy"):
        bridge.add_argument(f"--{name}", type=float, help=f"camera intrinsic {name}, pixels (instead of --camera)")
    bridge.add_argument("--camera-file", help="camera file (JSON: intrinsics, distortion, mounting), checked on load")
    bridge.add_argument("--site", metavar="FILE",
                        help="site file (*.site: marker ids, sizes, dictionary; onboard/flight/site.py) instead of the "
                             "graph's site (read when the bridge uses the graph: --camera, --write-graph or "
                             "--site-name): only its ids become targets, and they go with positions")
    bridge.add_argument("--site-name", metavar="NAME",
                        help="the graph's site to use when it holds several (default: the only one)")
    bridge.add_argument("--profile", default="auto", choices=("auto", "ardupilot", "px4"),
                        help="LANDING_TARGET frame: ardupilot = body FRD, px4 = local NED (default: from the heartbeat)")
    bridge.add_argument("--hold", type=float, default=1.5, metavar="S",
                        help="re-send the last target, predicted, up to S s after its frame (default 1.5; 0 = off)")
    bridge.add_argument("--write-graph", action="store_true",
                        help="write the flight state into the FlightControl component through the knowledge service")
    bridge.add_argument("--host", default="onboard",
                        help="the host this bridge runs on, whose write key it uses (default onboard: the knowledge "
                        "service takes the flight state only from the adaptation manager's host)")
    zsession.add_arguments(bridge)
    bridge.set_defaults(func=_bridge)
    return sub  # other parts add theirs (kgadapt.sim.cli: fake-fc, land-check)


def _add_link_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default="udpin:0.0.0.0:14550",
                        help="flight controller: udpin:HOST:PORT (default udpin:0.0.0.0:14550), udpout:HOST:PORT, "
                             "tcp:HOST:PORT or /dev/ttyX:BAUD")
    parser.add_argument("--system-id", type=int, default=1, help="our MAVLink system id (default 1)")
    parser.add_argument("--component-id", type=int, default=191, help="our component id (default 191, onboard computer)")
    parser.add_argument("--target-system", type=int, default=None, help="autopilot system id to follow (default: first heard)")
    parser.add_argument("--heartbeat-timeout", type=float, default=3.0, metavar="S",
                        help="link lost after S seconds without heartbeat (default 3)")


def _link_settings(args: argparse.Namespace) -> LinkSettings:
    from kgadapt.onboard.flight.mavlink import LinkSettings

    return LinkSettings(url=args.url, system_id=args.system_id, component_id=args.component_id,
                        target_system=args.target_system, heartbeat_timeout_s=args.heartbeat_timeout)


def stop_event() -> threading.Event:
    """An event set by SIGTERM or SIGINT.

    SIGINT gets its own handler: a background job of a non-interactive shell
    starts with SIGINT ignored, so Ctrl-C's KeyboardInterrupt would never come.
    """
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    return stop


def run_until(stop: threading.Event, duration: float, every: float, tick: Callable[[], object]) -> None:
    deadline = time.monotonic() + duration if duration > 0 else None
    try:
        while not stop.is_set():
            wait = every if deadline is None else min(every, deadline - time.monotonic())
            if wait <= 0 or stop.wait(wait):
                break
            tick()
    except KeyboardInterrupt:
        pass


def _monitor(args: argparse.Namespace) -> int:
    import queue

    from kgadapt.onboard.flight.mavlink import FlightLink

    if args.every <= 0:
        from kgadapt.shared.errors import ConfigError

        raise ConfigError(f"--every must be positive, not {args.every}")
    link = FlightLink(_link_settings(args))
    stop = stop_event()
    changed = threading.Event()
    events: queue.SimpleQueue[FlightState] = queue.SimpleQueue()  # snapshots made for link events: each one is printed
    shown: dict[str, Any] = {"discrete": None}

    def on_state(state: FlightState) -> None:
        if state.event:
            events.put(state)
        if state.discrete() != shown["discrete"]:
            changed.set()

    link.on_state(on_state)
    link.setup()
    try:
        link.wait_for_heartbeat(args.wait)

        def show(state: FlightState) -> None:
            shown["discrete"] = state.discrete()
            if args.json:
                print(json.dumps(_shown(state)), flush=True)
                return
            battery = "-" if state.battery_pct is None else f"{state.battery_pct:.0f}%"
            volts = "-" if state.battery_v is None else f"{state.battery_v:.2f} V"
            load = "-" if state.onboard_load is None else f"{state.onboard_load:.1f}%"
            event = f"  [{state.event}]" if state.event else ""
            print(f"link={'up' if state.link else 'LOST'} armed={state.armed} mode={state.mode} "
                  f"landed={state.landed_state} battery={battery} {volts} load={load} {_motion(state)}{event}",
                  flush=True)

        last = 0.0

        def tick() -> None:
            nonlocal last
            printed = False
            while not events.empty():
                show(events.get())
                printed = True
            state = link.state
            news = changed.is_set() and state.discrete() != shown["discrete"]
            changed.clear()
            if news or time.monotonic() - last >= args.every:
                show(state)
                printed = True
            if printed:
                last = time.monotonic()

        tick()
        run_until(stop, args.duration, min(0.05, args.every), tick)
    finally:
        link.shutdown()
    return 0


def _bridge(args: argparse.Namespace) -> int:
    from kgadapt.onboard.cli import log_site
    from kgadapt.onboard.flight.confirmation import ConfirmationSettings
    from kgadapt.onboard.flight.flight import (
        BridgeSettings,
        CameraIntrinsics,
        FlightBridge,
        FlightControlWriter,
        intrinsics_from_graph,
    )
    from kgadapt.onboard.flight.landing_targets import load_camera
    from kgadapt.onboard.flight.site import load_site, site_from_graph
    from kgadapt.shared import session as zsession
    from kgadapt.shared.errors import ConfigError
    from kgadapt.shared.readiness import announce_ready

    given = [args.fx, args.fy, args.cx, args.cy]
    camera_file = load_camera(args.camera_file) if args.camera_file else None
    site = load_site(args.site) if args.site else None  # read once: sizes for the targets, ids for the confirmer
    if camera_file is not None:
        if args.camera is not None or None not in given:
            raise ConfigError("give one of --camera-file, --camera NAME or --fx --fy --cx --cy")
        args.fx, args.fy, args.cx, args.cy = camera_file.fx, camera_file.fy, camera_file.cx, camera_file.cy
    elif (args.camera is None) == (None in given):
        raise ConfigError("give either --camera-file, --camera NAME or all of --fx --fy --cx --cy")
    zsettings = zsession.settings_from_args(args).with_defaults(mode="peer", connect=[zsession.DEFAULT_ENDPOINT])
    session = zsession.open_session(zsettings)
    stop = stop_event()
    bridge = None
    try:
        client = None
        if args.camera or args.write_graph or args.site_name:
            from kgadapt.knowledge.client import KnowledgeClient

            client = KnowledgeClient(session, args.robot, own=True, host=args.host)
        intrinsics = (intrinsics_from_graph(client, args.camera) if args.camera
                      else CameraIntrinsics(fx=args.fx, fy=args.fy, cx=args.cx, cy=args.cy))
        if site is None and client is not None:  # the graph's site, as the onboard agent takes it
            site = site_from_graph(client, args.site_name, wait_s=10.0)
        log_site(site)
        settings = BridgeSettings(robot=args.robot, link=_link_settings(args), detector=args.detector,
                                  target_id=args.target_id, intrinsics=intrinsics, camera=camera_file,
                                  markers=site, confirmation=ConfirmationSettings(site=site),
                                  profile=args.profile, hold_s=args.hold)
        bridge = FlightBridge(settings, on_state=FlightControlWriter(client) if args.write_graph else None)
        bridge.setup(session)
        announce_ready(status="flight bridge ready", robot=args.robot)
        run_until(stop, 0.0, 5.0, lambda: print(json.dumps(bridge.counters), file=sys.stderr, flush=True))
    finally:
        if bridge is not None:
            bridge.shutdown()
        session.close()
    return 0


def _num(value: float | None, fmt: str = "{:.2f}") -> str:
    return "-" if value is None else fmt.format(value)


def _motion(state: FlightState) -> str:
    """Altitude, attitude, position and rangefinder in one short line ('-' = unknown)."""
    import math

    att = "-" if state.attitude is None else "/".join(f"{math.degrees(a):.1f}" for a in state.attitude)
    pos = "-" if state.position_ned is None else "/".join(f"{v:.2f}" for v in state.position_ned)
    return (f"alt={_num(state.alt_rel_m)} m rpy={att} deg ned={pos} m rng={_num(state.rangefinder_m)} m"
            + (f" missing={','.join(state.missing)}" if state.missing else ""))


def status_lines(state: FlightState, timeouts: dict[str, float], now: float) -> list[str]:
    """``kgadapt flight status``: one line a group of fields, with its age and timeout."""
    import math

    from kgadapt.onboard.flight.mavlink import STREAM_FIELDS

    heard = dict(state.heard)
    lines = [f"link       {'up' if state.link else 'LOST'}  autopilot {state.autopilot or '-'} "
             f"system {state.system_id if state.system_id is not None else '-'}  reboots seen {state.reboots}"]
    shown = {
        "HEARTBEAT": f"armed {state.armed}  mode {state.mode}",
        "EXTENDED_SYS_STATE": f"landed {state.landed_state}",
        "SYS_STATUS": f"autopilot load {_num(state.onboard_load, '{:.1f}')} %",
        "BATTERY_STATUS": f"battery {_num(state.battery_pct, '{:.0f}')} %  {_num(state.battery_v)} V",
        "GLOBAL_POSITION_INT": f"altitude {_num(state.alt_rel_m)} m above home, {_num(state.alt_amsl_m)} m AMSL  "
                               f"lat {_num(state.lat_deg, '{:.7f}')} lon {_num(state.lon_deg, '{:.7f}')}",
        "ATTITUDE": "attitude " + ("-" if state.attitude is None else
                                   "roll {:.1f} pitch {:.1f} yaw {:.1f} deg".format(*map(math.degrees, state.attitude)))
                    + ("" if state.rates is None
                       else "  rates {:.1f} {:.1f} {:.1f} deg/s".format(*map(math.degrees, state.rates))),
        "LOCAL_POSITION_NED": "local NED " + ("-" if state.position_ned is None else
                                              "{:.2f} {:.2f} {:.2f} m".format(*state.position_ned))
                              + ("" if state.velocity_ned is None
                                 else "  v {:.2f} {:.2f} {:.2f} m/s".format(*state.velocity_ned)),
        "DISTANCE_SENSOR": f"rangefinder {_num(state.rangefinder_m)} m",
        "HOME_POSITION": "home " + ("-" if state.home is None else "{:.7f} {:.7f} {:.1f} m AMSL".format(*state.home)),
    }
    for stream in STREAM_FIELDS:
        age = "never heard" if stream not in heard else f"{now - heard[stream]:.2f} s ago"
        timeout = timeouts.get(stream)
        limit = "" if timeout is None else f" (unknown after {timeout:g} s)"
        lines.append(f"{stream:<20} {age:<12}{limit:<24} {shown[stream]}")
    if state.missing:
        lines.append("missing    " + ", ".join(state.missing))
    if state.rejected:
        lines.append(f"rejected   {state.rejected} command acknowledgement(s) rejected (retries included)")
    for refusal in state.refused:
        lines.append(f"refused    {refusal}")
    return lines


def _status(args: argparse.Namespace) -> int:
    from kgadapt.onboard.flight.mavlink import STREAM_FIELDS, FlightLink

    link = FlightLink(_link_settings(args))
    link.setup()
    try:
        link.wait_for_heartbeat(args.wait)
        wanted = {name for name, _ in link.settings.stream_rates}
        deadline = time.monotonic() + args.settle
        while time.monotonic() < deadline and not wanted <= set(dict(link.state.heard)):
            time.sleep(0.05)
        state = link.state
        timeouts = {name: link.stream_timeout(name) for name in STREAM_FIELDS}
        if args.json:
            print(json.dumps({**_shown(state), "timeouts": timeouts}), flush=True)
        else:
            print("\n".join(status_lines(state, timeouts, time.time())), flush=True)
    finally:
        link.shutdown()
    return 0
