"""The pre-processing steps a marker detector runs before ArUco, and the range of each setting.

One table for the two places that read a detector configuration: the model
importer (``preprocess :gamma, gamma: 0.5`` in ``.rpsl`` files, checked at load
time, every setting written out) and the detector itself
(:func:`kgadapt.onboard.markers.parse_config`, where a missing setting takes its
default). docs/CONTRACTS.md describes the ``config_json`` they share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class Setting:
    """One setting of a step: its type, default and inclusive range."""

    kind: type  # int or float
    default: float
    low: float
    high: float
    odd: bool = False  # a kernel size: odd numbers only

    def problem(self, value: object) -> str | None:
        """What is wrong with ``value`` in words ("must be int, not 2.5"), or None."""
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (
                self.kind is int and value != int(value)):
            return f"must be {self.kind.__name__}, not {value!r}"
        if not math.isfinite(value) or not self.low <= value <= self.high:
            return f"{value} is outside [{self.low:g}, {self.high:g}]"
        if self.odd and int(value) % 2 == 0:
            return f"must be odd, not {value}"
        return None


# op -> {setting: Setting}, in the order the detector documents them.
OPS: dict[str, dict[str, Setting]] = {
    "gamma": {"gamma": Setting(kind=float, default=1.0, low=0.05, high=10.0)},
    "clahe": {"clip_limit": Setting(kind=float, default=2.0, low=0.1, high=100.0),
              "tile": Setting(kind=int, default=8, low=1, high=64)},
    "stretch": {"low_pct": Setting(kind=float, default=1.0, low=0.0, high=49.0),
                "high_pct": Setting(kind=float, default=99.0, low=51.0, high=100.0)},
    "blur": {"ksize": Setting(kind=int, default=3, low=1, high=31, odd=True)},
}
