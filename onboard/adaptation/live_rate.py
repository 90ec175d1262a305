"""Live evidence: what the running detector finds on this robot, per band, and how the ranking weighs it.

Calibration (synthetic scene, or a recording: ``frames:NAME``) says how well a
configuration should find markers in a band; the running detector shows how
well it does here and now. The adaptation manager feeds every frame of its
running detector to :class:`LiveRates` (the configuration that frame ran, the
band the manager holds, the markers found) and writes each window's figures
every ``write_every_s`` through the knowledge service's ``live_rate`` verb: one
``LIVE_RATE`` relation per configuration x band x condition, replaced, never
appended. A frame counts only while markers are expected: some were seen
within the last ``expect_s`` (by whichever configuration ran then), or the
flight phase says the pad is in view (final descent).

:func:`weigh` is the rule the planner ranks by: a configuration's live figure
replaces its calibrated rate when it is fresh (updated within ``max_age_s``),
rests on at least ``min_expected`` frames with markers expected, and disagrees
with the calibrated rate by more than ``agree``; otherwise the calibration
decides (a live figure that agrees confirms it: real frames are seldom as
clean as the calibration scene, and a working configuration should not lose
its place to an untried one for that). Each row says which evidence scored it
(``evidence``: ``live``, or the calibration's source).

Nothing here does I/O or reads a clock: times are arguments.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from kgadapt.onboard.perception.ranking import TIE_RATE

LIVE = "live"  # the evidence name of a live figure (calibration's are its source: synthetic, frames:NAME)
CLOCK_SKEW_S = 5.0  # a live figure stamped this far in the future still counts as fresh


@dataclass(frozen=True, kw_only=True)
class LiveSettings:
    """How live evidence is gathered and weighed."""

    expect_s: float = 1.0  # markers seen within this long: the next frames are expected to show them
    window: int = 300  # frames with markers expected kept per configuration, band and condition (~10 s at 30/s)
    write_every_s: float = 2.0  # how often changed windows are written
    max_age_s: float = 120.0  # a live figure older than this no longer outweighs calibration
    min_expected: int = 30  # ... nor one resting on fewer frames with markers expected
    agree: float = 0.15  # a fresh live rate this close to the calibrated one confirms it: calibration's figure ranks

    def __post_init__(self) -> None:
        if self.window < 1 or self.min_expected < 1:
            raise ValueError(f"window {self.window!r}, min_expected {self.min_expected!r}: at least 1 each")
        if self.min_expected > self.window:
            raise ValueError(f"min_expected {self.min_expected} is more than a window holds ({self.window})")


def decided_by(ranking: Sequence[Mapping[str, Any]], chosen: Mapping[str, Any], *, tie: float = TIE_RATE) -> str | None:
    """Which evidence put ``chosen`` where it is in ``ranking`` (rows from :func:`weigh`, best first):
    ``live`` when its own score is live, or when a configuration that calibration put above it was
    ranked below it on live evidence; else its calibration's source (None: rows not weighed)."""
    if chosen.get("evidence") is None or chosen.get("evidence") == LIVE:
        return chosen.get("evidence")
    mine = chosen.get("calibrated_score")
    after = list(ranking)[list(ranking).index(chosen) + 1:] if chosen in ranking else []
    for row in after:
        theirs = row.get("calibrated_score")
        if (row.get("evidence") == LIVE and isinstance(mine, (int, float)) and isinstance(theirs, (int, float))
                and theirs > mine + tie):
            return LIVE
    return str(chosen["evidence"])


def fresh(live: Mapping[str, Any], *, now: float, settings: LiveSettings) -> bool:
    """A live figure recent enough and resting on enough frames to outweigh calibration."""
    at, expected, rate = live.get("at"), live.get("frames_expected"), live.get("detection_rate")
    if not isinstance(at, (int, float)) or not isinstance(expected, int) or not isinstance(rate, (int, float)):
        return False
    return expected >= settings.min_expected and -CLOCK_SKEW_S <= now - at <= settings.max_age_s


