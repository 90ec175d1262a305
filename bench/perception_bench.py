"""``kgadapt bench perception``: detector cost per configuration, frame transport, calibration.

Three measurements, written to ``bench/results/perception.json`` (records in
the shared format of bench/stats.py) and summarised for docs/perception.md:

1. **ms per frame** of every detector configuration of the shipped models at
   640x480, per illumination band (the calibration run: the same frames for
   every configuration; figures also written to ``calibration.json``/``.png``).
2. **frame transport** at 30 fps from the camera publisher (this process) to a
   detector in another process over Zenoh on loopback: publication to arrival
   in the detector (target p99 <= 20 ms), and capture to detections published.
3. **the calibration table**: detection rate, false markers per 1,000 frames
   and ms per frame per configuration, band and condition, and the first of
   each band's ranking.
4. **quality** (:mod:`kgadapt.bench.perception_quality`, into
   ``perception.quality.json``): per configuration x band x condition on fresh
   frames with the oracle gap of the planner's pick; phantom landing targets
   over frames without the site's markers (real photographs and synthetic
   patterns); real photographs against the synthetic scene at the same level;
   the issue's rate targets; and the **gap under blur with the detector's
   reflexes** (``reflex_blur``, beside the static gap under blur): the real
   ``Reflex`` on the calibrated graph's reflex table, fed real photographs
   sharp and then with a 7 px motion blur at day and dusk light, against the
   best configuration on the same frames (``--only-reflex-blur`` measures
   only this, into ``perception.reflex_blur.json``).
"""

from __future__ import annotations

import argparse
import os
import queue
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from kgadapt.shared.children import ChildProcess
from kgadapt.shared.errors import KgadaptError
from kgadapt.shared.resources import models, results_dir

REPO = Path(__file__).resolve().parent.parent
RESULTS = results_dir()
TRANSPORT_TARGET_P99_MS = 20.0
DAY_JSON = '{"dictionary": "DICT_4X4_50", "preprocess": [], "parameters": {}}'


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "perception",
        help="detector ms per frame per configuration, frame transport latency, calibration table",
        description="Perception benchmark: every detector configuration of the shipped models over the "
                    "synthetic scenario per illumination band (ms per frame, detection rate), and frame "
                    "transport at 30 fps from the camera publisher to a detector process over Zenoh "
                    "(latency p50/p99; target p99 <= 20 ms on loopback).",
    )
    p.add_argument("--frames", type=int, default=4, help="calibration frames per level and condition (default 4)")
    p.add_argument("--eval-frames", type=int, default=6,
                   help="fresh frames per level and condition for the oracle gap (default 6)")
    p.add_argument("--phantom-frames", type=int, default=10000,
                   help="frames without the site's markers for the phantom count (default 10000)")
    p.add_argument("--levels", type=int, default=4, help="calibration levels per band (default 4)")
    p.add_argument("--seconds", type=float, default=10.0, help="transport run length (default 10 s)")
    p.add_argument("--fps", type=float, default=30.0, help="transport frame rate (default 30)")
    p.add_argument("--store", default=None, help="store URL (default: a fresh embedded store in a temp dir)")
    p.add_argument("--out", type=Path, default=RESULTS / "perception.json", help="records (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--photos", action="store_true",
                   help="only the real-photograph figures: blur agreement with the synthetic scene and the oracle "
                        "gap of models naming DICT_4X4_50, DICT_6X6_250, DICT_5X5_1000, DICT_ARUCO_MIP_36h12 "
                        "(into perception.photos.json beside --out)")
    p.add_argument("--photo", action="append", default=[], metavar="DICTIONARY=FILE",
                   help="with --photos: the oracle gap of DICTIONARY on this real photograph of its markers "
                        "(repeatable) instead of the shipped ones or the recoded stand-in; with --only-reflex-blur: "
                        "these photographs (read with DICTIONARY) through the reflexes instead of the shipped ones "
                        "(into perception.reflex_blur.given.json); for photographs whose licence keeps them out "
                        "of sim/photographs (see its SOURCES.txt)")
    p.add_argument("--only-given", action="store_true",
                   help="with --photo: the oracle gap of the dictionaries given photographs only (the others take "
                        "a calibration each on the recoded stand-in)")
    p.add_argument("--photos-out", type=Path, default=None, metavar="FILE",
                   help="with --photos or --only-reflex-blur: where to write the figures (default "
                        "perception.photos.json / perception.reflex_blur.json beside --out, *.given.json with --photo)")
    p.add_argument("--site", type=Path, default=None, metavar="FILE",
                   help="with --photos: calibrate models naming the site file's dictionary with its markers, as "
                        "`kgadapt perception calibrate --site FILE` does (ids, sizes and how they are printed: its "
                        "layout); with --only-reflex-blur: the site the shipped models are calibrated with")
    p.add_argument("--skip-blur", action="store_true", help="with --photos: leave out the blur agreement")
    p.add_argument("--only-reflex-blur", action="store_true",
                   help="only the gap under blur with the detector's reflexes: calibrate, then real photographs, "
                        "sharp then with a 7 px motion blur, through the reflex table the graph gives (into "
                        "perception.reflex_blur.json beside --out)")
    p.add_argument("--blur-level", action="append", default=[], metavar="BAND=LEVEL",
                   help="with --only-reflex-blur: blur at this light level in BAND (dusk or day; repeatable, the "
                        "band's figures pool its levels; default dusk=25 and day=120)")
    p.set_defaults(func=_run)


