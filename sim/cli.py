"""The commands that drive the stand-ins: ``kgadapt flight fake-fc`` and ``kgadapt flight land-check``.

    kgadapt flight fake-fc --url udpout:127.0.0.1:14550 [--armed] [--mode LOITER] [--land-after 20]
    kgadapt flight land-check [--rate 1] [--no-rangefinder] [--no-sizes] [--sitl-url tcp:127.0.0.1:5760]

They belong to ``kgadapt flight`` for the person running them, and to the simulator by what they run,
so they are registered under ``flight`` through the command registry (pyproject.toml's
``kgadapt.commands``): the flight code itself never imports the simulator.
"""

from __future__ import annotations

import argparse
import json
import time

from kgadapt.onboard.flight.flight_cli import run_until, stop_event


def register_fake_fc(flight_subparsers: argparse._SubParsersAction) -> None:
    """Add ``kgadapt flight fake-fc``."""
    sub = flight_subparsers
    fake = sub.add_parser(
        "fake-fc", help="run a fake flight controller speaking MAVLink 2",
        description="A fake autopilot that follows ArduCopter (docs/flight.md): streams HEARTBEAT, SYS_STATUS, "
                    "BATTERY_STATUS, EXTENDED_SYS_STATE, and ATTITUDE, GLOBAL_POSITION_INT, LOCAL_POSITION_NED, "
                    "DISTANCE_SENSOR, HOME_POSITION when asked; acknowledges commands; lands with precision "
                    "landing on LANDING_TARGETs; counts what it receives. Prints its readiness line once its socket is open.",
    )
    fake.add_argument("--url", default="udpout:127.0.0.1:14550",
                      help="where to talk (default udpout:127.0.0.1:14550; udpin:HOST:PORT to listen)")
    fake.add_argument("--system-id", type=int, default=1, help="MAVLink system id (default 1)")
    fake.add_argument("--armed", action="store_true", help="report armed")
    fake.add_argument("--mode", default="LOITER", help="ArduCopter mode name (default LOITER)")
    fake.add_argument("--landed-state", default=None,
                      help="ON_GROUND, IN_AIR, TAKEOFF, LANDING, UNDEFINED (default IN_AIR if --armed else ON_GROUND)")
    fake.add_argument("--battery-pct", type=float, default=90.0, help="battery charge, percent (default 90)")
    fake.add_argument("--load-pct", type=float, default=22.0, help="main-loop load, percent (default 22)")
    fake.add_argument("--alt", type=float, default=None, metavar="M",
                      help="height above home (default 10 when --armed, else 0)")
    fake.add_argument("--no-rangefinder", action="store_true", help="no downward rangefinder")
    fake.add_argument("--land-after", type=float, default=None, metavar="S",
                      help="start the scripted final descent after S seconds")
    fake.add_argument("--descent", type=float, default=5.0, metavar="S", help="final descent duration (default 5)")
    fake.add_argument("--rate-scale", type=float, default=1.0,
                      help="multiply every stream rate (default 1: HEARTBEAT 1 Hz, SYS_STATUS 2 Hz, others 1 Hz)")
    fake.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0: run until stopped)")
    fake.add_argument("--json", action="store_true", help="print one JSON object per second")
    fake.set_defaults(func=_fake_fc)


def register_land_check(flight_subparsers: argparse._SubParsersAction) -> None:
    """Add ``kgadapt flight land-check``."""
    sub = flight_subparsers
    check = sub.add_parser(
        "land-check", help="fly one precision landing on a marker and print how far from it the vehicle landed",
        description="Marker 2.5 m forward, 2 m right, 10 m below; detections at --rate over Zenoh (in this "
                    "process) to the flight bridge; LAND; error at touchdown. The fake flight controller "
                    "(ArduCopter's speeds and AC_PrecLand behaviour) unless --sitl-url names a real autopilot.",
    )
    check.add_argument("--rate", type=float, default=1.0, help="detections a second (default 1)")
    check.add_argument("--no-rangefinder", action="store_true", help="the fake vehicle has no downward rangefinder")
    check.add_argument("--no-sizes", action="store_true", help="no marker sizes: angles (+ rangefinder) only")
    check.add_argument("--hold", type=float, default=1.5, metavar="S", help="re-send the last target up to S s")
    check.add_argument("--reboot-first", action="store_true",
                       help="reboot the autopilot on the ground first, report how soon every stream was back")
    check.add_argument("--sitl-url", default=None, help="a real autopilot, e.g. tcp:127.0.0.1:5760 (ArduCopter SITL)")
    check.add_argument("--json", action="store_true", help="print one JSON object")
    check.set_defaults(func=_land_check)