def weigh(ranking: Sequence[Mapping[str, Any]], live: Sequence[Mapping[str, Any]], *, now: float,
          settings: LiveSettings, penalty: float = 1.0, source: str = "synthetic") -> list[dict[str, Any]]:
    """``config_ranking`` rows with their ``score`` from the evidence that decides, and which (``evidence``).

    ``live``: ``live_rates`` rows of the same band and condition. A fresh one
    (:func:`fresh`) that disagrees with the calibrated rate by more than
    ``agree`` replaces it in the score (rate minus ``penalty`` x false markers
    per frame; the live window does not count false markers, the calibration's
    figure stays). Every row keeps its calibration's score as
    ``calibrated_score`` and carries its live figure (``live_rate``,
    ``live_frames_expected``, ``live_age_s``, ``live_agrees``) when it has one, fresh or not.
    """
    by_config = {str(r.get("config")): r for r in live}
    out = []
    for row in ranking:
        weighed = {**row, "evidence": source, "calibrated_score": row.get("score")}
        found = by_config.get(str(row.get("config")))
        if found is not None:
            at = found.get("at")
            weighed.update(live_rate=found.get("detection_rate"), live_frames_expected=found.get("frames_expected"),
                           live_age_s=round(now - at, 1) if isinstance(at, (int, float)) else None)
            if fresh(found, now=now, settings=settings):
                calibrated = row.get("detection_rate")
                agrees = (isinstance(calibrated, (int, float))
                          and abs(float(found["detection_rate"]) - float(calibrated)) <= settings.agree)
                weighed["live_agrees"] = agrees
                if not agrees:
                    weighed["score"] = (float(found["detection_rate"])
                                        - penalty * float(row.get("false_per_frame") or 0.0))
                    weighed["evidence"] = LIVE
        out.append(weighed)
    return out


@dataclass
class _Window:
    frames: int = 0  # every frame of this configuration in this band
    expected: collections.deque[tuple[float, int, int]] = field(default_factory=collections.deque)
    run_id: str | None = None
    host: str | None = None
    changed: bool = False


@dataclass(kw_only=True)
class LiveRates:
    """The running detector's live detection rate per configuration, band and condition (bounded)."""

    settings: LiveSettings = field(default_factory=LiveSettings)
    condition: str = "all"  # the manager knows the band, not the condition: the band as a whole
    _windows: dict[tuple[str, str], _Window] = field(default_factory=dict, repr=False)
    _seen: collections.deque[tuple[float, int]] = field(default_factory=collections.deque, repr=False)
    _written: float | None = field(default=None, repr=False)

    def add(self, *, config: str, band: str, found: int, now: float, pad_in_view: bool = False,
            run_id: str | None = None, host: str | None = None) -> bool:
        """One frame of ``config`` in ``band`` with ``found`` markers; True when markers were expected."""
        found = max(0, int(found))
        while self._seen and now - self._seen[0][0] > self.settings.expect_s:
            self._seen.popleft()
        in_view = max([found, *(n for _t, n in self._seen)])
        if found > 0:
            self._seen.append((now, found))
        expected = in_view if in_view > 0 else (1 if pad_in_view else 0)
        w = self._windows.setdefault((config, band), _Window(expected=collections.deque(maxlen=self.settings.window)))
        w.frames += 1
        w.run_id, w.host = run_id, host
        if expected:
            w.expected.append((now, expected, min(found, expected)))
            w.changed = True
        return expected > 0

    def due(self, now: float) -> list[dict[str, Any]]:
        """The ``live_rate`` writes due now (windows changed since the last), at most every ``write_every_s``."""
        if self._written is not None and now - self._written < self.settings.write_every_s:
            return []
        writes = []
        for (config, band), w in self._windows.items():
            if not w.changed or not w.expected:
                continue
            w.changed = False
            writes.append(self.figures(config, band, now, w))
        if writes:
            self._written = now
        return writes

    def figures(self, config: str, band: str, now: float, w: _Window | None = None) -> dict[str, Any]:
        """The ``live_rate`` write's parameters for one window."""
        w = w or self._windows[(config, band)]
        expected = sum(e for _t, e, _f in w.expected)
        found = sum(f for _t, _e, f in w.expected)
        return {"config": config, "band": band, "condition": self.condition,
                "detection_rate": round(found / expected, 4) if expected else 0.0,
                "frames": w.frames, "frames_expected": len(w.expected),
                "frames_seen": sum(1 for _t, _e, f in w.expected if f > 0),
                "since": min(w.expected[0][0], now) if w.expected else now, "time": now,
                **({"run_id": w.run_id} if w.run_id else {}), **({"host": w.host} if w.host else {})}
