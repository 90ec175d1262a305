"""Calibration: how well each detector configuration does in each illumination band.

Every configuration the knowledge store has for a feature (named queries
``detector_configs`` and ``detector_config``) runs over the same synthetic
frames: for each band, ``levels_per_band`` fixed levels at the midpoints of
equal slices of the band (so the band's dark end counts as much as its bright
end), ``frames_per_level`` frames each, JPEG-compressed as on the wire. A
detection counts when its id is right and its corners are within
``tolerance_px`` of the truth; anything else it reports is a false detection.

Figures per (configuration, band): ``detection_rate`` (hits / markers shown),
``false_rate`` (false / all detections reported), ``ms_per_frame`` (mean time
of pre-processing plus detection). They go into the graph as
``(PerceptionGraph)-[:CALIBRATED]->(IlluminationBand)`` through
``knowledge.runtime.record_calibration``, and into a JSON file and a PNG plot.

The best configuration of a band is the one with the highest detection rate
minus false rate; rates within ``tie_rate`` (half a point) of each other are equal, and then
the faster one wins.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from onboard.illumination import Band, bands_from_rows
from onboard.markers import DetectorConfig, MarkerDetector, Score, parse_config, score
from shared.errors import ConfigError, KgadaptError

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parent.parent
RESULTS_DIR = REPO / "bench" / "results"
FEATURE = "MarkerDetection"


@dataclass(frozen=True, kw_only=True)
class CalibrationSettings:
    """How much to render and how to judge it."""

    frames_per_level: int = 10
    levels_per_band: int = 4
    max_level: float = 200.0  # brighter than this saturates the synthetic camera
    jpeg_quality: int = 80
    width: int = 640
    height: int = 480
    tolerance_px: float = 5.0
    tie_rate: float = 0.005  # half a point: about one marker in 200
    seed: int = 7

    def __post_init__(self) -> None:
        if self.frames_per_level < 1 or self.levels_per_band < 1:
            raise ConfigError("calibration needs at least one level per band and one frame per level")


@dataclass
class CalibrationResult:
    """One configuration in one band."""

    config: str
    band: str
    detection_rate: float
    false_rate: float
    ms_per_frame: float
    ms_p99: float
    frames: int
    markers: int
    per_level: list[dict[str, float]] = field(default_factory=list)


def band_levels(band: Band, count: int, *, max_level: float = 200.0) -> list[float]:
    """``count`` levels at the midpoints of equal slices of ``band`` (capped at ``max_level``)."""
    low, high = band.min_level, min(band.max_level, max_level)
    if high <= low:
        high = low + 1.0
    step = (high - low) / count
    return [round(low + step * (i + 0.5), 2) for i in range(count)]


def render_test_frames(
    bands: Sequence[Band], settings: CalibrationSettings
) -> dict[str, list[tuple[float, np.ndarray, list[Any]]]]:
    """The frames every configuration is judged on: ``band -> [(level, grey, truth), ...]``."""
    import cv2

    from onboard.scenario import IlluminationProfile, SceneSettings, SyntheticScene

    scene = SyntheticScene(SceneSettings(width=settings.width, height=settings.height))
    rng = np.random.default_rng(settings.seed)
    out: dict[str, list[tuple[float, np.ndarray, list[Any]]]] = {}
    for band in bands:
        frames = []
        for level in band_levels(band, settings.levels_per_band, max_level=settings.max_level):
            profile = IlluminationProfile.constant(level)
            for i in range(settings.frames_per_level):
                frame = scene.render(i * 0.7, profile, rng)  # the sway moves the markers between frames
                ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, settings.jpeg_quality])
                gray = cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE)
                frames.append((level, gray, frame.truth))
        out[band.name] = frames
    return out


def calibrate(
    configs: Sequence[DetectorConfig],
    bands: Sequence[Band],
    settings: CalibrationSettings = CalibrationSettings(),
    *,
    progress: Callable[[str], None] | None = None,
) -> list[CalibrationResult]:
    """Run every configuration over every band's frames; return the figures."""
    if not configs:
        raise ConfigError("nothing to calibrate: no detector configurations")
    if not bands:
        raise ConfigError("nothing to calibrate: no illumination bands")
    frames = render_test_frames(bands, settings)
    detectors = [MarkerDetector(config) for config in configs]
    for detector in detectors:
        detector.detect(frames[bands[0].name][0][1])  # warm-up: the first call allocates
    results = []
    for band in bands:
        totals = [Score() for _ in detectors]
        times: list[list[float]] = [[] for _ in detectors]
        per_level: list[dict[float, tuple[Score, list[float]]]] = [{} for _ in detectors]
        # Every frame goes through every configuration in turn, so a burst of load from
        # elsewhere on the machine hits all configurations alike instead of one of them.
        for level, gray, truth in frames[band.name]:
            for i, detector in enumerate(detectors):
                found = detector.detect(gray)
                s = score(found.ids, found.corners, truth, tolerance_px=settings.tolerance_px)
                totals[i].add(s)
                times[i].append(found.processing_ms)
                level_score, level_times = per_level[i].setdefault(level, (Score(), []))
                level_score.add(s)
                level_times.append(found.processing_ms)
        for i, config in enumerate(configs):
            total = totals[i]
            result = CalibrationResult(
                config=config.name, band=band.name,
                detection_rate=round(total.detection_rate, 4), false_rate=round(_false_rate(total), 4),
                ms_per_frame=round(float(np.mean(times[i])), 3), ms_p99=round(float(np.percentile(times[i], 99)), 3),
                frames=total.frames, markers=total.truth,
                per_level=[
                    {"level": lv, "detection_rate": round(sc.detection_rate, 4), "false_rate": round(_false_rate(sc), 4),
                     "ms_per_frame": round(float(np.mean(ts)), 3)}
                    for lv, (sc, ts) in sorted(per_level[i].items())
                ],
            )
            results.append(result)
            if progress:
                progress(f"{config.name:28s} {band.name:6s} rate {result.detection_rate:6.1%} "
                         f"false {result.false_rate:5.1%} {result.ms_per_frame:6.2f} ms/frame")
    return results


