"""Illumination: robust luminance figures per frame, smoothing, and bands.

:func:`luminance` gives a frame's mean and its 5th, 50th and 95th
percentiles from a histogram of a subsample (every 4th pixel each way:
about 0.1 ms at 640x480 and as good as the full frame for these figures).
:class:`Smoother` is an exponential moving average with a time constant, so
it behaves the same whatever the frame rate and irons out flicker.
:func:`band_for_level` maps a level to an illumination band given the rows of
the knowledge store's named query ``detector_configs`` (the bands themselves
live in the graph, not here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from kgadapt.shared.errors import ConfigError


@dataclass(frozen=True)
class Luminance:
    """Luminance figures of one frame (grey levels 0..255)."""

    mean: float
    p5: float
    p50: float
    p95: float


def luminance(gray: np.ndarray, *, step: int = 4) -> Luminance:
    """Mean and percentiles of a grey frame, from every ``step``-th pixel."""
    import cv2

    if gray.ndim != 2 or gray.dtype != np.uint8 or gray.size == 0:
        raise ConfigError(f"luminance needs a non-empty grey uint8 image, got {gray.dtype} {gray.shape}")
    sample = np.ascontiguousarray(gray[::step, ::step])
    hist = cv2.calcHist([sample], [0], None, [256], [0, 256]).ravel()
    total = float(hist.sum())
    cumulative = np.cumsum(hist)
    mean = float(np.dot(hist, np.arange(256)) / total)

    def pct(p: float) -> float:
        return float(np.searchsorted(cumulative, total * p / 100.0))

    return Luminance(mean=mean, p5=pct(5), p50=pct(50), p95=pct(95))


class LightSource(str, Enum):
    """Which pixels a light estimate rests on."""

    FRAME = "frame"  # the usable pixels of the whole frame
    MARKERS = "markers"  # weighted towards the light around markers seen recently
    CLIPPED = "clipped"  # too few usable pixels: every unsaturated pixel, the frame is mostly black


@dataclass(frozen=True, kw_only=True)
class LightSettings:
    """How :func:`estimate_light` reads the light of a frame.

    Saturated pixels (a window, a lamp) say nothing about how bright the scene
    is beyond "more than the sensor holds", and near-black ones (a shadowed
    corner, a black object) nothing about the light on the rest, so both are left
    out; of the rest, a trimmed mean (``trim`` each side) keeps the band scale of
    the frame mean without being dragged by a few extreme pixels.
    """

    saturated: int = 250  # at or above: saturated
    black: int = 0  # at or below: black (clipped at the sensor's floor)
    trim: float = 0.02
    min_usable: float = 0.2  # below this share of usable pixels, fall back to all unsaturated ones
    marker_weight: float = 0.75  # share of the estimate given to the light around seen markers
    marker_margin: float = 0.5  # the region around a marker: its box widened by this share of its side
    step: int = 4  # every step-th pixel each way for the frame figure (and at most for the markers' region)
    marker_samples: int = 4096  # the markers' region is read as coarsely as leaves it at least this many pixels

    def __post_init__(self) -> None:
        if not 0 <= self.black < self.saturated <= 255:
            raise ConfigError(f"light estimate: need 0 <= black ({self.black}) < saturated ({self.saturated}) <= 255")
        if not 0 <= self.trim < 0.5 or not 0 <= self.marker_weight <= 1 or not 0 < self.min_usable <= 1:
            raise ConfigError("light estimate: trim in [0, 0.5), marker_weight in [0, 1], min_usable in (0, 1]")
        if self.step < 1 or self.marker_samples < 1 or self.marker_margin < 0:
            raise ConfigError("light estimate: step >= 1, marker_samples >= 1 and marker_margin >= 0")


@dataclass(frozen=True, kw_only=True)
class LightEstimate:
    """The light of one frame on the band scale, and what it was read from."""

    level: float  # what the band is read from
    frame_level: float  # trimmed mean of the frame's usable pixels
    marker_level: float | None  # the same around the markers seen, None when none were given
    source: LightSource
    usable: float  # share of the frame's sampled pixels that were used
    saturated: float  # share at or above the saturation level
    black: float  # share at or below the near-black level
    markers: int  # markers whose surroundings were weighed

    def as_wire(self) -> dict[str, Any]:
        return {"level": round(self.level, 3), "frame_level": round(self.frame_level, 3),
                "marker_level": None if self.marker_level is None else round(self.marker_level, 3),
                "source": self.source.value, "usable": round(self.usable, 4),
                "saturated": round(self.saturated, 4), "black": round(self.black, 4), "markers": self.markers}


def _trimmed_mean(hist: np.ndarray, low: int, high: int, trim: float) -> tuple[float, float]:
    """Trimmed mean of the histogram's bins ``low..high`` (inclusive) and their share of all pixels."""
    total = float(hist.sum())
    part = hist[low:high + 1].astype(np.float64)
    count = float(part.sum())
    if count <= 0 or total <= 0:
        return float("nan"), 0.0
    values = np.arange(low, high + 1, dtype=np.float64)
    if trim > 0:
        # Cut ``trim`` of the pixels from each end, fractional bins included.
        cum = np.cumsum(part)
        lo_cut, hi_cut = trim * count, (1.0 - trim) * count
        keep = np.clip(np.minimum(cum, hi_cut) - np.maximum(cum - part, lo_cut), 0.0, None)
    else:
        keep = part
    kept = float(keep.sum())
    mean = float(np.dot(keep, values) / kept) if kept > 0 else float(np.dot(part, values) / count)
    return mean, count / total