PHOTO_DICTIONARIES = ("DICT_4X4_50", "DICT_6X6_250", "DICT_5X5_1000", "DICT_ARUCO_MIP_36h12")


def run_photos(*, frames: int = 4, levels: int = 4, out: Path | str = RESULTS / "perception.photos.json",
               progress: Any = None, photos: Mapping[str, Sequence[Path]] | None = None,
               blur: bool = True, only_given: bool = False, site: Path | None = None) -> dict[str, Any]:
    """Blur agreement and the oracle gap per dictionary on real photographs; write them to ``out``.

    ``photos``: per dictionary, photograph files of its markers to measure its oracle gap on (read
    as the shipped ones are, at 640 x 480), in place of the shipped photographs or the recoded stand-in.
    ``only_given``: measure the dictionaries of ``photos`` only. ``site``: a site file whose markers
    (ids, sizes, layout) the calibration of models naming its dictionary draws.
    """

    from kgadapt.bench import perception_quality as quality
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store
    from kgadapt.onboard.perception.calibration import CalibrationSettings
    from kgadapt.onboard.perception.illumination import bands_from_rows

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="kgadapt-photos-") as tmp:
        store = open_store(f"embedded:{tmp}/store")
        store.setup()
        try:
            from kgadapt.knowledge.loader import load_models

            load_models(store, [models()])
            bands = bands_from_rows(run_named(store, "detector_configs", {"feature": "MarkerDetection"}))
        finally:
            store.shutdown()
    from kgadapt.onboard.flight.site import load_site
    from kgadapt.sim.photos import load_photo

    site_markers = load_site(site) if site else None
    agreement = quality.blur_agreement(progress=progress) if blur else None
    settings = CalibrationSettings(frames_per_level=frames, levels_per_band=levels)
    given = {d: [(str(f), load_photo(str(f))) for f in files] for d, files in (photos or {}).items()}
    # A given photograph may hold few markers (six on the DICT_4X4_50 one): frames x levels as calibrated
    # (16 a band and condition, 96 marker sightings for six) so that one marker is about one point, not four.
    oracle = {d: quality.photo_oracle_gap(d, bands, calibration=settings, progress=progress, given=given.get(d),
                                          site=site_markers,
                                          **({"frames": frames, "levels": levels} if d in given else {}))
              for d in PHOTO_DICTIONARIES if not only_given or d in given}
    return _save(out, {"site": None if site_markers is None else {"file": str(site), "site": site_markers.site,
                                                                  "dictionary": site_markers.dictionary,
                                                                  "layout": site_markers.layout},
                       "blur_agreement": agreement, "oracle_gap": oracle,
                       "oracle_target_met": all(o["target_met"] for o in oracle.values())},
                 load_before=load_before, frames=frames, levels=levels)


