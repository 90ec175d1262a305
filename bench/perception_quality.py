"""Detection quality on the realistic camera model and on real photographs (issue 11).

Used by ``kgadapt bench perception``:

* :func:`oracle_gap` - every configuration x band x condition on frames of
  their own (another seed than the calibration's): detection rate, false
  markers per 1,000 frames, ms per frame; and the **oracle gap**: the rate of
  the configuration the planner picks for the band (the graph's
  ``config_ranking``, condition ``all``: the planner does not know the
  condition) minus the best configuration's rate in that band and condition.
* :func:`phantoms` - frames of scenes without the site's markers (real
  photographs at their own light, darkened and blurred; synthetic textures,
  other dictionaries and ChArUco-like boards), through every configuration and
  the confirmation of :mod:`kgadapt.onboard.confirmation`: raw false markers and
  landing targets that would have been sent.
* :func:`photo_agreement` - every configuration (read with the photos'
  dictionary) on the real photographs darkened by the camera model and on the
  synthetic scene at the same level: do the rates agree?
* :func:`targets` - the issue's targets: dark band (level 6) with markers of 5
  px per cell and more, and a 7 px blur at day level.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable, Sequence

import numpy as np

from kgadapt.onboard.calibration import ALL, CONDITIONS, CalibrationSettings, calibrate, model_configs, rank_rows
from kgadapt.onboard.illumination import Band
from kgadapt.onboard.markers import DetectorConfig, MarkerDetector, Score, score

Progress = Callable[[str], None] | None


def shipped_configs() -> list[DetectorConfig]:
    return [c for c in model_configs() if c.name != "marker_detection_hd"]  # hd is suited for no band


def oracle_gap(ask: Callable[[str, dict[str, Any]], list[dict[str, Any]]], bands: Sequence[Band], *,
               frames: int, levels: int, seed: int = 11, progress: Progress = None) -> dict[str, Any]:
    """Fresh frames per configuration x band x condition, and the planner's pick against the best."""
    configs = shipped_configs()
    settings = CalibrationSettings(frames_per_level=frames, levels_per_band=levels, seed=seed)
    results = calibrate(configs, bands, settings, progress=progress)
    rows = []
    gaps = []
    for band in bands:
        ranking = rank_rows(ask("config_ranking", {"band": band.name}), score=lambda r: r["score"],
                            ms=lambda r: r["ms_per_frame"])
        pick = ranking[0]["config"] if ranking else None
        for condition in (*CONDITIONS, ALL):
            here = {r.config: r for r in results if r.band == band.name and r.condition == condition}
            best = max(here.values(), key=lambda r: (r.detection_rate, -r.ms_per_frame))
            picked = here.get(pick)
            gap = None if picked is None else round((best.detection_rate - picked.detection_rate) * 100, 1)
            gaps.append({"band": band.name, "condition": condition, "planner_pick": pick, "best": best.config,
                         "pick_rate": None if picked is None else picked.detection_rate,
                         "best_rate": best.detection_rate, "oracle_gap_points": gap})
            for r in here.values():
                rows.append({"config": r.config, "band": r.band, "condition": r.condition,
                             "detection_rate": r.detection_rate, "false_per_1000_frames": round(r.false_per_frame * 1000, 1),
                             "ms_per_frame": r.ms_per_frame, "frames": r.frames})
    worst = max((g for g in gaps if g["oracle_gap_points"] is not None), key=lambda g: g["oracle_gap_points"])
    return {"rows": rows, "gaps": gaps, "worst_gap": worst, "target_points": 5.0,
            "target_met": worst["oracle_gap_points"] <= 5.0}