def _fake_fc(args: argparse.Namespace) -> int:
    from kgadapt.shared.readiness import announce_ready
    from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState

    if args.rate_scale <= 0:
        from kgadapt.shared.errors import ConfigError

        raise ConfigError(f"--rate-scale must be positive, not {args.rate_scale}")
    r = args.rate_scale
    settings = FakeFCSettings(url=args.url, system_id=args.system_id, heartbeat_hz=1.0 * r,
                              sys_status_hz=2.0 * r, battery_hz=1.0 * r, extended_state_hz=1.0 * r,
                              rangefinder=not args.no_rangefinder)
    landed = args.landed_state or ("IN_AIR" if args.armed else "ON_GROUND")
    vehicle = VehicleState(armed=args.armed, mode=args.mode.upper(), landed_state=landed.upper(),
                           battery_pct=args.battery_pct, load_pct=args.load_pct, alt=args.alt)
    fc = FakeFlightController(settings, vehicle)
    stop = stop_event()
    fc.setup()
    started = time.monotonic()
    landing = {"started": False}
    print(f"fake flight controller ready: system {args.system_id} on {args.url}, {vehicle.mode}, "
          f"{'armed' if vehicle.armed else 'disarmed'}, {vehicle.landed_state}; one line a second follows "
          "(the next line tells scripts it is ready)", flush=True)
    announce_ready(status="fake flight controller ready", url=args.url)

    def tick() -> None:
        if args.land_after is not None and not landing["started"] and time.monotonic() - started >= args.land_after:
            landing["started"] = True
            fc.land(args.descent)
        v = fc.vehicle
        counts = {kind: fc.received_count(kind) for kind in ("HEARTBEAT", "LANDING_TARGET")}
        last = fc.received("LANDING_TARGET")[-1:]
        report = {"time": time.time(), "armed": v.armed, "mode": v.mode, "landed_state": v.landed_state,
                  "battery_pct": round(v.battery_pct, 1), "received": counts,
                  "last_landing_target": last[0].fields if last else None}
        if args.json:
            print(json.dumps(report, default=str), flush=True)
        else:
            target = ""
            if last:
                f = last[0].fields
                target = f" last target angle_x={f['angle_x']:+.4f} angle_y={f['angle_y']:+.4f} rad"
            print(f"{v.mode:<9} armed={v.armed!s:<5} {v.landed_state:<9} battery={v.battery_pct:5.1f}% "
                  f"heartbeats={counts['HEARTBEAT']} landing_targets={counts['LANDING_TARGET']}{target}", flush=True)

    try:
        run_until(stop, args.duration, 1.0, tick)
    finally:
        fc.shutdown()
    return 0


def _land_check(args: argparse.Namespace) -> int:
    from kgadapt.shared.session import ZenohSettings, open_session
    from kgadapt.sim.landing_check import LandingCheckSettings, run_landing_check

    settings = LandingCheckSettings(rate_hz=args.rate, rangefinder=not args.no_rangefinder,
                                    sizes_known=not args.no_sizes, hold_s=args.hold, url=args.sitl_url,
                                    reboot_first=args.reboot_first)
    session = open_session(ZenohSettings(mode="peer", listen=(), connect=()))
    try:
        result = run_landing_check(session, settings)
    finally:
        session.close()
    if args.json:
        print(json.dumps(result.as_dict()), flush=True)
    else:
        print(f"landed={result.landed} error={result.error_m:.2f} m acquired={result.acquired} "
              f"in {result.seconds:.1f} s; detections {result.detections}, LANDING_TARGETs "
              f"{result.targets_sent} + {result.targets_resent} re-sent"
              + ("" if result.max_gap_s is None else f"; longest gap after acquisition {result.max_gap_s:.2f} s")
              + ("" if result.streams_back_s is None else f"; streams back {result.streams_back_s:.1f} s after reboot, "
                 f"local position {result.origin_back_s:.1f} s"),
              flush=True)
    return 0 if result.landed else 1