def _false_rate(s: Score) -> float:
    reported = s.hits + s.false
    return s.false / reported if reported else 0.0


def best_per_band(results: Sequence[CalibrationResult], *, tie_rate: float = 0.005) -> dict[str, str]:
    """The winning configuration of each band (rate minus false rate; ties go to the faster)."""
    best: dict[str, CalibrationResult] = {}
    for r in results:
        current = best.get(r.band)
        if current is None:
            best[r.band] = r
            continue
        # Rounded so that 1.0 - 0.99 compares as 0.01, not 0.010000000000000009.
        gain = round((r.detection_rate - r.false_rate) - (current.detection_rate - current.false_rate), 6)
        if gain > tie_rate or (abs(gain) <= tie_rate and r.ms_per_frame < current.ms_per_frame):
            best[r.band] = r
    return {band: r.config for band, r in best.items()}


# -- the store side -----------------------------------------------------------


def configs_from_store(store: Any, feature: str = FEATURE) -> tuple[list[DetectorConfig], list[Band], list[dict[str, Any]]]:
    """The feature's configurations (checked) and bands from the graph, and the raw rows."""
    from knowledge.queries import run_named

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


def model_configs(folder: Path | str = REPO / "knowledge" / "models" / "perception") -> list[DetectorConfig]:
    """The detector configurations of the perception-graph model files, read without a store (tests, bench).

    Each ``*.rpsl`` file's perception graph names the configuration; its
    processing component with a ``config_json`` gives the settings.
    """
    from knowledge.importers.rpsl import parse

    configs = []
    for path in sorted(Path(folder).glob("*.rpsl")):
        model = parse(path.read_text(), str(path))
        graphs = [n.name for n in model.nodes if n.label == "PerceptionGraph"]
        settings = [n.props["config_json"] for n in model.nodes if n.props.get("config_json")]
        if len(graphs) == 1 and len(settings) == 1:
            configs.append(parse_config(graphs[0], settings[0]))
    return configs


def ensure_models(store: Any, feature: str = FEATURE) -> bool:
    """Load the shipped models when the graph has no configuration for ``feature``; True if loaded."""
    from knowledge.queries import run_named

    if run_named(store, "detector_configs", {"feature": feature}):
        return False
    from knowledge.loader import load_models

    models = REPO / "knowledge" / "models"
    log.info("graph has no %s configurations: loading %s", feature, models)
    load_models(store, [models])
    return True


def record(store: Any, results: Sequence[CalibrationResult], *, at: float | None = None) -> int:
    """Write every result as a CALIBRATED relation; return how many were written."""
    from knowledge.runtime import record_calibration

    at = time.time() if at is None else at
    for r in results:
        record_calibration(store, config=r.config, band=r.band, detection_rate=r.detection_rate,
                           false_rate=r.false_rate, ms_per_frame=r.ms_per_frame, time=at)
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
    """Rate / ms per frame for every configuration (rows) and band (columns)."""
    configs = sorted({r.config for r in results})
    by = {(r.config, r.band): r for r in results}
    best = best_per_band(results)
    width = max(len(c) for c in configs)
    lines = ["config".ljust(width) + "".join(f"  {b.name + ' rate/false/ms':>26s}" for b in bands)]
    for c in configs:
        cells = []
        for b in bands:
            r = by.get((c, b.name))
            mark = "*" if best.get(b.name) == c else " "
            cells.append(f"  {mark}{r.detection_rate:7.1%} {r.false_rate:5.1%} {r.ms_per_frame:7.2f} ms" if r else " " * 28)
        lines.append(c.ljust(width) + "".join(cells))
    lines.append("* best in band (highest rate minus false rate; within half a point the faster)")
    return "\n".join(lines)


def plot(results: Sequence[CalibrationResult], bands: Sequence[Band], path: Path | str) -> Path:
    """Grouped bars: detection rate (top) and ms per frame (bottom) per band and configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    configs = sorted({r.config for r in results})
    by = {(r.config, r.band): r for r in results}
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
    top.set_title("ArUco detector configurations per illumination band (synthetic scenario)")
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


def run_calibration(
    store_url: str | None,
    *,
    feature: str = FEATURE,
    settings: CalibrationSettings = CalibrationSettings(),
    write_store: bool = True,
    json_path: Path | str | None = RESULTS_DIR / "calibration.json",
    plot_path: Path | str | None = RESULTS_DIR / "calibration.png",
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Calibrate every configuration of ``feature`` in the store at ``store_url``; write the outputs."""
    from knowledge.store import open_store

    store = open_store(store_url)
    store.setup()
    try:
        if ensure_models(store, feature) and progress:
            progress("the graph was empty: loaded knowledge/models")
        configs, bands, _rows = configs_from_store(store, feature)
        if not configs:
            raise KgadaptError(f"the store has no detector configuration with config_json for feature {feature!r}")
        results = calibrate(configs, bands, settings, progress=progress)
        if write_store:
            record(store, results)
    finally:
        store.shutdown()
    data = report(results, bands, configs, settings)
    data["store"] = store.url
    data["table"] = table(results, bands).splitlines()
    if json_path:
        data["json"] = str(write_json(data, json_path))
    if plot_path:
        data["plot"] = str(plot(results, bands, plot_path))
    return data