def _region_light(hist: np.ndarray, settings: LightSettings) -> tuple[float, float, LightSource]:
    mean, usable = _trimmed_mean(hist, settings.black + 1, settings.saturated - 1, settings.trim)
    if usable >= settings.min_usable:
        return mean, usable, LightSource.FRAME
    mean, _share = _trimmed_mean(hist, 0, settings.saturated - 1, settings.trim)
    if math.isnan(mean):  # every pixel saturated
        return float(settings.saturated), usable, LightSource.CLIPPED
    return mean, usable, LightSource.CLIPPED


Box = tuple[int, int, int, int]  # x0, y0, x1, y1: pixels x0 <= x < x1, y0 <= y < y1


def marker_boxes(shape: tuple[int, int], markers: Sequence[Any], margin: float) -> list[Box]:
    """The boxes around ``markers`` (each 4 x [x, y] corners), widened by ``margin`` of their side and cut to
    a frame of ``shape``; markers with fewer than 3 finite corners or wholly outside are left out."""
    h, w = shape
    boxes = []
    for corners in markers:
        xs, ys = _corner_coordinates(corners)
        if len(xs) < 3 or not all(map(math.isfinite, xs + ys)):
            continue
        x0, y0, x1, y1 = min(xs), min(ys), max(xs), max(ys)
        pad = margin * max(x1 - x0, y1 - y0)
        xa, ya = int(max(x0 - pad, 0)), int(max(y0 - pad, 0))
        xb, yb = int(min(x1 + pad + 1, w)), int(min(y1 + pad + 1, h))
        if xb > xa and yb > ya:
            boxes.append((xa, ya, xb, yb))
    return boxes


