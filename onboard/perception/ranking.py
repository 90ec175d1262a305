"""The ranking of detector configurations in a band and condition: one rule for every place that ranks.

Calibration's own report (:func:`~kgadapt.onboard.perception.calibration.rank`), the planner
(:class:`~kgadapt.onboard.adaptation.adaptation.Planner`, named query ``config_ranking``) and the
detector's reflexes (:class:`~kgadapt.onboard.perception.reflex.ReflexTable`, named query
``reflex_table``) all order configurations with :func:`rank_rows`:

1. score: detection rate minus ``penalty`` x false markers per frame (:func:`score_of`); scores within
   ``tie_rate`` of the best left are equal;
2. of those, speed, but only beyond the timing's noise (:func:`clearly_faster`): calibration's ms per
   frame is measured on a shared machine, and a few per cent between two configurations is load, not
   the configurations;
3. of the equally fast ones, robustness: the mean score in the band's other conditions
   (:func:`robustness_of`; blur, a window, small markers, uneven light), so a tie in one condition
   goes to the configuration that holds better in the others;
4. then the name, so the order never depends on the order rows arrive in.

Nothing here does I/O.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Callable, Mapping, Sequence

PENALTY = 1.0  # score lost per false marker per frame
TIE_RATE = 0.005  # scores within half a point (about one marker in 200) are equal
# Two configurations are equally fast unless one's ms per frame is below the other's by more than
# SPEED_NOISE_REL of its own figure and by more than SPEED_NOISE_MS. Calibration times them in turn on the
# same frames, yet on this 2-core machine under load their ratio moves: the committed runs measured the
# day configuration 10 % and 14 % faster than the dusk one in the day band, and a loaded run measured the
# order reversed (picking dusk cost 16.7 points at day/blur). Four day-band calibrations (4 x 4 frames,
# load 15-19) put dusk at 1.01-1.15 x day's ms, and dark, really slower, at 1.32-1.43 x. 20 % is above
# that spread and below dark's gap; below 1 ms
# (3 % of a 33 ms frame at 30 frames/s) a difference is timer and scheduling jitter and buys nothing.
SPEED_NOISE_REL = 0.2
SPEED_NOISE_MS = 1.0


def score_of(detection_rate: float, false_per_frame: float | None, penalty: float = PENALTY) -> float:
    """What a configuration is ranked by: detection rate minus ``penalty`` x false markers per frame."""
    return round(detection_rate - penalty * (false_per_frame or 0.0), 6)


def clearly_faster(ms: float, than_ms: float) -> bool:
    """``ms`` per frame is faster than ``than_ms`` by more than calibration's timing noise
    (:data:`SPEED_NOISE_REL` of ``ms`` and :data:`SPEED_NOISE_MS`); an unknown time (inf) is never faster."""
    return ms < than_ms - max(SPEED_NOISE_MS, SPEED_NOISE_REL * ms)


def robustness_of(other_rate: float | None, other_false_per_frame: float | None, other_conditions: int | None,
                  penalty: float = PENALTY) -> float | None:
    """What a configuration finds in the band's other conditions: the mean of their scores (mean rate minus
    ``penalty`` x mean false markers per frame); None when it was calibrated in no other condition."""
    if not other_conditions or other_rate is None:
        return None
    return score_of(float(other_rate), other_false_per_frame, penalty)


def rank_rows(rows: Sequence[Any], *, score: Callable[[Any], float], ms: Callable[[Any], float],
              robustness: Callable[[Any], float | None] = lambda r: None,
              name: Callable[[Any], str] = lambda r: str(r["config"]), tie_rate: float = TIE_RATE) -> list[Any]:
    """``rows`` best first: highest score; of the scores within ``tie_rate`` of the best left, the fastest
    unless another is as fast within timing noise (:func:`clearly_faster`); of the equally fast ones, the
    most robust (None: no figure, last), then the first by name."""
    left = list(rows)
    ordered = []
    while left:
        best = max(score(r) for r in left)
        tied = [r for r in left if best - score(r) <= tie_rate + 1e-9]
        fastest = min(ms(r) for r in tied)
        quick = [r for r in tied if not clearly_faster(fastest, ms(r))]

        def key(r: Any) -> tuple[float, str]:
            sturdy = robustness(r)
            return (-sturdy if sturdy is not None else math.inf, name(r))

        pick = min(quick, key=key)
        ordered.append(pick)
        left.remove(pick)
    return ordered


def ties(scores: Sequence[float], tie_rate: float = TIE_RATE) -> bool:
    """Some two of ``scores`` are within ``tie_rate`` of each other: ranking them takes more than the score."""
    ordered = sorted(scores)
    return any(high - low <= tie_rate + 1e-9 for low, high in itertools.pairwise(ordered))


OTHER_FIGURES = ("other_rate", "other_false_per_frame", "other_conditions")  # what robustness is made of


def rank_graph_rows(rows: Sequence[Mapping[str, Any]], *, penalty: float = PENALTY,
                    tie_rate: float = TIE_RATE) -> list[dict[str, Any]]:
    """Rows of ``config_ranking`` (joined with ``config_robustness``) or ``reflex_table``, with their ``score``,
    best first by :func:`rank_rows`, each with its ``robustness`` (from :data:`OTHER_FIGURES`; None without)."""
    scored = [{**r, "robustness": robustness_of(r.get("other_rate"), r.get("other_false_per_frame"),
                                                r.get("other_conditions"), penalty)} for r in rows]
    return rank_rows(scored, score=lambda r: float(r.get("score") or 0.0),
                     ms=lambda r: float(r["ms_per_frame"]) if r.get("ms_per_frame") is not None else math.inf,
                     robustness=lambda r: r["robustness"], name=lambda r: str(r.get("config")), tie_rate=tie_rate)
