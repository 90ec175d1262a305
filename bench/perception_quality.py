"""Detection quality on the realistic camera model and on real photographs (issue 11).

Used by ``kgadapt bench perception``:

* :func:`oracle_gap` - every configuration x band x condition on frames of
  their own (another seed than the calibration's): detection rate, false
  markers per 1,000 frames, ms per frame; and the **oracle gap**: the rate of
  the configuration the planner picks for the band (the graph's
  ``config_ranking``, condition ``all``: the planner does not know the
  condition) minus the best configuration's rate in that band and condition;
  its worst is also given apart for the conditions the pick is ranked on and
  for those calibration sets apart (motion blur): :func:`gaps_by_ranking`.
* :func:`phantoms` - frames of scenes without the site's markers (real
  photographs at their own light, darkened and blurred; synthetic textures,
  other dictionaries and ChArUco-like boards), through every configuration and
  the confirmation of :mod:`kgadapt.onboard.flight.confirmation`: raw false markers and
  landing targets that would have been sent.
* :func:`photo_agreement` - every configuration (read with the photos'
  dictionary) on the real photographs darkened by the camera model and on the
  synthetic scene at the same level: do the rates agree?
* :func:`targets` - the issue's targets: dark band (level 6) with markers of 5
  px per cell and more, and a 7 px blur at day level.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from kgadapt.onboard.perception.calibration import ALL, APART, CONDITIONS, CalibrationSettings, calibrate, model_configs
from kgadapt.onboard.perception.illumination import Band
from kgadapt.onboard.perception.markers import DetectorConfig, MarkerDetector, Score, score
from kgadapt.onboard.perception.ranking import rank_graph_rows

Progress = Callable[[str], None] | None


# Configurations the models hold but suit for no band, so the adaptation never picks them.
UNSUITED = ("marker_detection_hd", "marker_detection_blur")


def shipped_configs() -> list[DetectorConfig]:
    return [c for c in model_configs() if c.name not in UNSUITED]


def blur_candidate() -> DetectorConfig:
    """The configuration made for motion blur (knowledge/models/perception/marker_detection_blur.rpsl)."""
    return next(c for c in model_configs() if c.name == "marker_detection_blur")


def oracle_gap(ask: Callable[[str, dict[str, Any]], list[dict[str, Any]]], bands: Sequence[Band], *,
               frames: int, levels: int, seed: int = 11, progress: Progress = None) -> dict[str, Any]:
    """Fresh frames per configuration x band x condition, and the planner's pick against the best."""
    configs = shipped_configs()
    settings = CalibrationSettings(frames_per_level=frames, levels_per_band=levels, seed=seed)
    results = calibrate(configs, bands, settings, progress=progress)
    rows = []
    gaps = []
    for band in bands:
        ranking = rank_graph_rows(ask("config_ranking", {"band": band.name}))
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
            "target_met": worst["oracle_gap_points"] <= 5.0, "by_ranking": gaps_by_ranking(gaps)}


def gaps_by_ranking(gaps: Sequence[dict[str, Any]], *, target_points: float = 5.0) -> dict[str, Any]:
    """The worst gap where the band's pick is ranked (the conditions of ``all``) and where it is not
    (calibration's ``APART``: motion blur), each against the target.

    Both figures, because they answer different questions: the first is whether the ranking picks well
    for the light it ranks on; the second is what a pick made for the light loses to a motion it is not
    ranked on. Since the blur condition took the real photographs' marker sizes (f50966c) and left
    ``all`` (4514836), the second is 33 points at day where the first is 2.8; the overall ``worst_gap``
    and ``target_met`` stay over every condition.
    """
    out: dict[str, Any] = {}
    for kind, inside in (("ranked", lambda c: c not in APART), ("apart", lambda c: c in APART)):
        here = [g for g in gaps if inside(g["condition"]) and g["oracle_gap_points"] is not None]
        worst = max(here, key=lambda g: g["oracle_gap_points"], default=None)
        out[kind] = {"conditions": sorted({g["condition"] for g in here}), "worst_gap": worst,
                     "target_met": None if worst is None else worst["oracle_gap_points"] <= target_points}
    return out