def _save(out: str, data: dict[str, Any], *, load_before: Sequence[float], frames: int, levels: int) -> dict[str, Any]:
    """``data`` with the machine, the load before and after and the calibration's size, written to ``out``."""
    import json

    from kgadapt.bench import stats

    data = {"machine": stats.machine_info(), "load_average_before": [round(v, 2) for v in load_before],
            "load_average_after": [round(v, 2) for v in os.getloadavg()],
            "calibration": {"frames_per_level": frames, "levels_per_band": levels}, **data}
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    data["out"] = str(path)
    return data


def _given_photos(args: argparse.Namespace) -> dict[str, list[Path]]:
    """The ``--photo DICTIONARY=FILE`` options, per dictionary; SystemExit naming a bad one."""
    photos: dict[str, list[Path]] = {}
    for item in args.photo:
        dictionary, sep, file = item.partition("=")
        if not sep or dictionary not in PHOTO_DICTIONARIES or not Path(file).is_file():
            raise SystemExit(f"kgadapt bench perception: --photo {item!r}: give DICTIONARY=FILE, DICTIONARY one of "
                             f"{', '.join(PHOTO_DICTIONARIES)} and FILE an existing photograph")
        photos.setdefault(dictionary, []).append(Path(file))
    return photos


def _blur_levels(args: argparse.Namespace) -> dict[str, list[float]]:
    """The ``--blur-level BAND=LEVEL`` options, per band; SystemExit naming a bad one."""
    levels: dict[str, list[float]] = {}
    for item in args.blur_level:
        band, sep, value = item.partition("=")
        try:
            level = float(value)
        except ValueError:
            level = -1.0
        if not sep or band not in ("dusk", "day") or not 0 < level <= 255:
            raise SystemExit(f"kgadapt bench perception: --blur-level {item!r}: give BAND=LEVEL, BAND dusk or day "
                             "and LEVEL a mean grey level in (0, 255]")
        levels.setdefault(band, []).append(level)
    return levels


def _run_photos(args: argparse.Namespace) -> int:
    import json

    photos = _given_photos(args)
    if args.only_given and not photos:
        raise SystemExit("kgadapt bench perception: --only-given needs at least one --photo DICTIONARY=FILE")
    # Figures on photographs given here (not shipped) go beside the shipped ones', not over them.
    name = "perception.photos.given.json" if photos else "perception.photos.json"
    data = run_photos(frames=args.frames, levels=args.levels, out=args.photos_out or Path(args.out).parent / name,
                      progress=None if args.json else _say, photos=photos, blur=not args.skip_blur,
                      only_given=args.only_given, site=args.site)
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for r in (data["blur_agreement"] or {}).get("rows", []):
        print(f"blur {r['blur_px']:g} px {r['config']:24s} photos {r['photos']:6.1%} synthetic {r['synthetic']:6.1%} "
              f"({r['difference_points']:+.1f} points; before {r['synthetic_before']:6.1%})")
    for d, o in data["oracle_gap"].items():
        print(f"{d} ({o['frames']}): worst oracle gap {o['worst_gap']['oracle_gap_points']} points at "
              f"{o['worst_gap']['band']}/{o['worst_gap']['condition']} (target <= 5: "
              f"{'met' if o['target_met'] else 'NOT met'})")
    print(f"wrote {data['out']}")
    return 0