def phantom_scenes(total: int, *, run: int = 20):
    """``total`` frames without DICT_4X4_50 markers, in runs of ``run`` consecutive frames of one scene."""
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames
    from kgadapt.sim.scenario import CameraModel, IlluminationProfile, SceneSettings, SyntheticScene

    photos = [load_photo(name) for name in PHOTO_DICTIONARIES]
    variants = [(None, CameraModel()), (30.0, CameraModel()), (6.0, CameraModel()), (100.0, CameraModel(blur_px=7))]
    made = 0
    k = 0
    while made < total:
        n = min(run, total - made)
        if k % 3 != 2:  # two runs of photographs for one of synthetic patterns
            photo = photos[k % len(photos)]
            level, camera = variants[(k // len(photos)) % len(variants)]
            for frame in photo_frames(photo, level, count=n, camera=camera, seed=k):
                yield f"photo:{k % len(photos)}", frame.image
        else:
            scene = SyntheticScene(SceneSettings(markers=(), other_dict=3, charuco=1, texture=2, seed=k))
            level = (120.0, 25.0, 6.0)[(k // 3) % 3]
            profile = IlluminationProfile.constant(level)
            for i in range(n):
                yield "synthetic", scene.render(i / 30, profile).image
        made += n
        k += 1


def phantoms(*, frames: int, site_ids: Sequence[int], progress: Progress = None) -> dict[str, Any]:
    """Every configuration over ``frames`` frames without the site's markers: raw phantoms and landing targets."""
    from kgadapt.onboard.confirmation import ConfirmationSettings, MarkerConfirmer
    from kgadapt.onboard.site import SiteMarkers

    configs = shipped_configs()
    detectors = [MarkerDetector(c) for c in configs]
    site = SiteMarkers(site="bench", dictionary="DICT_4X4_50", sizes_m={i: 0.2 for i in site_ids})
    open_check = [MarkerConfirmer() for _ in configs]  # no site known: steadiness and clean cells only
    site_check = [MarkerConfirmer(ConfirmationSettings(site=site)) for _ in configs]
    raw = [0] * len(configs)
    unclean_passed = [0] * len(configs)
    targets_open = [0] * len(configs)
    targets_site = [0] * len(configs)
    seen = 0
    last_scene = None
    for scene, image in phantom_scenes(frames):
        seen += 1
        if scene != last_scene:  # a new scene: the confirmer starts over as after a gap
            last_scene = scene
        for i, detector in enumerate(detectors):
            found = detector.detect(image)
            raw[i] += len(found.ids)
            unclean_passed[i] += sum(found.clean)
            t = float(seen)
            targets_open[i] += bool(open_check[i].update(found.ids, found.corners, t, found.clean))
            targets_site[i] += bool(site_check[i].update(found.ids, found.corners, t, found.clean))
        if progress and seen % 2000 == 0:
            progress(f"phantoms: {seen} frames, raw {sum(raw)}, landing targets {sum(targets_open)} / {sum(targets_site)}")
    per_config = {c.name: {"raw_false_markers": raw[i], "raw_per_1000_frames": round(raw[i] * 1000 / seen, 1),
                           "clean_cells_passed": unclean_passed[i],
                           "landing_targets_no_site": targets_open[i], "landing_targets_with_site": targets_site[i]}
                  for i, c in enumerate(configs)}
    return {"frames": seen, "per_config": per_config, "target": 0,
            "target_met": all(v["landing_targets_no_site"] == 0 and v["landing_targets_with_site"] == 0
                              for v in per_config.values())}


def photo_agreement(*, levels: Sequence[float] = (6.0, 15.0, 30.0), frames: int = 8) -> dict[str, Any]:
    """Every configuration with the photos' dictionary: rate on darkened photos and on the synthetic scene."""
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames, photo_truth, shifted
    from kgadapt.sim.scenario import IlluminationProfile, SceneSettings, SyntheticScene

    names = [n for n, d in PHOTO_DICTIONARIES.items() if d == "DICT_6X6_250"]
    photos = {n: load_photo(n) for n in names}
    truths = {n: photo_truth(p, "DICT_6X6_250") for n, p in photos.items()}
    scene = SyntheticScene(SceneSettings(dictionary="DICT_6X6_250"))
    rows = []
    for config in shipped_configs():
        detector = MarkerDetector(replace(config, dictionary="DICT_6X6_250"))
        for level in (None, *levels):
            per_photo = {}
            total = Score()
            for n in names:
                s = Score()
                for frame in photo_frames(photos[n], level, count=frames, seed=3):
                    found = detector.detect(frame.image)
                    s.add(score(found.ids, found.corners, shifted(truths[n], frame.shift)))
                per_photo[n] = round(s.detection_rate, 3)
                total.add(s)
            synthetic = None
            if level is not None:
                syn = Score()
                rng = np.random.default_rng(5)
                for i in range(frames):
                    f = scene.render(i * 0.7, IlluminationProfile.constant(level), rng)
                    found = detector.detect(f.image)
                    syn.add(score(found.ids, found.corners, f.truth))
                synthetic = round(syn.detection_rate, 3)
            rows.append({"config": config.name, "level": level, "photos": round(total.detection_rate, 3),
                         "photo_false_per_frame": round(total.false_per_frame, 3), "per_photo": per_photo,
                         "synthetic": synthetic,
                         "difference_points": None if synthetic is None else round((total.detection_rate - synthetic) * 100, 1)})
    return {"markers_per_photo": {n: len(t) for n, t in truths.items()}, "rows": rows}


def targets(*, frames: int = 20) -> dict[str, Any]:
    """The issue's two rate targets, for every configuration."""
    from kgadapt.sim.scenario import CameraModel, IlluminationProfile, SceneSettings, SyntheticScene

    out: dict[str, Any] = {}
    cases = {
        "dark level 6, markers 10-20 px per cell": (6.0, CameraModel(), 1.0),
        "dark level 6, markers 5-10 px per cell": (6.0, CameraModel(), 0.5),
        "day level 120, 7 px motion blur": (120.0, CameraModel(blur_px=7.0, blur_angle=25.0), 1.0),
    }
    for name, (level, camera, scale) in cases.items():
        scene = SyntheticScene(SceneSettings(marker_scale=scale))
        profile = IlluminationProfile.constant(level, camera=camera)
        rng = np.random.default_rng(13)
        rendered = [scene.render(i * 0.7, profile, rng) for i in range(frames)]
        out[name] = {}
        for config in shipped_configs():
            detector = MarkerDetector(config)
            s = Score()
            for f in rendered:
                found = detector.detect(f.image)
                s.add(score(found.ids, found.corners, f.truth))
            out[name][config.name] = round(s.detection_rate, 3)
    return out