def phantom_scenes(total: int, *, run: int = 20):
    """``total`` frames without DICT_4X4_50 markers, in runs of ``run`` consecutive frames of one scene."""
    from kgadapt.onboard.perception.scene import CameraModel, IlluminationProfile, SceneSettings, SyntheticScene
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames

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
    from kgadapt.onboard.flight.confirmation import ConfirmationSettings, MarkerConfirmer
    from kgadapt.onboard.flight.site import SiteMarkers

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
    from kgadapt.onboard.perception.scene import IlluminationProfile, SceneSettings, SyntheticScene
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames, photo_truth, shifted

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
    from kgadapt.onboard.perception.scene import CameraModel, IlluminationProfile, SceneSettings, SyntheticScene

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


# -- real photographs: blur agreement and the oracle gap per dictionary (issue 29) --------------------------

BLUR_PHOTOS = ("contrib_singlemarkersoriginal.jpg", "contrib_img_00.jpg", "contrib_img_01.jpg", "contrib_img_02.jpg",
               "contrib_img_03.jpg", "contrib_chocclusion_original.jpg", "contrib_gboriginal.png")
# (contrib_diamondmarkers.png repeats ids within a frame, which a score by id cannot judge.)


def _photo_dictionary(name: str) -> str:
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, PHOTO_DIR

    found = PHOTO_DICTIONARIES[name]
    return str(PHOTO_DIR / "contrib_tutorial_dict.yml") if found == "custom" else found


def _jpeg(image: np.ndarray, quality: int = 80) -> np.ndarray:
    import cv2

    return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_GRAYSCALE)


def blur_agreement(configs: Sequence[DetectorConfig] | None = None, *, blurs: Sequence[float] = (7.0, 3.0),
                   level: float = 120.0, frames: int = 3, synthetic_frames: int = 10,
                   progress: Progress = None) -> dict[str, Any]:
    """Every configuration's rate on the real photographs blurred vs on the calibration's blur scene, same blur.

    Photographs: each with its own dictionary, through the camera model at
    ``level`` with a motion blur of ``blur`` px at 25 degrees and JPEG 80, scored
    against what OpenCV's default detector finds in the sharp photograph.
    Synthetic: the calibration's ``blur`` condition (markers laid out as the
    photographs show them, lens and motion blur in linear light, noise, JPEG 80)
    with the same blur length; and, for comparison, the scene the calibration
    used before (six 60-125 px markers, no lens blur).
    """
    from kgadapt.onboard.perception.calibration import condition_profile
    from kgadapt.onboard.perception.scene import CameraModel, IlluminationProfile, SceneSettings, SyntheticScene
    from kgadapt.sim.photos import load_photo, photo_frames, photo_truth, shifted

    configs = list(configs) if configs is not None else [*shipped_configs(), blur_candidate()]
    photos = {n: load_photo(n) for n in BLUR_PHOTOS}
    truths = {n: photo_truth(p, _photo_dictionary(n)) for n, p in photos.items()}
    rows = []
    for blur in blurs:
        camera = CameraModel(blur_px=blur, blur_angle=25.0)
        shots = {n: [(_jpeg(f.image), f.shift) for f in photo_frames(photos[n], level, count=frames, camera=camera,
                                                                     seed=3)] for n in photos}
        profile = condition_profile("blur", level)
        profile = replace(profile, camera=replace(profile.camera, blur_px=blur))
        scene = SyntheticScene(SceneSettings(dictionary="DICT_6X6_250").with_options(profile.scene))
        rng = np.random.default_rng(5)
        rendered = [scene.render(i * 0.7, profile, rng) for i in range(synthetic_frames)]
        synthetic = [(_jpeg(f.image), f.truth) for f in rendered]
        old_scene = SyntheticScene(SceneSettings(dictionary="DICT_6X6_250"))
        old_profile = IlluminationProfile.constant(level, camera=CameraModel(blur_px=blur, blur_angle=25.0))
        old = [(_jpeg(f.image), f.truth) for f in (old_scene.render(i * 0.7, old_profile, rng)
                                                     for i in range(synthetic_frames))]
        for config in configs:
            real = Score()
            for n in photos:
                detector = MarkerDetector(replace(config, dictionary=_photo_dictionary(n)))
                for image, shift in shots[n]:
                    found = detector.detect(image)
                    real.add(score(found.ids, found.corners, shifted(truths[n], shift)))
            detector = MarkerDetector(replace(config, dictionary="DICT_6X6_250"))
            figures = {}
            for key, images in (("synthetic", synthetic), ("synthetic_before", old)):
                s = Score()
                for image, truth in images:
                    found = detector.detect(image)
                    s.add(score(found.ids, found.corners, truth))
                figures[key] = round(s.detection_rate, 3)
            difference = round((figures["synthetic"] - real.detection_rate) * 100, 1)
            rows.append({"config": config.name, "blur_px": blur, "photos": round(real.detection_rate, 3),
                         "photo_markers": real.truth, **figures, "difference_points": difference,
                         "difference_before_points": round((figures["synthetic_before"] - real.detection_rate) * 100, 1),
                         "within_10": abs(difference) <= 10})
            if progress:
                progress(f"blur {blur:g} px {config.name:24s} photos {real.detection_rate:6.1%} "
                         f"synthetic {figures['synthetic']:6.1%} (before {figures['synthetic_before']:6.1%})")
    seven = [r for r in rows if r["blur_px"] == 7.0]
    return {"level": level, "photos": list(BLUR_PHOTOS), "markers_per_photo": {n: len(t) for n, t in truths.items()},
            "rows": rows, "target_points": 10.0, "target_met_7px": all(r["within_10"] for r in seven),
            "target_met_all": all(r["within_10"] for r in rows)}