def _run(args: argparse.Namespace) -> int:
    import json

    if args.photos:
        return _run_photos(args)
    if args.only_reflex_blur:
        return _run_reflex_blur(args)

    summary = run(frames=args.frames, levels=args.levels, seconds=args.seconds, fps=args.fps,
                  store_url=args.store, out=args.out, progress=None if args.json else _say,
                  eval_frames=args.eval_frames, phantom_frames=args.phantom_frames)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print("\n".join(summary["calibration_table"]))
        t = summary["transport"]
        print(f"transport at {t['fps']:g} fps, {t['frames_sent']} frames sent, {t['detections']} detections: "
              f"publish->detector p50 {t['transport_p50_ms']:.2f} ms p99 {t['transport_p99_ms']:.2f} ms "
              f"(target p99 <= {TRANSPORT_TARGET_P99_MS:g}: {'met' if t['target_met'] else 'NOT met'}); "
              f"capture->detections p50 {t['end_to_end_p50_ms']:.2f} ms p99 {t['end_to_end_p99_ms']:.2f} ms")
        q = summary["quality"]
        print("oracle gap (points) per band and condition: " + ", ".join(
            f"{g['band']}/{g['condition']} {g['oracle_gap_points']}" for g in q["oracle"]["gaps"]))
        print(f"worst oracle gap {q['oracle']['worst_gap']['oracle_gap_points']} points "
              f"(target <= 5: {'met' if q['oracle']['target_met'] else 'NOT met'})")
        for kind, what in (("ranked", "conditions the band's pick is ranked on"),
                           ("apart", "conditions figured apart from the ranking")):
            part = q["oracle"]["by_ranking"][kind]
            if part["worst_gap"] is not None:
                w = part["worst_gap"]
                print(f"  {what} ({', '.join(part['conditions'])}): worst {w['oracle_gap_points']} points at "
                      f"{w['band']}/{w['condition']} ({w['planner_pick']} {w['pick_rate']:.1%}, "
                      f"{w['best']} {w['best_rate']:.1%}; target <= 5: {'met' if part['target_met'] else 'NOT met'})")
        _print_reflex_blur(q["reflex_blur"], q["oracle"]["by_ranking"]["apart"])
        ph = q["phantoms"]
        print(f"phantoms over {ph['frames']} frames without site markers: " + "; ".join(
            f"{c}: raw {v['raw_false_markers']}, landing targets {v['landing_targets_no_site']} (no site) / "
            f"{v['landing_targets_with_site']} (site)" for c, v in ph["per_config"].items()))
        for case, rates in q["targets"].items():
            print(f"{case}: " + ", ".join(f"{c} {r:.1%}" for c, r in rates.items()))
        print(f"wrote {summary['out']}")
    return 0


def _print_reflex_blur(data: Mapping[str, Any], static: Mapping[str, Any] | None = None) -> None:
    """The gap under blur with the detector's reflexes, beside the static one (the band's pick alone)."""
    if static is not None and static.get("worst_gap") is not None:
        w = static["worst_gap"]
        print(f"  static gap under blur (synthetic scene, the band's pick alone): worst {w['oracle_gap_points']} "
              f"points at {w['band']}/{w['condition']}")
    for band, b in data["bands"].items():
        level = ", ".join(f"{v:g}" for v in (b["level"] if isinstance(b["level"], list) else [b["level"]]))
        print(f"  gap under blur with the detector's reflexes ({level} light, real photographs, "
              f"{data['blur_px']:g} px blur, after {data['reaction_frames']} frames): {band} {b['gap_points']} points "
              f"(with the reflexes {b['reflex_rate']:.1%}, the pick {b['pick']} alone {b['pick_rate']:.1%}: "
              f"static {b['static_gap_points']} points; best {b['best']} {b['best_rate']:.1%}; "
              f"{b['hedged_frames']} hedged frames)")
    print(f"  worst gap under blur with the detector's reflexes {data['worst_gap_points']} points (target <= 5: "
          f"{'met' if data['target_met'] else 'NOT met'})")


def run_reflex_blur(*, frames: int = 4, levels: int = 4, out: Path | str = RESULTS / "perception.reflex_blur.json",
                    progress: Any = None, photos: Mapping[str, Sequence[Path]] | None = None,
                    site: Path | None = None, blur_levels: Mapping[str, Sequence[float]] | None = None,
                    **options: Any) -> dict[str, Any]:
    """Calibrate the shipped models in a fresh store, then the gap under blur with the detector's reflexes.

    ``photos``: per dictionary, real photographs of its markers to feed the reflexes instead of the
    shipped blur-agreement photographs (the models calibrated as shipped, or with ``site``'s markers).
    ``blur_levels``: band -> light levels to blur at (default the day level 120 and the dusk band's middle).
    """

    from kgadapt.bench import perception_quality as quality
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store
    from kgadapt.onboard.perception.calibration import CalibrationSettings, run_calibration

    load_before = os.getloadavg()
    settings = CalibrationSettings(frames_per_level=frames, levels_per_band=levels)
    from kgadapt.onboard.flight.site import load_site
    from kgadapt.sim.photos import load_photo

    if blur_levels:
        options["levels"] = {band: list(values) for band, values in blur_levels.items()}
    if photos:
        options["given"] = [(str(f), load_photo(str(f)), d) for d, files in photos.items() for f in files]
    with tempfile.TemporaryDirectory(prefix="kgadapt-reflex-blur-") as tmp:
        url = f"embedded:{tmp}/store"
        run_calibration(url, settings=settings, progress=progress, json_path=None, plot_path=None,
                        site=load_site(site) if site else None)
        with open_store(url) as store:
            data = quality.reflex_blur(lambda name, params: run_named(store, name, params), progress=progress,
                                       **options)
    return _save(out, {"site": None if site is None else str(site), **data}, load_before=load_before,
                 frames=frames, levels=levels)


