"""``kgadapt perception``: camera publisher, detector, calibration, profile check.

::

    kgadapt perception camera [--source synthetic[:PROFILE] | device:N | file:PATH] [--fps 30] ...
    kgadapt perception detect --host H --instance I (--config NAME | --config-json JSON) [--connect EP]
    kgadapt perception calibrate [--store URL] [--frames N] [--levels N] [--site FILE] [--json]
    kgadapt perception calibrate --frames-from DIR_OR_VIDEO [--store URL] [--json]
    kgadapt perception profile FILE [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "perception",
        help="camera publisher, marker detector, calibration of detector configurations",
        description="Perception: publish camera frames (real or synthetic), run the marker detector, "
                    "calibrate the detector configurations of the knowledge store per illumination band.",
    )
    sub = parser.add_subparsers(dest="perception_command", metavar="ACTION")
    sub.required = True
    _register_camera(sub)
    _register_detect(sub)
    _register_calibrate(sub)
    _register_profile(sub)


# -- camera --------------------------------------------------------------------


def _register_camera(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from kgadapt.shared.agent import DEFAULT_ROBOT
    from kgadapt.shared.session import add_arguments

    p = sub.add_parser(
        "camera",
        help="publish frames and illumination over Zenoh",
        description="Capture from a source and publish JPEG frames (kind 'frame') and luminance figures "
                    "(kind 'illumination') until SIGINT/SIGTERM or --duration. Sources: synthetic[:PROFILE] "
                    "(default; the demo profile), device:N (/dev/videoN), file:PATH (a video file, looped).",
    )
    p.add_argument("--source", default="synthetic", help="synthetic[:PROFILE], device:N or file:PATH (default synthetic)")
    p.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")
    p.add_argument("--camera", default="cam0", help="camera name in the key expressions (default cam0)")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    p.add_argument("--quality", type=int, default=80, help="JPEG quality 1..100 (default 80)")
    p.add_argument("--width", type=int, default=640, help="frame width (default 640)")
    p.add_argument("--height", type=int, default=480, help="frame height (default 480)")
    p.add_argument("--speed", type=float, default=1.0, help="synthetic scenario time per wall-clock second (default 1)")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="synthetic scenario start time (default 0)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: run until a signal)")
    p.add_argument("--json", action="store_true", help="print the final counters as JSON")
    add_arguments(p)
    p.set_defaults(func=_camera)


def _camera(args: argparse.Namespace) -> int:
    from kgadapt.onboard.perception.camera import CameraPart, CameraSettings, make_source
    from kgadapt.shared.agent import StopSignals
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    settings = CameraSettings(robot=args.robot, camera=args.camera, fps=args.fps, jpeg_quality=args.quality,
                              width=args.width, height=args.height)
    source = make_source(args.source, width=args.width, height=args.height, fps=args.fps,
                         speed=args.speed, start_s=args.start)
    zenoh_settings = settings_from_args(args).with_defaults(mode="peer", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh_settings)
    part = CameraPart(settings, source)
    started = time.monotonic()
    try:
        with StopSignals() as stop:
            part.setup(session)
            print(f"camera {args.camera}: {source.description}, {args.fps:g} fps, {args.width}x{args.height}, "
                  f"JPEG {args.quality}", flush=True)
            deadline = None if args.duration is None else started + args.duration
            while not stop.event.is_set() and not part.finished.is_set():
                remaining = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
                if remaining <= 0:
                    break
                stop.event.wait(remaining)
    finally:
        part.shutdown()
        session.close()
    stats = part.stats
    result: dict[str, Any] = {
        "captured": stats.captured, "published": stats.published, "dropped_queue": stats.dropped_queue,
        "read_failures": stats.read_failures, "seconds": round(time.monotonic() - started, 2),
        "encode_ms_mean": round(sum(stats.encode_ms) / len(stats.encode_ms), 3) if stats.encode_ms else None,
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(", ".join(f"{k} {v}" for k, v in result.items()))
    if part.error is not None:
        raise part.error
    return 0


# -- detect --------------------------------------------------------------------


def _register_detect(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from kgadapt.onboard.perception.detector import add_detector_arguments

    p = sub.add_parser(
        "detect",
        help="run the marker detector (same as python -m kgadapt.onboard.perception.detector)",
        description="The marker-detector program: gets its configuration from the knowledge store "
                    "(--config) or inline (--config-json), detects markers in the camera's frames and "
                    "publishes detections. Prints its readiness line when ready; exit status 2 when the store "
                    "does not know the configuration.",
    )
    add_detector_arguments(p)
    p.set_defaults(func=_detect)


def _detect(args: argparse.Namespace) -> int:
    from kgadapt.onboard.perception.detector import run

    return run(args)


# -- calibrate -----------------------------------------------------------------


def _register_calibrate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from kgadapt.onboard.perception.calibration import FEATURE, RESULTS_DIR

    p = sub.add_parser(
        "calibrate",
        help="measure every detector configuration per illumination band; write the figures to the graph",
        description="Run every detector configuration of the store over the synthetic scenario at fixed "
                    "levels in each illumination band; measure detection rate (against ground truth, false "
                    "detections counted) and ms per frame; write them as CALIBRATED relations, a JSON file "
                    "and a PNG plot. Loads knowledge/models first when the graph has no configuration.",
    )
    p.add_argument("--store", default=None, help="store URL (default $KGADAPT_STORE or the embedded store)")
    p.add_argument("--feature", default=FEATURE, help=f"feature whose configurations to calibrate (default {FEATURE})")
    p.add_argument("--frames", type=int, default=4, help="frames per level and condition (default 4)")
    p.add_argument("--conditions", default=None,
                   help="comma-separated conditions (default all: clean,blur,uneven,window,small)")
    p.add_argument("--levels", type=int, default=4, help="levels per band (default 4)")
    p.add_argument("--quality", type=int, default=80, help="JPEG quality of the test frames (default 80)")
    p.add_argument("--site", default=None, metavar="FILE",
                   help="site file (JSON: dictionary, markers, layout): its ids and sizes in the calibration scene, "
                        "printed as its layout says (apart, chessboard, touching)")
    p.add_argument("--frames-from", default=None, metavar="DIR_OR_VIDEO",
                   help="calibrate on recorded frames (a folder of images or a video) instead of the synthetic "
                        "scene, markers labelled by the configurations' agreement; recorded as source frames:NAME")
    p.add_argument("--agree", type=int, default=2, metavar="N",
                   help="with --frames-from: configurations that must find a marker for it to count (default 2)")
    p.add_argument("--out", default=None,
                   help=f"JSON output (default {RESULTS_DIR / 'calibration.json'}, with --frames-from "
                        f"{RESULTS_DIR / 'calibration_frames.json'})")
    p.add_argument("--plot", default=None,
                   help=f"PNG plot (default {RESULTS_DIR / 'calibration.png'} where the 'plots' extra is installed, "
                        "else none; '' for none)")
    p.add_argument("--no-record", action="store_true", help="do not write the figures into the graph")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.set_defaults(func=_calibrate)


def _calibrate(args: argparse.Namespace) -> int:
    from kgadapt.onboard.perception.calibration import CONDITIONS, RESULTS_DIR, CalibrationSettings, run_calibration

    progress = None if args.json else (lambda line: print(line, file=sys.stderr, flush=True))
    if args.frames_from:
        return _calibrate_frames(args, progress)
    conditions = tuple(c.strip() for c in args.conditions.split(",")) if args.conditions else tuple(CONDITIONS)
    settings = CalibrationSettings(frames_per_level=args.frames, levels_per_band=args.levels,
                                   jpeg_quality=args.quality, conditions=conditions)
    site = None
    if args.site:
        from kgadapt.onboard.flight.site import load_site

        site = load_site(args.site)
    out = RESULTS_DIR / "calibration.json" if args.out is None else args.out
    plot_path = args.plot
    if plot_path is None:  # the default plot only where matplotlib is (a robot's install leaves it out)
        from kgadapt.shared.extras import installed

        plot_path = str(RESULTS_DIR / "calibration.png") if installed("matplotlib") else None
        if plot_path is None:
            print("no plot: matplotlib (kgadapt[plots]) is not installed", file=sys.stderr)
    data = run_calibration(args.store, feature=args.feature, settings=settings, write_store=not args.no_record,
                           json_path=out or None, plot_path=plot_path or None, progress=progress, site=site)
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print("\n".join(data["table"]))
    print("best per band: " + ", ".join(f"{band} -> {config}" for band, config in data["best"].items()))
    if not args.no_record:
        print(f"recorded {len(data['results'])} CALIBRATED relations in {data['store']}")
    for key in ("json", "plot"):
        if key in data:
            print(f"wrote {data[key]}")
    return 0


def _calibrate_frames(args: argparse.Namespace, progress: Any) -> int:
    from kgadapt.onboard.perception.calibration import RESULTS_DIR
    from kgadapt.onboard.perception.recorded_calibration import AgreementSettings, run_frame_calibration

    out = RESULTS_DIR / "calibration_frames.json" if args.out is None else args.out
    data = run_frame_calibration(args.store, args.frames_from, feature=args.feature,
                                 settings=AgreementSettings(min_configs=args.agree), write_store=not args.no_record,
                                 json_path=out or None, progress=progress)
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    labels = data["labels"]
    print(f"{data['source']}: frames per band {labels['frames_per_band']}, {labels['frames_outside']} outside every band")
    print("markers agreed on: " + ("; ".join(f"{d}: {ids}" for d, ids in labels["real"].items()) or "none"))
    for r in data["results"]:
        print(f"  {r['config']:28s} {r['band']:6s} rate {r['detection_rate']:6.1%} of {r['markers']:5d} agreed, "
              f"false/frame {r['false_per_frame']:6.3f}, {r['ms_per_frame']:6.2f} ms/frame")
    if data["recorded"]:
        print(f"recorded {len(data['results'])} CALIBRATED relations (source {data['source']}) in {data['store']}")
    if "json" in data:
        print(f"wrote {data['json']}")
    return 0


# -- profile -------------------------------------------------------------------


def _register_profile(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "profile",
        help="check an illumination profile file and show its levels",
        description="Parse an illumination profile (JSON or CSV; errors name file and line) and print its "
                    "level once per second (or every --step seconds).",
    )
    p.add_argument("file", help="profile file (.json or .csv)")
    p.add_argument("--step", type=float, default=1.0, help="seconds between printed samples (default 1)")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.set_defaults(func=_profile)


def _profile(args: argparse.Namespace) -> int:
    from kgadapt.onboard.perception.scene import load_profile
    from kgadapt.shared.errors import ConfigError

    if not args.step > 0:
        raise ConfigError(f"--step {args.step}: must be positive")
    profile = load_profile(args.file)
    samples = []
    t = 0.0
    while t <= profile.duration + 1e-9:
        depth, hz = profile.flicker_at(t)
        samples.append({"t": round(t, 3), "level": round(profile.level_at(t), 2),
                        "flicker_depth": round(depth, 3), "flicker_hz": hz})
        t += args.step
    if args.json:
        print(json.dumps({"file": profile.source, "duration_s": profile.duration, "points": len(profile.points),
                          "gradient": profile.gradient, "noise": profile.noise, "loop": profile.loop,
                          "samples": samples}))
        return 0
    print(f"{profile.source}: {len(profile.points)} points, {profile.duration:g} s, gradient {profile.gradient}, "
          f"noise {profile.noise}, {'looped' if profile.loop else 'not looped'}")
    for s in samples:
        flicker = f"  flicker {s['flicker_depth']:.2f} at {s['flicker_hz']:g} Hz" if s["flicker_depth"] else ""
        print(f"  t={s['t']:7.2f} s  level {s['level']:6.1f}{flicker}")
    return 0