def recoded_photo(photo: np.ndarray, truth: Sequence[dict[str, Any]], dictionary: str) -> tuple[np.ndarray, list[dict]]:
    """The photograph with each marker's code replaced by a marker of ``dictionary`` on the same quad.

    For dictionaries no photograph holds: the paper, light, lens and
    surroundings stay the photograph's; the new code is drawn with the
    photograph's own black and white of that marker (in linear light), softened
    as the photograph's edges are. Ids are the old ones modulo the dictionary's size.
    """
    import cv2

    from kgadapt.onboard.perception.markers import aruco_dictionary
    from kgadapt.onboard.perception.scene import srgb_decode, srgb_encode

    found = aruco_dictionary(dictionary)
    size = int(found.bytesList.shape[0])
    linear = srgb_decode(photo)
    h, w = photo.shape
    out_truth = []
    used: set[int] = set()
    for item in truth:
        marker_id = int(item["id"]) % size
        while marker_id in used:
            marker_id = (marker_id + 1) % size
        used.add(marker_id)
        quad = np.float32(item["corners"]).reshape(4, 2)
        side = 16 * (int(found.markerSize) + 2)
        code = cv2.aruco.generateImageMarker(found, marker_id, side).astype(np.float32) / 255.0
        src = np.float32([[-0.5, -0.5], [side - 0.5, -0.5], [side - 0.5, side - 0.5], [-0.5, side - 0.5]])
        matrix = cv2.getPerspectiveTransform(src, quad)
        warped = cv2.warpPerspective(code, matrix, (w, h), flags=cv2.INTER_AREA)
        mask = np.zeros((h, w), np.float32)
        cv2.fillConvexPoly(mask, np.round(quad * 16).astype(np.int32), 1.0, lineType=cv2.LINE_AA, shift=4)
        inside = linear[mask > 0.5]
        if inside.size < 16:
            continue
        dark, light = np.percentile(inside, 5), np.percentile(inside, 95)
        drawn = cv2.GaussianBlur(dark + (light - dark) * warped, (0, 0), 0.6)
        linear = linear * (1 - mask) + drawn * mask
        out_truth.append({"id": marker_id, "corners": item["corners"]})
    return srgb_encode(np.clip(linear, 0, 1)), out_truth


