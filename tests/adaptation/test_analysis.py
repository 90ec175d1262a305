"""The analysis step: band changes with hysteresis and dwell, and the other triggers."""

from __future__ import annotations

import math

from kgadapt.onboard.adaptation.adaptation import Analyzer, Band, BandTracker, CollapseWatch, Placement, bands_from_rows

BANDS = [Band("dark", 0, 25), Band("dusk", 25, 80), Band("day", 80, 256)]


def tracker(**kw) -> BandTracker:
    return BandTracker(bands=BANDS, hysteresis=4.0, dwell_s=1.0, **kw)


def test_the_first_level_sets_the_band_at_once():
    t = tracker()
    assert t.update(120.0, now=0.0) == BANDS[2]
    assert t.current.name == "day"


def test_a_band_change_needs_the_new_band_to_hold_for_the_dwell_time():
    t = tracker()
    t.update(120.0, 0.0)
    assert t.update(50.0, 1.0) is None  # dusk seen, dwell starts
    assert t.update(50.0, 1.5) is None
    assert t.update(50.0, 2.0).name == "dusk"


def test_light_hovering_at_a_threshold_causes_no_change():
    t = tracker()
    t.update(90.0, 0.0)  # day
    changes = []
    for i in range(200):  # oscillate +-3 around the day/dusk edge at 80, 10 Hz for 20 s
        level = 80.0 + 3.0 * math.sin(i)
        change = t.update(level, 0.1 * i)
        if change:
            changes.append(change.name)
    assert changes == []


def test_a_brief_dip_shorter_than_the_dwell_does_not_change_the_band():
    t = tracker()
    t.update(120.0, 0.0)
    t.update(10.0, 1.0)
    t.update(10.0, 1.5)
    assert t.update(120.0, 1.9) is None
    assert t.update(10.0, 2.2) is None  # dwell restarts from here
    assert t.current.name == "day"


def test_bands_come_from_the_detector_configuration_rows_darkest_first():
    rows = [
        {"config": "a", "band": "day", "min_level": 80, "max_level": 256},
        {"config": "b", "band": "dark", "min_level": 0, "max_level": 25},
        {"config": "c", "band": "day", "min_level": 80, "max_level": 256},
    ]
    assert [b.name for b in bands_from_rows(rows)] == ["dark", "day"]


def test_analyzer_reports_a_band_change_with_from_and_to():
    a = Analyzer(tracker=tracker())
    assert a.on_illumination(120.0, 0.0) is None  # first band is not a change
    a.on_illumination(15.0, 1.0)
    trigger = a.on_illumination(15.0, 2.5)
    assert trigger.kind == "band_changed"
    assert trigger.detail["from"] == "day" and trigger.detail["to"] == "dark"


def test_a_host_whose_free_memory_no_longer_covers_the_running_detectors_demand_is_memory_short():
    a = Analyzer(tracker=tracker())
    running = Placement(config="marker_detection_day", deployment="d", host="onboard", demand_mb=120, held_mb=50)
    assert a.on_host_status("onboard", free_mb=300, cpu_load=10, now=0, running=running) is None
    assert a.on_host_status("onboard", free_mb=70, cpu_load=10, now=0.5, running=running) is None  # 70+50 covers 120
    trigger = a.on_host_status("onboard", free_mb=69, cpu_load=10, now=1, running=running)
    assert trigger.kind == "memory_short" and trigger.detail["host"] == "onboard"
    # A squeeze on another host does not concern the running detector.
    assert a.on_host_status("remote", free_mb=-5, cpu_load=10, now=1, running=running) is None


def test_losing_the_running_host_is_urgent_and_its_return_is_noticed():
    a = Analyzer(tracker=tracker())
    running = Placement(config="c", deployment="d", host="remote")
    assert a.on_liveliness("remote", True, 0.0, running).kind == "host_back"
    lost = a.on_liveliness("remote", False, 1.0, running)
    assert lost.kind == "host_lost" and lost.urgent
    assert a.on_liveliness("remote", False, 1.1, running) is None  # no repeat