def _run_reflex_blur(args: argparse.Namespace) -> int:
    import json

    photos = _given_photos(args)
    # Figures on photographs given here (not shipped) go beside the shipped ones', not over them.
    name = "perception.reflex_blur.given.json" if photos else "perception.reflex_blur.json"
    data = run_reflex_blur(frames=args.frames, levels=args.levels, out=args.photos_out or Path(args.out).parent / name,
                           progress=None if args.json else _say, photos=photos, site=args.site,
                           blur_levels=_blur_levels(args))
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    _print_reflex_blur(data)
    print(f"wrote {data['out']} (load average {data['load_average_before']} before, {data['load_average_after']} after)")
    return 0


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def run(*, frames: int = 4, levels: int = 4, seconds: float = 10.0, fps: float = 30.0,
        store_url: str | None = None, out: Path | str = RESULTS / "perception.json",
        progress: Any = None, eval_frames: int = 6, phantom_frames: int = 10000) -> dict[str, Any]:
    """Run all four measurements; write the records; return a summary."""
    import json

    from kgadapt.bench import perception_quality as quality
    from kgadapt.bench import stats
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store
    from kgadapt.onboard.perception.calibration import CalibrationSettings, run_calibration
    from kgadapt.onboard.perception.illumination import bands_from_rows

    settings = CalibrationSettings(frames_per_level=frames, levels_per_band=levels)
    folder = Path(out).parent  # the calibration's and the quality's files go beside the records
    with tempfile.TemporaryDirectory(prefix="kgadapt-perception-") as tmp:
        url = store_url or f"embedded:{tmp}/store"
        calibration = run_calibration(url, settings=settings, progress=progress,
                                      json_path=folder / "calibration.json", plot_path=folder / "calibration.png")
        # The planner's view: the ranking query on the calibrated graph, judged on fresh frames.
        with open_store(url) as store:
            ask = lambda name, params: run_named(store, name, params)  # noqa: E731
            bands = bands_from_rows(ask("detector_configs", {}))
            if progress:
                progress("oracle gap: every configuration on fresh frames ...")
            oracle = quality.oracle_gap(ask, bands, frames=eval_frames, levels=levels)
            if progress:
                progress("gap under blur with the detector's reflexes: real photographs through the reflex table ...")
            reflex_blur = quality.reflex_blur(ask, progress=progress)
    if progress:
        progress(f"phantoms: {phantom_frames} frames without the site's markers ...")
    from kgadapt.onboard.flight.site import load_site

    site = load_site(models() / "sites" / "demo.site")
    phantoms = quality.phantoms(frames=phantom_frames, site_ids=sorted(site.ids), progress=progress)
    if progress:
        progress("real photographs against the synthetic scene ...")
    photos = quality.photo_agreement()
    target_rates = quality.targets()
    quality_summary = {"oracle": oracle, "reflex_blur": reflex_blur, "phantoms": phantoms, "photos": photos,
                       "targets": target_rates}
    (folder / "perception.quality.json").write_text(json.dumps({"machine": stats.machine_info(), **quality_summary},
                                                             indent=2) + "\n")
    records: list[dict[str, Any]] = []
    for r in calibration["results"]:
        records.append({
            "store": "none", "n": None, "op": f"detect {r['config']} {r['band']} {r['condition']}",
            "mean_ms": r["ms_per_frame"], "sd_ms": None, "p50_ms": None, "p99_ms": r["ms_p99"],
            "reps": r["frames"], "config": r["config"], "band": r["band"], "condition": r["condition"],
            "detection_rate": r["detection_rate"], "false_per_frame": r["false_per_frame"],
            "false_per_reported": r["false_per_reported"], "resolution": "640x480",
        })
    if progress:
        progress(f"frame transport: {seconds:g} s at {fps:g} fps to a detector process ...")
    transport = measure_transport(seconds=seconds, fps=fps)
    for op, key in (("transport publish->detector", "transport_ms"), ("capture->detections", "end_to_end_ms"),
                    ("detector processing", "processing_ms")):
        records.append(stats.make_record(store="zenoh-loopback", n=None, op=op, samples_ms=transport.pop(key),
                                         fps=fps, resolution="640x480"))
    summary = {
        "machine": stats.machine_info(),
        "calibration_best": calibration["best"],
        "calibration_table": calibration["table"],
        "transport": transport,
        "quality": {"oracle": {k: v for k, v in oracle.items() if k != "rows"}, "reflex_blur": reflex_blur,
                    "phantoms": phantoms, "targets": target_rates},
        "records": records,
    }
    path = stats.write_records(out, records)
    summary["out"] = str(path)
    side = Path(path).with_suffix(".summary.json")
    side.write_text(json.dumps({k: v for k, v in summary.items() if k != "records"}, indent=2) + "\n")
    return summary