def photo_oracle_gap(dictionary: str, bands: Sequence[Band], *, calibration: CalibrationSettings = CalibrationSettings(),
                     frames: int = 2, levels: int = 2, progress: Progress = None,
                     given: Sequence[tuple[str, np.ndarray]] | None = None, site: Any = None) -> dict[str, Any]:
    """Models naming ``dictionary``, calibrated; their first-ranked per band against the best on real photographs.

    ``site`` (:class:`~kgadapt.onboard.flight.site.SiteMarkers`): calibrated with its markers when it is of
    ``dictionary`` (its ids, sizes and print layout), as ``kgadapt perception calibrate --site`` does.

    Real frames: the photographs of ``dictionary``'s markers where there are
    some (DICT_6X6_250, the custom file), else the DICT_6X6_250 photographs
    recoded (:func:`recoded_photo`), darkened to ``levels`` levels of every band
    by the camera model, clean, with a 7 px motion blur, and with a saturated
    window over the top 15 % (markers under it count neither way).
    """
    from kgadapt.onboard.perception.calibration import band_levels, rank
    from kgadapt.onboard.perception.scene import CameraModel, LightLayout
    from kgadapt.sim.photos import PHOTO_DICTIONARIES, load_photo, photo_frames, photo_truth, shifted

    configs = [replace(c, dictionary=dictionary) for c in shipped_configs()]
    results = calibrate(configs, bands, calibration, site=site)
    picks = {b.name: rank(results, b.name)[0].config for b in bands}
    own = [n for n in BLUR_PHOTOS if _photo_dictionary(n) == dictionary]
    if given is not None:
        source = "photographs: " + ", ".join(n for n, _ in given)
        photos = [(p, photo_truth(p, dictionary)) for _, p in given]
    elif own:
        source = "photographs"
        photos = [(load_photo(n), photo_truth(load_photo(n), dictionary)) for n in own]
    else:
        source = "DICT_6X6_250 photographs recoded"
        photos = [recoded_photo(load_photo(n), photo_truth(load_photo(n), "DICT_6X6_250"), dictionary)
                  for n, d in PHOTO_DICTIONARIES.items() if d == "DICT_6X6_250"]
    conditions = {"clean": (CameraModel(), LightLayout()), "blur": (CameraModel(blur_px=7.0, blur_angle=25.0), LightLayout()),
                  "window": (CameraModel(), LightLayout(window=0.15))}
    detectors = [MarkerDetector(c) for c in configs]
    gaps = []
    for band in bands:
        for condition, (camera, light) in conditions.items():
            scores = [Score() for _ in configs]
            for level in band_levels(band, levels):
                for k, (photo, truth) in enumerate(photos):
                    for frame in photo_frames(photo, level, count=frames, camera=camera, light=light, seed=k):
                        image = _jpeg(frame.image)
                        moved = shifted(truth, frame.shift)
                        edge = light.window * photo.shape[0] + 2
                        hidden = [t["id"] for t in moved if min(y for _x, y in t["corners"]) <= edge] \
                            if light.window else []
                        kept = [t for t in moved if t["id"] not in hidden]
                        for i, detector in enumerate(detectors):
                            found = detector.detect(image)
                            scores[i].add(score(found.ids, found.corners, kept, ignore=hidden))
            rates = {c.name: round(s.detection_rate, 4) for c, s in zip(configs, scores)}
            best = max(rates, key=lambda n: rates[n])
            gap = round((rates[best] - rates[picks[band.name]]) * 100, 1)
            gaps.append({"band": band.name, "condition": condition, "planner_pick": picks[band.name], "best": best,
                         "rates": rates, "oracle_gap_points": gap})
            if progress:
                progress(f"{dictionary} {band.name}/{condition}: pick {picks[band.name]} {rates[picks[band.name]]:.1%}, "
                         f"best {best} {rates[best]:.1%}, gap {gap} points")
    worst = max(gaps, key=lambda g: g["oracle_gap_points"])
    return {"dictionary": dictionary, "frames": source, "photo_markers": [len(t) for _, t in photos],
            "site_layout": site.layout if site is not None and site.dictionary == dictionary else None,
            "picks": picks, "gaps": gaps, "worst_gap": worst,
            "target_points": 5.0, "target_met": worst["oracle_gap_points"] <= 5.0,
            "calibrated": [{"config": r.config, "band": r.band, "condition": r.condition,
                            "detection_rate": r.detection_rate} for r in results]}


# -- the robot under blur, end to end: the detector's reflexes on real photographs (issue 29) ---------------

