"""Calibration on the robot's own recorded frames, with markers labelled by the configurations' agreement.

Synthetic frames have a ground truth; recorded frames do not. Here the truth
is what the configurations agree on: every configuration (each with the
dictionary it names) runs on every frame; a marker (dictionary, id) counts as
real when at least ``min_configs`` configurations found it somewhere in the
recording, or, for a dictionary only one configuration reads, when that one
found it in at least ``min_frames`` frames; only detections whose cells read
clean (:func:`kgadapt.onboard.perception.markers.cells_are_clean`) vote, so a code two
configurations both decode inside another dictionary's marker is not agreed on. In each frame the truth is then the
real markers that any configuration found there, at the median of the corners
they found; a configuration scores a hit when it found such a marker within
``tolerance_px`` of those corners, and a false marker for anything else it
reports. A marker no configuration found in a frame is not counted: the rates
are relative to what the configurations see together, which is what the ranking
needs (which configuration to prefer), not an absolute figure.

Each frame's band comes from its light estimate
(:func:`kgadapt.onboard.perception.illumination.estimate_light`, which a window cannot
fool). The figures, per configuration and band (condition ``all``), go into the
graph beside the synthetic ones, as CALIBRATED relations whose ``source`` names
the recording (``frames:NAME``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from kgadapt.onboard.perception.calibration import ALL, CalibrationResult, configs_from_store, ensure_models, record, result_of
from kgadapt.onboard.perception.illumination import Band, estimate_light
from kgadapt.onboard.perception.markers import DetectorConfig, MarkerDetector, Score, score
from kgadapt.shared.errors import ConfigError, KgadaptError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass(frozen=True, kw_only=True)
class AgreementSettings:
    """How much agreement makes a marker real, and how much of the recording to read."""

    min_configs: int = 2  # configurations that must have found a marker
    min_frames: int = 3  # frames, where only one configuration reads the marker's dictionary
    tolerance_px: float = 5.0
    max_frames: int = 3000
    stride: int = 1  # every n-th frame of a video

    def __post_init__(self) -> None:
        if self.min_configs < 1 or self.min_frames < 1 or self.max_frames < 1 or self.stride < 1:
            raise ConfigError("frame calibration: min_configs, min_frames, max_frames and stride must be at least 1")
        if not self.tolerance_px > 0:
            raise ConfigError(f"frame calibration: tolerance_px {self.tolerance_px} must be positive")


def source_name(path: Path | str) -> str:
    """What the figures from a recording are recorded as: ``frames:`` and the folder's or video's name."""
    return f"frames:{Path(path).resolve().name}"


def read_frames(path: Path | str, *, max_frames: int = 3000, stride: int = 1) -> Iterator[tuple[str, np.ndarray]]:
    """``(name, grey frame)`` from a folder of images (in name order) or a video file; ConfigError naming it."""
    import cv2

    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ConfigError(f"frames folder {path}: no images ({', '.join(IMAGE_SUFFIXES)})")
        for file in files[:max_frames]:
            image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise ConfigError(f"frame {file}: not an image OpenCV can read")
            yield file.name, image
        return
    if not path.is_file():
        raise ConfigError(f"frames from {path}: no such folder or video file")
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise ConfigError(f"video {path}: OpenCV cannot open it")
        index = given = 0
        while given < max_frames:
            ok, image = capture.read()
            if not ok:
                break
            if index % stride == 0:
                grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                yield f"{path.name}#{index}", grey
                given += 1
            index += 1
        if index == 0:
            raise ConfigError(f"video {path}: no frame could be read")
    finally:
        capture.release()


@dataclass
class _Seen:
    """One frame: its band and what each configuration found in it."""

    name: str
    band: str
    level: float
    found: list[tuple[list[int], list[Any], float]]  # per configuration: ids, corners, ms
    clean: list[list[bool]]  # per configuration: per marker, its cells read clean


@dataclass
class FrameLabels:
    """The markers the configurations agreed on, and how many frames fell in each band."""

    real: dict[str, list[int]] = field(default_factory=dict)  # dictionary -> ids counted as real
    rejected: dict[str, list[int]] = field(default_factory=dict)  # found, but not agreed on
    frames_per_band: dict[str, int] = field(default_factory=dict)
    frames_outside: int = 0  # frames whose light is in no band


def _band_of(level: float, bands: Sequence[Band]) -> str | None:
    inside = [b for b in bands if b.contains(level)]
    return inside[0].name if inside else None


def _consensus(seen: _Seen, members: Sequence[int]) -> dict[int, np.ndarray]:
    """id -> the median corners of the configurations ``members`` that found it in this frame."""
    corners: dict[int, list[np.ndarray]] = {}
    for i in members:
        ids, found, _ms = seen.found[i]
        for marker_id, c in zip(ids, found):
            corners.setdefault(int(marker_id), []).append(np.asarray(c, np.float32).reshape(4, 2))
    return {k: np.median(np.stack(v), axis=0) for k, v in corners.items()}


def label_and_score(configs: Sequence[DetectorConfig], frames: Iterator[tuple[str, np.ndarray]], bands: Sequence[Band],
                    settings: AgreementSettings = AgreementSettings(), *,
                    progress: Callable[[str], None] | None = None) -> tuple[list[CalibrationResult], FrameLabels]:
    """Every configuration on every frame; the agreed markers as truth; figures per configuration and band."""
    if not configs:
        raise ConfigError("nothing to calibrate: no detector configurations")
    detectors = [MarkerDetector(c) for c in configs]
    groups: dict[str, list[int]] = {}
    for i, c in enumerate(configs):
        groups.setdefault(c.dictionary, []).append(i)
    labels = FrameLabels()
    seen_frames: list[_Seen] = []
    for count, (name, gray) in enumerate(frames, 1):
        level = estimate_light(gray).level
        band = _band_of(level, bands)
        if band is None:
            labels.frames_outside += 1
            continue
        found, clean = [], []
        for detector in detectors:
            d = detector.detect(gray)
            found.append((d.ids, d.corners, d.processing_ms))
            clean.append(d.clean)
        seen_frames.append(_Seen(name, band, level, found, clean))
        labels.frames_per_band[band] = labels.frames_per_band.get(band, 0) + 1
        if progress and count % 100 == 0:
            progress(f"{count} frames read")
    if not seen_frames:
        raise ConfigError("no recorded frame has light within an illumination band")
    # Which configurations found each (dictionary, id) near the others' corners, and in how many frames.
    finders: dict[tuple[str, int], set[int]] = {}
    frame_count: dict[tuple[str, int], int] = {}
    for seen in seen_frames:
        for dictionary, members in groups.items():
            agreed = _consensus(seen, members)
            for i in members:
                ids, corners, _ms = seen.found[i]
                for marker_id, c, clean in zip(ids, corners, seen.clean[i]):
                    if not clean:
                        continue
                    centre = agreed[int(marker_id)]
                    error = float(np.linalg.norm(np.asarray(c, np.float32).reshape(4, 2) - centre, axis=1).mean())
                    if error <= settings.tolerance_px:
                        finders.setdefault((dictionary, int(marker_id)), set()).add(i)
            for marker_id in agreed:
                frame_count[(dictionary, marker_id)] = frame_count.get((dictionary, marker_id), 0) + 1
    real: set[tuple[str, int]] = set()
    for key, who in finders.items():
        alone = len(groups[key[0]]) == 1
        if len(who) >= settings.min_configs or (alone and frame_count.get(key, 0) >= settings.min_frames):
            real.add(key)
    for dictionary, marker_id in sorted(frame_count):
        (labels.real if (dictionary, marker_id) in real else labels.rejected).setdefault(dictionary, []).append(marker_id)
    results = []
    for band in bands:
        here = [s for s in seen_frames if s.band == band.name]
        if not here:
            continue
        for i, config in enumerate(configs):
            members = groups[config.dictionary]
            total, times = Score(), []
            per_level: dict[float, tuple[Score, list[float]]] = {}
            for seen in here:
                truth = [{"id": k, "corners": v.tolist()} for k, v in _consensus(seen, members).items()
                         if (config.dictionary, k) in real]
                ids, corners, ms = seen.found[i]
                s = score(ids, corners, truth, tolerance_px=settings.tolerance_px)
                total.add(s)
                times.append(ms)
                level_score, level_times = per_level.setdefault(round(seen.level), (Score(), []))
                level_score.add(s)
                level_times.append(ms)
            results.append(result_of(config.name, band.name, ALL, total, times, per_level))
            if progress:
                r = results[-1]
                progress(f"{config.name:28s} {band.name:6s} rate {r.detection_rate:6.1%} (of {total.truth} agreed) "
                         f"false/frame {r.false_per_frame:6.3f} {r.ms_per_frame:6.2f} ms/frame")
    return results, labels


def run_frame_calibration(store_url: str | None, frames_from: Path | str, *, feature: str = "MarkerDetection",
                          settings: AgreementSettings = AgreementSettings(), write_store: bool = True,
                          json_path: Path | str | None = None,
                          progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Calibrate every configuration of ``feature`` in the store on a recording; record the figures by its name."""
    from dataclasses import asdict

    from kgadapt.knowledge.store import open_store
    from kgadapt.onboard.perception.calibration import write_json

    source = source_name(frames_from)
    store = open_store(store_url)
    store.setup()
    try:
        if ensure_models(store, feature) and progress:
            progress("the graph was empty: loaded knowledge/models")
        configs, bands, _rows = configs_from_store(store, feature)
        if not configs:
            raise KgadaptError(f"the store has no detector configuration with config_json for feature {feature!r}")
        frames = read_frames(frames_from, max_frames=settings.max_frames, stride=settings.stride)
        results, labels = label_and_score(configs, frames, bands, settings, progress=progress)
        if write_store:
            record(store, results, source=source)
    finally:
        store.shutdown()
    data: dict[str, Any] = {
        "source": source, "frames_from": str(frames_from), "settings": asdict(settings), "store": store.url,
        "labels": asdict(labels), "results": [asdict(r) for r in results], "recorded": write_store,
        "at": time.time(),
    }
    if json_path:
        data["json"] = str(write_json(data, json_path))
    return data
