"""Live evidence (onboard/adaptation/live_rate.py): how frames count and how the ranking weighs them, on plain values."""

from __future__ import annotations

import pytest

from kgadapt.onboard.adaptation.live_rate import LiveRates, LiveSettings, decided_by, fresh, weigh
from kgadapt.onboard.perception.calibration import rank_rows

SETTINGS = LiveSettings(max_age_s=60.0, min_expected=30, window=100, write_every_s=2.0, expect_s=1.0,
                        agree=0.15)
# Synthetic calibration ranks A over B in the band.
RANKING = [{"config": "A", "detection_rate": 0.95, "false_per_frame": 0.0, "ms_per_frame": 5.0, "score": 0.95},
           {"config": "B", "detection_rate": 0.80, "false_per_frame": 0.05, "ms_per_frame": 9.0, "score": 0.75}]


def live(config: str, rate: float, expected: int = 40, at: float = 1000.0) -> dict:
    return {"config": config, "detection_rate": rate, "frames": expected + 10, "frames_expected": expected,
            "frames_seen": int(rate * expected), "since": at - 5.0, "at": at}


def ranked(rows: list[dict]) -> list[str]:
    return [r["config"] for r in rank_rows(rows, score=lambda r: r["score"], ms=lambda r: r["ms_per_frame"],
                                           tie_rate=0.005)]


def test_fresh_live_evidence_on_enough_frames_outweighs_synthetic_calibration():
    rows = weigh(RANKING, [live("A", 0.0), live("B", 1.0)], now=1003.0, settings=SETTINGS, source="synthetic")
    assert ranked(rows) == ["B", "A"]
    a, b = (next(r for r in rows if r["config"] == c) for c in "AB")
    assert (a["evidence"], a["score"], a["live_age_s"]) == ("live", 0.0, 3.0)
    assert b["evidence"] == "live" and b["score"] == pytest.approx(1.0 - 0.05)  # calibration's false markers stay
    assert decided_by(rank_rows(rows, score=lambda r: r["score"], ms=lambda r: 0.0), b) == "live"
    # A collapse alone is enough: B keeps its synthetic figure and still comes first; the live evidence
    # (on A) is what decided.
    alone = rank_rows(weigh(RANKING, [live("A", 0.1)], now=1003.0, settings=SETTINGS), score=lambda r: r["score"],
                      ms=lambda r: r["ms_per_frame"])
    assert [r["config"] for r in alone] == ["B", "A"] and alone[0]["evidence"] == "synthetic"
    assert decided_by(alone, alone[0]) == "live"


def test_live_evidence_that_agrees_with_calibration_confirms_it_and_calibration_ranks():
    # Real frames are seldom as clean as the scene: A working at 0.85 of its 0.95 keeps its place above B.
    rows = weigh(RANKING, [live("A", 0.85), live("B", 0.7)], now=1003.0, settings=SETTINGS)
    order = rank_rows(rows, score=lambda r: r["score"], ms=lambda r: r["ms_per_frame"])
    assert [r["config"] for r in order] == ["A", "B"]
    assert [(r["evidence"], r["live_agrees"], r["score"]) for r in order] == [
        ("synthetic", True, 0.95), ("synthetic", True, 0.75)]
    assert decided_by(order, order[0]) == "synthetic"


@pytest.mark.parametrize("why, figure, now", [
    ("too old", live("A", 0.0, at=900.0), 1000.0),
    ("too few frames with markers expected", live("A", 0.0, expected=29), 1000.0),
    ("from the future beyond clock skew", live("A", 0.0, at=1100.0), 1000.0),
])
def test_live_evidence_that_is_stale_or_thin_leaves_the_calibration_in_charge(why, figure, now):
    rows = weigh(RANKING, [figure], now=now, settings=SETTINGS, source="frames:hall")
    assert not fresh(figure, now=now, settings=SETTINGS), why
    assert ranked(rows) == ["A", "B"], why
    a = next(r for r in rows if r["config"] == "A")
    assert a["evidence"] == "frames:hall" and a["score"] == 0.95 and a["live_rate"] == 0.0  # shown, not counted


def test_frames_count_only_while_markers_are_expected():
    rates = LiveRates(settings=SETTINGS)
    t = 100.0
    for _ in range(30):  # day: B finds 2 markers a frame
        assert rates.add(config="B", band="day", found=2, now=t)
        t += 1 / 30
    for _ in range(60):  # the light steps to dark under A: expected for a second after the last marker, then not
        rates.add(config="A", band="dark", found=0, now=t)
        t += 1 / 30
    a = rates.figures("A", "dark", t)
    assert a["frames"] == 60 and 29 <= a["frames_expected"] <= 31 and a["frames_seen"] == 0
    assert a["detection_rate"] == 0.0
    # In final descent the pad is in view: frames count although nothing was seen lately.
    assert rates.add(config="A", band="dark", found=0, now=t, pad_in_view=True)
    # Finding one of the two markers in view is half the expected markers.
    rates.add(config="C", band="dark", found=2, now=t + 0.01)
    rates.add(config="C", band="dark", found=1, now=t + 0.02)
    assert rates.figures("C", "dark", t + 0.02)["detection_rate"] == pytest.approx(0.75)


def test_writes_are_bounded_one_per_changed_window_at_most_every_few_seconds():
    rates = LiveRates(settings=SETTINGS)
    for i in range(300):  # 10 s at 30 frames/s, two configurations, one band each
        rates.add(config="A" if i % 2 else "B", band="dark", found=1, now=100.0 + i / 30)
    writes = rates.due(110.0)
    assert sorted(w["config"] for w in writes) == ["A", "B"]
    assert all(w["frames_expected"] == 100 and w["frames"] == 150 for w in writes)  # the window is bounded
    assert rates.due(111.0) == []  # within write_every_s
    assert rates.due(113.0) == []  # nothing new since
    rates.add(config="A", band="dark", found=1, now=113.5)
    assert [w["config"] for w in rates.due(114.0)] == ["A"]