def reflex_under_blur(table: Any, levels: Mapping[str, float | Sequence[float]], *, photos: Sequence[str] = BLUR_PHOTOS,
                      sharp_frames: int = 15, blur_frames: int = 30, reaction_frames: int = 5,
                      blur_px: float = 7.0, fps: float = 30.0, settings: Any = None, timed: bool = True,
                      progress: Progress = None,
                      given: Sequence[tuple[str, np.ndarray, str]] | None = None) -> dict[str, Any]:
    """What the robot finds under motion blur with the detector's reflexes, against the best configuration.

    For each band in ``levels`` (band -> light level, or several: the band's
    figures then pool them) and each photograph: a
    fresh :class:`~kgadapt.onboard.perception.reflex.Reflex` on ``table`` (the
    graph's ``reflex_table``, compiled) runs the band's pick; it is fed
    ``sharp_frames`` frames of the photograph through the camera model at the
    level (markers seen), then ``blur_frames`` of the same scene with a
    ``blur_px`` motion blur at 25 degrees (JPEG 80), at ``fps``. Per frame it
    does what the running detector does (kgadapt.onboard.perception.detector):
    the frame's light estimate (weighted around the markers of the last
    second) to ``on_light``, the running configuration's detection, the hedge
    the reflex asks for on frames it found nothing on (every frame while a try
    after a fall is judged), within the graph's ms-per-frame budget when
    ``timed`` (the detector's rule, with measured times), ``on_result`` with
    the clean counts, and whichever of the two found more is what it publishes.
    The rate is over the blurred frames after the first ``reaction_frames``
    (the reflex's reaction); the oracle is the best single configuration of
    the table on those same frames. ``given``: ``(name, grey 640x480 frame,
    dictionary)`` of photographs to use instead of the shipped ``photos``
    (e.g. real photographs of another dictionary's markers, not shipped).
    """
    import time

    from kgadapt.onboard.perception.illumination import estimate_light
    from kgadapt.onboard.perception.reflex import Reflex, ReflexSettings
    from kgadapt.onboard.perception.scene import CameraModel
    from kgadapt.sim.photos import load_photo, photo_frames, photo_truth, shifted

    settings = settings or ReflexSettings()
    choices = table.choices()
    cores: dict[str, dict[str, MarkerDetector]] = {}  # dictionary -> configuration -> detector
    sharp_camera, blur_camera = CameraModel(), CameraModel(blur_px=blur_px, blur_angle=25.0)
    out: dict[str, Any] = {}
    for band, level in levels.items():
        entry = table.entry(band)
        if entry is None or entry.best is None:
            raise KeyError(f"reflex table has no in-place choice for band {band!r}")
        pick = entry.best.config
        reflex_score = Score()
        oracle = {name: Score() for name in choices}
        per_photo: dict[str, dict[str, float]] = {}
        swaps: list[dict[str, Any]] = []
        hedged = 0
        sources = given if given is not None else [(n, load_photo(n), _photo_dictionary(n)) for n in photos]
        band_levels = [float(v) for v in level] if isinstance(level, (list, tuple)) else [float(level)]
        runs = [(lv, k, source) for lv in band_levels for k, source in enumerate(sources)]
        for lv, k, (name, photo, dictionary) in runs:
            here = cores.setdefault(dictionary, {n: MarkerDetector(replace(c.settings, dictionary=dictionary))
                                                 for n, c in choices.items()})
            truth = photo_truth(photo, dictionary)
            frames = [(False, f) for f in photo_frames(photo, lv, count=sharp_frames, camera=sharp_camera, seed=k)]
            frames += [(True, f) for f in photo_frames(photo, lv, count=blur_frames, camera=blur_camera,
                                                       seed=100 + k)]
            reflex = Reflex(table=table, running=pick, settings=settings)
            seen: tuple[float, Any] = (-1e9, [])
            spent: dict[str, float] = {}
            blurred = 0
            mine, theirs = Score(), {n: Score() for n in here}
            for i, (is_blur, frame) in enumerate(frames):
                now = i / fps
                image = _jpeg(frame.image)
                at, corners = seen
                level_now = estimate_light(image, corners if now - at <= 1.0 else ()).level
                swap = reflex.on_light(level_now)
                if swap is not None:
                    swaps.append({"photo": name, "frame": i, "blurred": is_blur, "config": swap.config,
                                  "evidence": str(swap.evidence)})
                start = time.perf_counter()
                found = here[reflex.running].detect(image)
                ms = (time.perf_counter() - start) * 1e3
                count = found.clean_count
                hedge = reflex.hedge_for(level_now) if (not count or reflex.comparing) else None
                hedge_found = None
                if hedge is not None and hedge in here and table.budget_ms is not None:
                    cost = spent.get(hedge, choices[hedge].ms_per_frame or ms)
                    if not timed or ms + cost <= table.budget_ms:
                        start = time.perf_counter()
                        hedge_found = here[hedge].detect(image)
                        spent[hedge] = (time.perf_counter() - start) * 1e3
                        hedged += 1
                if hedge_found is None:
                    hedge = None
                hedge_count = hedge_found.clean_count if hedge_found is not None else 0
                swap = reflex.on_result(count, now, hedge=hedge, hedge_found=hedge_count, level=level_now)
                published = hedge_found if hedge_found is not None and hedge_count > count else found
                if swap is not None:
                    swaps.append({"photo": name, "frame": i, "blurred": is_blur, "config": swap.config,
                                  "evidence": str(swap.evidence)})
                if published.ids:
                    seen = (now, published.corners)
                if not is_blur:
                    continue
                blurred += 1
                if blurred <= reaction_frames:
                    continue
                moved = shifted(truth, frame.shift)
                mine.add(score(published.ids, published.corners, moved))
                for n, detector in here.items():
                    f = detector.detect(image)
                    theirs[n].add(score(f.ids, f.corners, moved))
            reflex_score.add(mine)
            for n, s in theirs.items():
                oracle[n].add(s)
            per_photo[name if len(band_levels) == 1 else f"{name} @ {lv:g}"] = {"reflex": round(mine.detection_rate, 4),
                               **{n: round(s.detection_rate, 4) for n, s in theirs.items()}}
        rates = {n: round(s.detection_rate, 4) for n, s in oracle.items()}
        best = max(rates, key=lambda n: rates[n])
        rate = round(reflex_score.detection_rate, 4)
        gap = round((rates[best] - rate) * 100, 1)
        out[band] = {"level": level, "pick": pick, "reflex_rate": rate, "pick_rate": rates[pick],
                     "best": best, "best_rate": rates[best], "rates": rates, "gap_points": gap,
                     "static_gap_points": round((rates[best] - rates[pick]) * 100, 1),
                     "markers": reflex_score.truth, "false_per_frame": round(reflex_score.false_per_frame, 4),
                     "hedged_frames": hedged, "per_photo": per_photo, "swaps": swaps}
        if progress:
            shown = ", ".join(f"{v:g}" for v in band_levels)
            progress(f"blur {blur_px:g} px at {band} (level {shown}): with the reflexes {rate:.1%}, the pick "
                     f"{pick} alone {rates[pick]:.1%}, best {best} {rates[best]:.1%}: gap {gap} points")
    worst = max(out.values(), key=lambda v: v["gap_points"], default=None)
    return {"photos": [n for n, _p, _d in given] if given is not None else list(photos),
            "dictionaries": sorted({d for _n, _p, d in given}) if given is not None else None,
            "sharp_frames": sharp_frames, "blur_frames": blur_frames,
            "reaction_frames": reaction_frames, "blur_px": blur_px, "fps": fps, "timed": timed,
            "bands": out, "worst_gap_points": None if worst is None else worst["gap_points"],
            "target_points": 5.0, "target_met": None if worst is None else worst["gap_points"] <= 5.0}


# The levels the bench measures blur at: the day level, and the middle of the shipped dusk band.
BLUR_LEVELS = {"dusk": 25.0, "day": 120.0}


def reflex_blur(ask: Callable[[str, dict[str, Any]], list[dict[str, Any]]], *, deployment: str = "detector_day",
                host: str = "onboard", levels: Mapping[str, float | Sequence[float]] = BLUR_LEVELS, progress: Progress = None,
                **options: Any) -> dict[str, Any]:
    """:func:`reflex_under_blur` on the reflex table a detector of ``deployment`` on ``host`` reads from the
    (calibrated) graph, as the running detector compiles it."""
    from kgadapt.onboard.perception.markers import parse_config
    from kgadapt.onboard.perception.reflex import ReflexTable

    table = ReflexTable.from_rows(ask("reflex_table", {"deployment": deployment, "host": host}),
                                  parse=lambda name, raw, dictionary: parse_config(name, raw, dictionary=dictionary))
    return {"deployment": deployment, "host": host,
            **reflex_under_blur(table, levels, progress=progress, **options)}
