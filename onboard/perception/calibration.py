"""Calibration: how well each detector configuration does in each illumination band and condition.

Every configuration the knowledge store has for a feature (named queries
``detector_configs`` and ``detector_config``) runs over the same synthetic
frames of the realistic camera (sRGB, Poisson-Gaussian noise, 8 bits; see
:mod:`kgadapt.onboard.perception.scene`): for each band, ``levels_per_band`` fixed levels at
the midpoints of equal slices of the band, and for each level every condition
of :data:`CONDITIONS` (clean, a 7 px motion blur, uneven light with blind
stripes, a saturated window, small markers), ``frames_per_level`` frames each,
JPEG-compressed as on the wire. A detection counts when its id is right and
its corners are within ``tolerance_px`` of the truth; anything else it reports
is a false detection. Every configuration is calibrated in every band, not
only the band it is suited for, so the planner can rank them all.

Figures per (configuration, band, condition), and per (configuration, band)
over all conditions but :data:`APART` (motion blur) as condition ``all`` (the
mean of those conditions' figures: each weighs alike): ``detection_rate`` (hits / markers
shown), ``false_per_frame`` (false markers per frame), ``false_per_reported``
(false markers / markers reported), ``ms_per_frame`` (mean time of
pre-processing plus detection). They go into the graph as
``(PerceptionGraph)-[:CALIBRATED {condition}]->(IlluminationBand)`` through
``kgadapt.knowledge.runtime.record_calibration``, and into a JSON file and a PNG plot.

The ranking of a band and condition (:func:`rank` here, ``config_ranking`` and
``reflex_table`` for the planner and the detector's reflexes) follows one rule,
:mod:`kgadapt.onboard.perception.ranking`: detection rate minus ``penalty`` x
false markers per frame; scores within ``tie_rate`` (half a point) of the best
are equal, and of those the faster beyond the timing's noise goes first, then
the more robust in the band's other conditions, then by name.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from kgadapt.onboard.flight.site import DEFAULT_DICTIONARY, SiteMarkers
from kgadapt.onboard.perception.illumination import Band, bands_from_rows
from kgadapt.onboard.perception.markers import DetectorConfig, MarkerDetector, Score, aruco_dictionary, parse_config, score
from kgadapt.onboard.perception.ranking import TIE_RATE, rank_rows, robustness_of, score_of
from kgadapt.shared.errors import ConfigError, KgadaptError
from kgadapt.shared.preprocessing import is_dictionary_file
from kgadapt.shared.resources import models, results_dir

log = logging.getLogger(__name__)

RESULTS_DIR = results_dir()
FEATURE = "MarkerDetection"


# condition -> what it changes: profile keyword arguments and scene options.
CONDITIONS: dict[str, dict[str, Any]] = {
    "clean": {},
    # A 7 px motion blur, in linear light before the noise, through a lens that is not perfectly sharp, on
    # markers sized and set as the real photographs show them: the rates then agree with the photographs
    # blurred alike (bench perception, photo_blur_agreement; docs/perception.md).
    "blur": {"camera": {"blur_px": 7.0, "blur_angle": 25.0, "lens_sigma": 0.6}, "scene": {"layout": "photos"}},
    "uneven": {"light": {"stripes": 5, "stripe_depth": 0.6}, "gradient": 0.6},
    "window": {"light": {"window": 0.15}},
    "small": {"scene": {"marker_scale": 0.4}},  # 25-50 px markers: 4-8 px per cell
}
ALL = "all"
# Conditions figured on their own but not into ``all``: the band as a whole is what the light decides, and
# motion blur is not the light but the flight. Mixed in, a 7 px blur as likely as clean frames would make the
# heavy dark configuration first in the day band (it holds 13 % of blurred markers, the day one 3 %): a
# light decision hanging on a motion nobody measured. Its figures stay per condition (config_ranking, blur).
APART = ("blur",)
SYNTHETIC = "synthetic"  # the source of figures from the synthetic scene; recorded frames: frames:NAME


def condition_profile(condition: str, level: float) -> Any:
    """The constant-light profile of ``condition`` at ``level``."""
    from kgadapt.onboard.perception.scene import CameraModel, IlluminationProfile, LightLayout, SceneOptions

    spec = CONDITIONS.get(condition)
    if spec is None:
        raise ConfigError(f"unknown calibration condition {condition!r} (use {', '.join(CONDITIONS)})")
    kwargs: dict[str, Any] = {}
    if "camera" in spec:
        kwargs["camera"] = CameraModel(**spec["camera"])
    if "light" in spec:
        kwargs["light"] = LightLayout(**spec["light"])
    if "scene" in spec:
        kwargs["scene"] = SceneOptions(**spec["scene"])
    if "gradient" in spec:
        kwargs["gradient"] = spec["gradient"]
    return IlluminationProfile.constant(level, **kwargs)


@dataclass(frozen=True, kw_only=True)
class CalibrationSettings:
    """How much to render and how to judge it."""

    frames_per_level: int = 4  # per condition: 4 frames x 5 conditions = 20 frames per level
    levels_per_band: int = 4
    conditions: tuple[str, ...] = tuple(CONDITIONS)
    max_level: float = 200.0  # brighter than this saturates the synthetic camera
    jpeg_quality: int = 80
    width: int = 640
    height: int = 480
    tolerance_px: float = 5.0
    tie_rate: float = TIE_RATE
    seed: int = 7

    def __post_init__(self) -> None:
        if self.frames_per_level < 1 or self.levels_per_band < 1:
            raise ConfigError("calibration needs at least one level per band and one frame per level")
        unknown = [c for c in self.conditions if c not in CONDITIONS]
        if unknown or not self.conditions:
            raise ConfigError(f"calibration conditions {unknown or '(none)'}: use some of {', '.join(CONDITIONS)}")


@dataclass
class CalibrationResult:
    """One configuration in one band and condition (``all``: every condition of the band together)."""

    config: str
    band: str
    detection_rate: float
    false_per_frame: float
    false_per_reported: float
    ms_per_frame: float
    ms_p99: float
    frames: int
    markers: int
    condition: str = ALL
    per_level: list[dict[str, float]] = field(default_factory=list)

    @property
    def score(self) -> float:
        return score_of(self.detection_rate, self.false_per_frame)


def band_levels(band: Band, count: int, *, max_level: float = 200.0) -> list[float]:
    """``count`` levels at the midpoints of equal slices of ``band`` (capped at ``max_level``)."""
    low, high = band.min_level, min(band.max_level, max_level)
    if high <= low:
        high = low + 1.0
    step = (high - low) / count
    return [round(low + step * (i + 0.5), 2) for i in range(count)]


Frame = tuple[float, np.ndarray, list[Any], list[int]]  # (level, grey frame, truth, ids partly hidden)


def render_test_frames(bands: Sequence[Band], settings: CalibrationSettings, *, dictionary: str = DEFAULT_DICTIONARY,
                       site: SiteMarkers | None = None) -> dict[tuple[str, str], list[Frame]]:
    """The frames configurations of ``dictionary`` are judged on: ``(band, condition) -> [(level, grey, truth), ...]``.

    The markers are ``dictionary``'s: the site's ids and sizes, printed as its
    ``layout`` says (apart, in a chessboard's white squares, or touching in a
    board with a marker in every square), when ``site`` is of that dictionary,
    else the scene's poses with ids the dictionary has. Every
    dictionary gets the same poses, light, noise and seed, so its figures differ
    from another's only by what its markers are.
    """
    import cv2

    from kgadapt.onboard.perception.scene import SceneSettings, SyntheticScene, markers_for

    size = int(aruco_dictionary(dictionary).bytesList.shape[0])
    use_site = site is not None and site.dictionary == dictionary
    ids = sorted(site.sizes_m) if use_site and site else ()
    sizes = dict(site.sizes_m) if use_site and site else None
    base = SceneSettings(width=settings.width, height=settings.height, dictionary=dictionary,
                         print_layout=site.layout if use_site and site else "apart")
    rng = np.random.default_rng(settings.seed)
    out: dict[tuple[str, str], list[Frame]] = {}
    scenes: dict[Any, Any] = {}
    for band in bands:
        for condition in settings.conditions:
            frames: list[Frame] = []
            for level in band_levels(band, settings.levels_per_band, max_level=settings.max_level):
                profile = condition_profile(condition, level)
                scene = scenes.get(profile.scene)
                if scene is None:
                    chosen = base.with_options(profile.scene)
                    chosen = replace(chosen, markers=markers_for(size, ids, sizes, chosen.markers) if chosen.markers
                                     else ())
                    scene = scenes[profile.scene] = SyntheticScene(chosen)
                for i in range(settings.frames_per_level):
                    frame = scene.render(i * 0.7, profile, rng)  # the sway moves the markers between frames
                    ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, settings.jpeg_quality])
                    gray = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE) if ok else None
                    if gray is None:
                        raise ConfigError(f"cannot JPEG-encode a {settings.width}x{settings.height} frame at quality "
                                          f"{settings.jpeg_quality}")
                    frames.append((level, gray, frame.truth, frame.extras.get("hidden", [])))
            out[(band.name, condition)] = frames
    return out


def judge(detectors: Sequence[MarkerDetector], frames: Sequence[Frame], *, tolerance_px: float
          ) -> list[tuple[Score, list[float], dict[float, tuple[Score, list[float]]]]]:
    """Every frame through every detector in turn: per detector its score, times and per-level figures.

    In turn, so a burst of load from elsewhere on the machine hits all
    configurations alike instead of one of them.
    """
    out: list[tuple[Score, list[float], dict[float, tuple[Score, list[float]]]]] = [(Score(), [], {}) for _ in detectors]
    for level, gray, truth, hidden in frames:
        for i, detector in enumerate(detectors):
            found = detector.detect(gray)
            s = score(found.ids, found.corners, truth, tolerance_px=tolerance_px, ignore=hidden)
            total, times, per_level = out[i]
            total.add(s)
            times.append(found.processing_ms)
            level_score, level_times = per_level.setdefault(level, (Score(), []))
            level_score.add(s)
            level_times.append(found.processing_ms)
    return out


def result_of(config: str, band: str, condition: str, total: Score, times: list[float],
            per_level: dict[float, tuple[Score, list[float]]]) -> CalibrationResult:
    return CalibrationResult(
        config=config, band=band, condition=condition,
        detection_rate=round(total.detection_rate, 4), false_per_frame=round(total.false_per_frame, 4),
        false_per_reported=round(total.false_per_reported, 4),
        ms_per_frame=round(float(np.mean(times)), 3), ms_p99=round(float(np.percentile(times, 99)), 3),
        frames=total.frames, markers=total.truth,
        per_level=[
            {"level": lv, "detection_rate": round(sc.detection_rate, 4), "false_per_frame": round(sc.false_per_frame, 4),
             "ms_per_frame": round(float(np.mean(ts)), 3)}
            for lv, (sc, ts) in sorted(per_level.items())
        ],
    )


def calibrate(
    configs: Sequence[DetectorConfig],
    bands: Sequence[Band],
    settings: CalibrationSettings = CalibrationSettings(),
    *,
    progress: Callable[[str], None] | None = None,
    site: SiteMarkers | None = None,
) -> list[CalibrationResult]:
    """Run every configuration over every band's and condition's frames; return the figures.

    One result per (configuration, band, condition) and one per (configuration,
    band) over all its conditions (condition ``all``). Each configuration is
    shown the markers of the dictionary it names (and the ``site``'s ids and
    sizes when the site prints that dictionary).
    """
    if not configs:
        raise ConfigError("nothing to calibrate: no detector configurations")
    if not bands:
        raise ConfigError("nothing to calibrate: no illumination bands")
    results: dict[tuple[str, str, str], CalibrationResult] = {}
    # Each configuration on the markers of the dictionary it names: one set of frames per dictionary.
    for dictionary in sorted({config.dictionary for config in configs}):
        group = [config for config in configs if config.dictionary == dictionary]
        frames = render_test_frames(bands, settings, dictionary=dictionary, site=site)
        detectors = [MarkerDetector(config) for config in group]
        for detector in detectors:
            detector.detect(next(iter(frames.values()))[0][1])  # warm-up: the first call allocates
        for band in bands:
            overall: list[tuple[Score, list[float], dict[float, tuple[Score, list[float]]]]] = [
                (Score(), [], {}) for _ in detectors]
            for condition in settings.conditions:
                judged = judge(detectors, frames[(band.name, condition)], tolerance_px=settings.tolerance_px)
                for i, config in enumerate(group):
                    total, times, per_level = judged[i]
                    results[(config.name, band.name, condition)] = result_of(config.name, band.name, condition, total,
                                                                           times, per_level)
                    if condition in APART and any(c not in APART for c in settings.conditions):
                        continue
                    all_total, all_times, all_levels = overall[i]
                    all_total.add(total)
                    all_times.extend(times)
                    for level, (sc, ts) in per_level.items():
                        level_score, level_times = all_levels.setdefault(level, (Score(), []))
                        level_score.add(sc)
                        level_times.extend(ts)
            for i, config in enumerate(group):
                result = result_of(config.name, band.name, ALL, *overall[i])
                # The band as a whole weighs every condition alike, whatever number of markers its scene shows
                # (the blur scene shows thirteen small ones, the others six).
                parts = [results[(config.name, band.name, c)] for c in settings.conditions if c not in APART] or \
                    [results[(config.name, band.name, c)] for c in settings.conditions]
                result.detection_rate = round(float(np.mean([r.detection_rate for r in parts])), 4)
                result.false_per_frame = round(float(np.mean([r.false_per_frame for r in parts])), 4)
                result.false_per_reported = round(float(np.mean([r.false_per_reported for r in parts])), 4)
                results[(config.name, band.name, ALL)] = result
                if progress:
                    progress(f"{config.name:28s} {band.name:6s} rate {result.detection_rate:6.1%} "
                             f"false/frame {result.false_per_frame:6.3f} {result.ms_per_frame:6.2f} ms/frame "
                             f"({dictionary if not is_dictionary_file(dictionary) else Path(dictionary).name})")
        del frames
    # In the order the configurations were given, band by band, conditions before ``all`` (as before).
    order = {c.name: i for i, c in enumerate(configs)}
    return sorted(results.values(), key=lambda r: ([b.name for b in bands].index(r.band), r.condition == ALL,
                                                   r.condition if r.condition == ALL else
                                                   list(settings.conditions).index(r.condition), order[r.config]))


def rank(results: Sequence[CalibrationResult], band: str, condition: str = ALL, *,
         tie_rate: float = TIE_RATE) -> list[CalibrationResult]:
    """The configurations of ``band`` and ``condition`` best first (see the module's docstring)."""
    others: dict[str, list[CalibrationResult]] = {}
    for r in results:
        if r.band == band and r.condition not in (condition, ALL):
            others.setdefault(r.config, []).append(r)

    def robustness(r: CalibrationResult) -> float | None:
        mine = others.get(r.config, [])
        if not mine:
            return None
        return robustness_of(float(np.mean([o.detection_rate for o in mine])),
                             float(np.mean([o.false_per_frame for o in mine])), len(mine))

    return rank_rows([r for r in results if r.band == band and r.condition == condition],
                     score=lambda r: r.score, ms=lambda r: r.ms_per_frame, robustness=robustness,
                     name=lambda r: r.config, tie_rate=tie_rate)


def best_per_band(results: Sequence[CalibrationResult], *, tie_rate: float = TIE_RATE,
                  condition: str = ALL) -> dict[str, str]:
    """The winning configuration of each band in ``condition`` (see :func:`rank`)."""
    bands = sorted({r.band for r in results})
    out = {}
    for band in bands:
        ranked = rank(results, band, condition, tie_rate=tie_rate)
        if ranked:
            out[band] = ranked[0].config
    return out


# -- the store side -----------------------------------------------------------


def configs_from_store(store: Any, feature: str = FEATURE) -> tuple[list[DetectorConfig], list[Band], list[dict[str, Any]]]:
    """The feature's configurations (checked) and bands from the graph, and the raw rows."""
    from kgadapt.knowledge.queries import run_named

    rows = run_named(store, "detector_configs", {"feature": feature})
    bands = bands_from_rows(rows)
    configs = []
    # A configuration suited for no band (e.g. one made for another camera mode) is never chosen
    # by the adaptation, and its frames would not be these: it is left out.
    for name in sorted({r["config"] for r in rows if r.get("band") is not None}):
        found = run_named(store, "detector_config", {"config": name})
        if not found or found[0].get("config_json") is None:
            log.warning("configuration %s has no config_json; not calibrated", name)
            continue
        configs.append(parse_config(name, found[0]["config_json"], dictionary=found[0].get("dictionary")))
    return configs, bands, rows


def model_configs(folder: Path | str | None = None) -> list[DetectorConfig]:
    """The detector configurations of the perception-graph model files, read without a store (tests, bench).

    Each ``*.rpsl`` file's perception graph names the configuration; its
    processing component with a ``config_json`` gives the settings.
    """
    from kgadapt.knowledge.importers.rpsl import parse

    configs = []
    for path in sorted(Path(folder or models() / "perception").glob("*.rpsl")):
        model = parse(path.read_text(), str(path))
        graphs = [n.name for n in model.nodes if n.label == "PerceptionGraph"]
        settings = [n.props["config_json"] for n in model.nodes if n.props.get("config_json")]
        if len(graphs) == 1 and len(settings) == 1:
            configs.append(parse_config(graphs[0], settings[0]))
    return configs


def ensure_models(store: Any, feature: str = FEATURE) -> bool:
    """Load the shipped models when the graph has no configuration for ``feature``; True if loaded."""
    from kgadapt.knowledge.queries import run_named

    if run_named(store, "detector_configs", {"feature": feature}):
        return False
    from kgadapt.knowledge.loader import load_models

    folder = models()
    log.info("graph has no %s configurations: loading %s", feature, folder)
    load_models(store, [folder])
    return True


def record(store: Any, results: Sequence[CalibrationResult], *, at: float | None = None,
           source: str = SYNTHETIC) -> int:
    """Write every result as a CALIBRATED relation of ``source``; return how many were written."""
    from kgadapt.knowledge.runtime import record_calibration

    at = time.time() if at is None else at
    for r in results:
        record_calibration(store, config=r.config, band=r.band, condition=r.condition,
                           detection_rate=r.detection_rate, false_per_frame=r.false_per_frame,
                           false_per_reported=r.false_per_reported, ms_per_frame=r.ms_per_frame, time=at,
                           source=source)
    return len(results)


# -- outputs ------------------------------------------------------------------


def report(results: Sequence[CalibrationResult], bands: Sequence[Band], configs: Sequence[DetectorConfig],
           settings: CalibrationSettings) -> dict[str, Any]:
    """Everything about one calibration run as a JSON-ready dict."""
    return {
        "settings": asdict(settings),
        "bands": [{"name": b.name, "min_level": b.min_level, "max_level": b.max_level,
                   "levels": band_levels(b, settings.levels_per_band, max_level=settings.max_level)} for b in bands],
        "configs": {c.name: c.as_json() for c in configs},
        "results": [asdict(r) for r in results],
        "best": best_per_band(results, tie_rate=settings.tie_rate),
    }


def table(results: Sequence[CalibrationResult], bands: Sequence[Band]) -> str:
    """Rate / false markers per 1,000 frames / ms per frame for every configuration, band and condition."""
    configs = sorted({r.config for r in results})
    conditions = [ALL] + [c for c in CONDITIONS if any(r.condition == c for r in results)]
    by = {(r.config, r.band, r.condition): r for r in results}
    width = max(len(c) for c in configs) + 9
    lines = ["config / condition".ljust(width) + "".join(f"  {b.name + ' rate/false per 1k/ms':>30s}" for b in bands)]
    for condition in conditions:
        best = best_per_band(results, condition=condition)
        for c in configs:
            cells = []
            for b in bands:
                r = by.get((c, b.name, condition))
                mark = "*" if best.get(b.name) == c else " "
                cells.append(f"  {mark}{r.detection_rate:7.1%} {r.false_per_frame * 1000:7.0f} {r.ms_per_frame:7.2f} ms"
                             if r else " " * 32)
            lines.append(f"{c} {condition}".ljust(width) + "".join(cells))
    lines.append("* first in the ranking (rate minus false markers per frame; within half a point the faster "
                 "beyond timing noise, then the more robust in the band's other conditions)")
    return "\n".join(lines)


def plot(results: Sequence[CalibrationResult], bands: Sequence[Band], path: Path | str) -> Path:
    """Grouped bars: detection rate (top) and ms per frame (bottom) per band and configuration."""
    from kgadapt.shared.extras import require

    matplotlib = require("matplotlib", extra="plots", what="the calibration plot")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    configs = sorted({r.config for r in results})
    by = {(r.config, r.band): r for r in results if r.condition == ALL}
    x = np.arange(len(bands))
    width = 0.8 / max(len(configs), 1)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for i, c in enumerate(configs):
        rates = [by[(c, b.name)].detection_rate * 100 if (c, b.name) in by else 0 for b in bands]
        ms = [by[(c, b.name)].ms_per_frame if (c, b.name) in by else 0 for b in bands]
        offset = (i - (len(configs) - 1) / 2) * width
        top.bar(x + offset, rates, width, label=c)
        bottom.bar(x + offset, ms, width, label=c)
    top.set_ylabel("detection rate (%)")
    top.set_ylim(0, 125)
    top.set_yticks(range(0, 101, 20))
    top.legend(fontsize=8, loc="upper center", ncol=min(len(configs), 3), frameon=False)
    top.set_title("ArUco detector configurations per illumination band (sRGB camera model, all conditions)")
    bottom.set_ylabel("ms per frame")
    bottom.set_xticks(x, [f"{b.name}\n[{b.min_level:g}, {b.max_level:g})" for b in bands])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_json(data: Mapping[str, Any], path: Path | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)
    return path


@contextlib.contextmanager
def calibration_store(store_url: str | None, feature: str = FEATURE, *, progress: Callable[[str], None] | None = None,
                      ) -> Iterator[tuple[Any, list[DetectorConfig], list[Band]]]:
    """The store at ``store_url`` set up (the shipped models loaded into an empty one), with the
    configurations and bands of ``feature`` to calibrate; shut down when the block ends.

    Refuses a store with no configuration of ``feature`` to calibrate.
    """
    from kgadapt.knowledge.store import open_store

    store = open_store(store_url)
    store.setup()
    try:
        if ensure_models(store, feature) and progress:
            progress("the graph was empty: loaded knowledge/models")
        configs, bands, _rows = configs_from_store(store, feature)
        if not configs:
            raise KgadaptError(f"the store has no detector configuration with config_json for feature {feature!r}")
        yield store, configs, bands
    finally:
        store.shutdown()


def run_calibration(
    store_url: str | None,
    *,
    feature: str = FEATURE,
    settings: CalibrationSettings = CalibrationSettings(),
    write_store: bool = True,
    json_path: Path | str | None = RESULTS_DIR / "calibration.json",
    plot_path: Path | str | None = RESULTS_DIR / "calibration.png",
    progress: Callable[[str], None] | None = None,
    site: SiteMarkers | None = None,
) -> dict[str, Any]:
    """Calibrate every configuration of ``feature`` in the store at ``store_url``; write the outputs."""
    with calibration_store(store_url, feature, progress=progress) as (store, configs, bands):
        results = calibrate(configs, bands, settings, progress=progress, site=site)
        if write_store:
            record(store, results)
    data = report(results, bands, configs, settings)
    data["store"] = store.url
    data["table"] = table(results, bands).splitlines()
    if json_path:
        data["json"] = str(write_json(data, json_path))
    if plot_path:
        data["plot"] = str(plot(results, bands, plot_path))
    return data
