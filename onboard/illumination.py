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
from typing import Any, Iterable, Mapping

import numpy as np

from shared.errors import ConfigError


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