def test_a_detection_rate_collapse_is_reported_with_its_evidence():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10))
    t = 0.0
    for _ in range(20):  # working: markers in every frame
        t += 0.1
        assert a.on_detection(True, t, expected_rate=0.9, config="c1") is None
    triggers = []
    for _ in range(10):
        t += 0.1
        triggers.append(a.on_detection(False, t, expected_rate=0.9, config="c1"))
    fired = [x for x in triggers if x]
    assert [x.kind for x in fired] == ["rate_collapsed"]
    assert fired[0].detail["config"] == "c1" and fired[0].detail["rate"] < 0.45 and fired[0].detail["expected"] == 0.9
    assert fired[0].detail["last_marker_s_ago"] <= 1.0 and a.collapsed == {"c1"}


def test_a_marker_that_left_the_view_costs_one_change_not_a_cascade():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10, memory_s=5.0))
    t = 0.0
    for _ in range(20):
        t += 0.1
        a.on_detection(True, t, expected_rate=0.9, config="c1")
    fired = []
    for config in ("c1", "c2", "c3"):  # the next detectors see nothing either: nothing is in view
        a.reset_rate()
        for _ in range(100):
            t += 0.1
            trigger = a.on_detection(False, t, expected_rate=0.9, config=config)
            if trigger:
                fired.append(trigger.detail["config"])
    assert fired == ["c1"]


def test_after_recovery_a_new_collapse_counts_again_and_a_band_change_rearms():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10))
    t = 0.0

    def feed(seen, n, config="c1"):
        nonlocal t
        out = []
        for _ in range(n):
            t += 0.1
            trigger = a.on_detection(seen, t, expected_rate=0.9, config=config)
            if trigger:
                out.append(trigger)
        return out

    feed(True, 10)
    assert len(feed(False, 10)) == 1
    assert feed(False, 10) == []  # quiet until it recovers
    feed(True, 20)  # recovered: armed again
    assert len(feed(False, 10)) == 1
    a.on_illumination(120, t)
    a.on_illumination(5, t + 0.1)
    a.on_illumination(5, t + 2.0)  # a band change
    assert a.collapsed == set() and a.collapse.armed


def test_a_flickering_detection_well_above_half_the_promise_is_no_collapse():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10))
    assert all(a.on_detection(i % 3 != 0, i * 0.1, expected_rate=0.9) is None for i in range(200))


def test_no_collapse_is_claimed_where_calibration_promised_little():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10))
    assert all(a.on_detection(False, float(i), expected_rate=0.0) is None for i in range(20))
    assert all(a.on_detection(False, float(i), expected_rate=None) is None for i in range(20))


def test_a_detector_finding_one_marker_of_six_has_collapsed_though_every_frame_has_one():
    a = Analyzer(tracker=tracker(), collapse=CollapseWatch(window=10))
    t = 0.0
    for _ in range(20):
        t += 0.1
        assert a.on_detection(6, t, expected_rate=0.95, config="c1") is None
    fired = []
    for _ in range(10):
        t += 0.1
        trigger = a.on_detection(1, t, expected_rate=0.95, config="c1")
        if trigger:
            fired.append(trigger)
    assert len(fired) == 1 and fired[0].detail["in_view"] == 6 and fired[0].detail["rate"] < 0.95 / 2


def test_the_next_band_is_the_one_left_last_else_the_neighbour_whose_edge_the_light_is_nearest():
    t = tracker()
    t.update(120.0, 0.0)
    assert t.current.name == "day" and t.neighbour(120.0).name == "dusk"  # the only neighbour
    t.current = next(b for b in BANDS if b.name == "dusk")
    assert t.neighbour(70.0).name == "day"
    assert t.neighbour(30.0).name == "dark"
    t = tracker()
    t.update(120.0, 0.0)
    t.update(5.0, 1.0)
    assert t.update(5.0, 2.5).name == "dark"
    assert t.neighbour(5.0).name == "day"  # the light comes back (not the adjacent dusk)
