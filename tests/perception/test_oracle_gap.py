"""The perception bench's oracle gap names where the band's pick is ranked and where it is not (issue 29)."""

from __future__ import annotations

from kgadapt.bench.perception_quality import gaps_by_ranking
from kgadapt.onboard.perception.calibration import ALL, APART, CONDITIONS


def gap(band: str, condition: str, points: float | None) -> dict:
    return {"band": band, "condition": condition, "planner_pick": "marker_detection_day", "best": "marker_detection_dark",
            "pick_rate": 0.5, "best_rate": 0.5, "oracle_gap_points": points}


def test_a_gap_under_blur_is_reported_apart_from_the_ranked_conditions_and_not_hidden():
    # Today's day band: 2.8 where the pick is ranked, 33.0 under the motion blur calibration sets apart.
    gaps = [gap("day", c, 0.0) for c in (*CONDITIONS, ALL)]
    gaps[list(CONDITIONS).index("uneven")]["oracle_gap_points"] = 2.8
    gaps[list(CONDITIONS).index("blur")]["oracle_gap_points"] = 33.0
    split = gaps_by_ranking(gaps)
    assert split["ranked"]["worst_gap"]["oracle_gap_points"] == 2.8 and split["ranked"]["target_met"] is True
    assert split["apart"]["worst_gap"]["condition"] == "blur" and split["apart"]["target_met"] is False
    assert set(split["apart"]["conditions"]) == set(APART)
    assert ALL in split["ranked"]["conditions"] and "blur" not in split["ranked"]["conditions"]


def test_a_condition_without_a_pick_counts_nowhere():
    split = gaps_by_ranking([gap("dark", "clean", None), gap("dark", "blur", None)])
    assert split["ranked"] == {"conditions": [], "worst_gap": None, "target_met": None}
    assert split["apart"]["worst_gap"] is None