def _corner_coordinates(corners: Any) -> tuple[list[float], list[float]]:
    """A marker's corners as x and y lists: plain Python for the lists a decoded detection carries (a numpy
    call per marker cost more than the histogram), numpy for arrays or other nestings; none when they are not
    (x, y) pairs of numbers (a malformed detection from the wire is left out, not an error of the frame)."""
    if not isinstance(corners, np.ndarray):
        try:
            return [float(p[0]) for p in corners], [float(p[1]) for p in corners]
        except (TypeError, IndexError, ValueError):
            pass  # e.g. a [[[x, y], ...]] nesting: numpy's reshape below
    try:
        pts = np.asarray(corners, np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        return [], []
    return pts[:, 0].tolist(), pts[:, 1].tolist()


def _box_mask(boxes: Sequence[Box], origin: tuple[int, int], shape: tuple[int, int], step: int) -> np.ndarray:
    """The mask of ``boxes`` over the pixels (origin_y + i * step, origin_x + j * step) of ``shape``."""
    ox, oy = origin
    mask = np.zeros(shape, np.uint8)
    for xa, ya, xb, yb in boxes:
        # Sampled rows oy + i*step with ya <= oy + i*step < yb: i from ceil((ya - oy) / step) to ceil((yb - oy) / step).
        mask[-(-(ya - oy) // step):-(-(yb - oy) // step), -(-(xa - ox) // step):-(-(xb - ox) // step)] = 255
    return mask


def marker_mask(shape: tuple[int, int], markers: Sequence[Any], margin: float, *, step: int = 1) -> np.ndarray | None:
    """A mask of the regions around ``markers`` over every ``step``-th pixel each way of a frame of ``shape``
    (the mask of ``frame[::step, ::step]``); None when none is in the frame."""
    boxes = marker_boxes(shape, markers, margin)
    h, w = shape
    return _box_mask(boxes, (0, 0), (-(-h // step), -(-w // step)), step) if boxes else None


def marker_histogram(gray: np.ndarray, boxes: Sequence[Box], step: int) -> np.ndarray:
    """The grey-level histogram (256 bins) of the pixels in ``boxes``, each counted once, read from every
    ``step``-th pixel each way of their bounding box (from its top left corner). Only that box is scanned:
    a far marker's small region costs little, where a mask over the whole frame scanned every pixel."""
    import cv2

    x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
    pixels = np.ascontiguousarray(gray[y0:y1:step, x0:x1:step])
    mask = None if len(boxes) == 1 else _box_mask(boxes, (x0, y0), pixels.shape, step)
    return cv2.calcHist([pixels], [0], mask, [256], [0, 256]).ravel()


def estimate_light(gray: np.ndarray, markers: Sequence[Any] = (), settings: LightSettings = LightSettings()) -> LightEstimate:
    """The light of a grey frame that a window, a lamp or a black corner cannot fool.

    ``markers`` are the corners of markers seen recently (detections); when
    given, the light around them gets ``settings.marker_weight`` of the
    estimate, because that is the light the detector has to work in.
    """
    import cv2

    if gray.ndim != 2 or gray.dtype != np.uint8 or gray.size == 0:
        raise ConfigError(f"light estimate needs a non-empty grey uint8 image, got {gray.dtype} {gray.shape}")
    step = settings.step
    sample = np.ascontiguousarray(gray[::step, ::step])
    hist = cv2.calcHist([sample], [0], None, [256], [0, 256]).ravel()
    total = float(hist.sum())
    saturated = float(hist[settings.saturated:].sum()) / total
    black = float(hist[:settings.black + 1].sum()) / total
    frame_level, usable, source = _region_light(hist, settings)
    level, marker_level, seen = frame_level, None, 0
    boxes = marker_boxes(gray.shape, markers, settings.marker_margin) if len(markers) else []
    if boxes:
        covered = min(sum((xb - xa) * (yb - ya) for xa, ya, xb, yb in boxes), gray.size)
        fine = max(1, min(step, math.isqrt(covered // settings.marker_samples)))
        region = marker_histogram(gray, boxes, fine)
        marker_level, _usable, _how = _region_light(region, settings)
        seen = len(boxes)
        level = settings.marker_weight * marker_level + (1.0 - settings.marker_weight) * frame_level
        source = LightSource.MARKERS
    return LightEstimate(level=level, frame_level=frame_level, marker_level=marker_level, source=source,
                         usable=usable, saturated=saturated, black=black, markers=seen)


class Smoother:
    """Exponential moving average with time constant ``tau_s`` (seconds).

    The first value is taken as is; later ones weigh ``1 - exp(-dt / tau)``.
    """

    def __init__(self, tau_s: float = 0.5) -> None:
        if not tau_s > 0:
            raise ConfigError(f"smoothing time constant must be positive, not {tau_s}")
        self.tau_s = tau_s
        self.value: float | None = None
        self._last: float | None = None

    def update(self, value: float, t: float) -> float:
        if self.value is None or self._last is None:
            self.value = float(value)
        else:
            dt = max(t - self._last, 0.0)
            alpha = 1.0 - math.exp(-dt / self.tau_s)
            self.value += alpha * (float(value) - self.value)
        self._last = t
        return self.value


@dataclass(frozen=True)
class Band:
    """An illumination band from the knowledge graph: levels in [min_level, max_level)."""

    name: str
    min_level: float
    max_level: float

    def contains(self, level: float, margin: float = 0.0) -> bool:
        return self.min_level - margin <= level < self.max_level + margin


def bands_from_rows(rows: Iterable[Mapping[str, Any]]) -> list[Band]:
    """The distinct bands in ``detector_configs`` rows, lowest first.

    Raises ConfigError when a band lacks its limits or two rows disagree on them.
    """
    found: dict[str, Band] = {}
    for row in rows:
        name = row.get("band")
        if name is None:
            continue  # a configuration not SUITED_FOR any band
        low, high = row.get("min_level"), row.get("max_level")
        if not isinstance(low, (int, float)) or not isinstance(high, (int, float)) or not low < high:
            raise ConfigError(f"illumination band {name!r} has bad limits min_level={low!r} max_level={high!r}")
        band = Band(str(name), float(low), float(high))
        if found.setdefault(band.name, band) != band:
            raise ConfigError(f"illumination band {name!r} appears with different limits: {found[band.name]} and {band}")
    return sorted(found.values(), key=lambda b: b.min_level)


def band_for_level(
    level: float,
    rows: Iterable[Mapping[str, Any]],
    *,
    current: str | None = None,
    hysteresis: float = 0.0,
) -> str:
    """The band whose range holds ``level``, given ``detector_configs`` rows.

    With ``current`` and ``hysteresis`` (grey levels) the current band is kept
    while the level stays within its range widened by that margin, so a level
    hovering at a border does not flip the band every frame. Below the lowest
    band or above the highest, the nearest band is chosen; in a gap between
    bands, the nearer one.
    """
    bands = bands_from_rows(rows)
    if not bands:
        raise ConfigError("no illumination bands: the detector_configs rows name none")
    if current is not None and hysteresis > 0:
        for band in bands:
            if band.name == current and band.contains(level, hysteresis):
                return band.name
    for band in bands:
        if band.contains(level):
            return band.name

    def distance(band: Band) -> float:
        return band.min_level - level if level < band.min_level else level - band.max_level

    return min(bands, key=distance).name