def measure_transport(*, seconds: float, fps: float, robot: str = "benchperc") -> dict[str, Any]:
    """Camera publisher here, detector in a child process; latencies from the detections' timestamps."""
    from kgadapt.bench import stats
    from kgadapt.onboard.perception.camera import CameraPart, CameraSettings, SyntheticSource
    from kgadapt.onboard.perception.scene import IlluminationProfile
    from kgadapt.shared import keys, messages
    from kgadapt.shared.session import ZenohSettings, open_session

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    session = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    got: queue.Queue[bytes] = queue.Queue()
    sub = session.declare_subscriber(keys.detector_markers(robot, "bench"), lambda s: got.put(s.payload.to_bytes()))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    child = ChildProcess(
        [sys.executable, "-m", "kgadapt.onboard.perception.detector", "--robot", robot, "--host", "bench", "--instance", "bench",
         "--config-json", DAY_JSON, "--connect", endpoint], name="transport bench detector", cwd=REPO, env=env)
    camera = CameraPart(CameraSettings(robot=robot, fps=fps), SyntheticSource(IlluminationProfile.constant(120)))
    try:
        child.wait_ready(30.0)
        camera.setup(session)
        # The first frames pay for the subscription reaching us and OpenCV's first allocations.
        _drain(got, time.monotonic() + 1.0)
        start_published = camera.stats.published
        bodies = [messages.decode(p, "detections") for p in _drain(got, time.monotonic() + seconds)]
        sent = camera.stats.published - start_published
    finally:
        camera.shutdown()
        child.stop(first=signal.SIGTERM)
        sub.undeclare()
        session.close()
    transport = [(b["received"] - b["frame_sent"]) * 1e3 for b in bodies if "frame_sent" in b]
    end_to_end = [(b["time"] - b["frame_time"]) * 1e3 for b in bodies]
    processing = [b["processing_ms"] for b in bodies]
    if not transport:
        raise KgadaptError("the transport bench got no detections")
    t = stats.summarize(transport)
    e = stats.summarize(end_to_end)
    return {
        "fps": fps, "seconds": seconds, "frames_sent": sent, "detections": len(bodies),
        "dropped_stale": bodies[-1].get("dropped", 0) if bodies else 0,
        "transport_p50_ms": round(t.p50_ms, 3), "transport_p99_ms": round(t.p99_ms, 3),
        "end_to_end_p50_ms": round(e.p50_ms, 3), "end_to_end_p99_ms": round(e.p99_ms, 3),
        "target_p99_ms": TRANSPORT_TARGET_P99_MS, "target_met": t.p99_ms <= TRANSPORT_TARGET_P99_MS,
        "transport_ms": transport, "end_to_end_ms": end_to_end, "processing_ms": processing,
    }


def _drain(q: queue.Queue[bytes], until: float) -> list[bytes]:
    items = []
    while True:
        left = until - time.monotonic()
        if left <= 0:
            return items
        try:
            items.append(q.get(timeout=left))
        except queue.Empty:
            return items


def _free_port() -> int:
    from kgadapt.operator.cluster import free_tcp_port

    return free_tcp_port()
