"""The detector's reflex rules (kgadapt.onboard.perception.reflex) over plain values: the table the graph gives,
and what each frame's evidence leads to. The whole path with processes is tests/adaptation/test_reflex.py."""

from __future__ import annotations

import pytest

from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.queries import run_named
from kgadapt.knowledge.store import open_store
from kgadapt.onboard.perception.markers import parse_config
from kgadapt.onboard.perception.reflex import Reflex, ReflexSettings, ReflexTable
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.resources import models
from kgadapt.shared.states import ReflexEvidence

CONFIG = '{"dictionary": "DICT_4X4_50", "preprocess": [], "parameters": {}}'


def row(band, low, high, config, *, rate=None, in_place=True, suited=True, ms=3.0, margin=5.0, budget=33.0,
        deployment=None, false=0.0):
    return {"band": band, "min_level": low, "max_level": high, "margin": margin, "config": config,
            "dictionary": "DICT_4X4_50", "config_json": CONFIG, "detection_rate": rate, "false_per_frame": false,
            "ms_per_frame": ms, "suited": suited, "deployment": deployment or f"d_{config}", "in_place": in_place,
            "budget_ms": budget}


def parse(name, raw, dictionary):
    return parse_config(name, raw, dictionary=dictionary)


BANDS = [("dark", 0, 12), ("dusk", 12, 40), ("day", 40, 255)]


def table(**extra):
    return ReflexTable.from_rows([row(b, lo, hi, b, **extra) for b, lo, hi in BANDS], parse=parse)


def test_the_table_ranks_calibrated_configurations_and_keeps_only_what_may_run_here_in_place():
    rows = [row("dark", 0, 12, "dark_a", rate=0.9, suited=False), row("dark", 0, 12, "dark_b", rate=0.95, ms=9),
            row("dark", 0, 12, "dark_hd", rate=1.0, in_place=False, suited=False),
            row("day", 40, 255, "day", suited=True, margin=None)]
    t = ReflexTable.from_rows(rows, parse=parse, default_margin=4.0)
    dark = t.entry("dark")
    assert [c.config for c in dark.choices] == ["dark_b", "dark_a"]  # the best one needs another process
    assert dark.best_elsewhere == "dark_hd"
    assert t.entry("day").margin == 4.0 and t.budget_ms == 33.0
    assert [e.band.name for e in t.entries] == ["dark", "day"]


def test_fresh_live_evidence_reorders_the_table_as_it_reorders_the_planner_s_ranking():
    # Calibration puts dark_a first in band dark; this robot's own detector found 10 % with it over the last
    # minute (60 frames with markers expected) while dark_b, the second, found 90 %.
    def dark(config, rate, **live):
        return {**row("dark", 0, 12, config, rate=rate), **live}

    now = 10_000.0
    fresh = [dark("dark_a", 0.95, live_rate=0.10, live_frames_expected=60, live_at=now - 60),
             dark("dark_b", 0.80, live_rate=0.90, live_frames_expected=60, live_at=now - 60)]
    assert [c.config for c in ReflexTable.from_rows(fresh, parse=parse, now=now).entry("dark").choices] == [
        "dark_b", "dark_a"]
    # Evidence too old, or resting on too few frames, or no clock to age it by: calibration decides.
    stale = [{**r, "live_at": now - 600} for r in fresh]
    few = [{**r, "live_frames_expected": 5} for r in fresh]
    for rows, at in ((stale, now), (few, now), (fresh, None)):
        assert [c.config for c in ReflexTable.from_rows(rows, parse=parse, now=at).entry("dark").choices] == [
            "dark_a", "dark_b"]


def test_the_graph_s_live_figures_reach_the_detector_s_table(tmp_path):
    # The shipped models, calibrated so that the day configuration ranks first in band dark; the manager's
    # live write (the same writer its service verb uses) says it finds nothing there while the dark one does.
    import time

    from kgadapt.knowledge.runtime import record_calibration, record_live_rate

    now = time.time()
    with open_store(f"embedded:{tmp_path / 'store'}") as store:
        load_models(store, [str(models())])
        for config, rate in (("marker_detection_day", 0.95), ("marker_detection_dark", 0.80),
                             ("marker_detection_dusk", 0.70)):
            record_calibration(store, config=config, band="dark", detection_rate=rate, false_per_frame=0.0,
                               ms_per_frame=4.0, time=1.0)
        before = run_named(store, "reflex_table", {"deployment": "detector_day", "host": "onboard"})
        for config, rate in (("marker_detection_day", 0.0), ("marker_detection_dark", 0.92)):
            record_live_rate(store, config=config, band="dark", detection_rate=rate, frames=90, frames_expected=60,
                             frames_seen=int(rate * 60), since=now - 5, time=now - 1, run_id="run-1", host="onboard")
        after = run_named(store, "reflex_table", {"deployment": "detector_day", "host": "onboard"})
    order = [c.config for c in ReflexTable.from_rows(before, parse=parse, now=now).entry("dark").choices]
    assert order[0] == "marker_detection_day"
    order = [c.config for c in ReflexTable.from_rows(after, parse=parse, now=now).entry("dark").choices]
    assert order[:2] == ["marker_detection_dark", "marker_detection_dusk"]  # day's 0 % live is below dusk's 70 %
    assert {r["config"]: r["live_rate"] for r in after if r["band"] == "dark"}["marker_detection_dark"] == 0.92


def test_a_bad_band_row_is_refused_naming_the_band():
    with pytest.raises(ConfigError, match="band 'dark'"):
        ReflexTable.from_rows([{**row("dark", 0, 12, "x"), "max_level": None}], parse=parse)


def test_a_frame_past_the_edge_by_the_margin_switches_before_it_is_detected():
    r = Reflex(table=table(), running="day")
    assert r.on_light(120.0) is None and r.band == "day"
    assert r.on_light(36.0) is None  # within the margin below the edge (40 - 5)
    swap = r.on_light(5.0)
    assert (swap.config, swap.previous, swap.band, swap.from_band, swap.evidence) == (
        "dark", "day", "dark", "day", ReflexEvidence.LIGHT)
    assert swap.deployment == "d_dark" and r.running == "dark"
    assert r.on_light(6.0) is None  # the same band: nothing more


def test_a_detector_just_started_takes_its_configuration_s_band_so_a_step_during_its_start_counts():
    r = Reflex(table=table(), running="dusk")
    swap = r.on_light(120.0)  # started for dusk, the light is day already
    assert (swap.config, swap.from_band, swap.band) == ("day", "dusk", "day")
    r2 = Reflex(table=table(), running="dusk")
    assert r2.on_light(20.0) is None and r2.band == "dusk"


def test_a_band_nothing_may_take_in_place_is_reported_not_switched():
    rows = [row("day", 40, 255, "day"), row("dark", 0, 12, "dark_remote", in_place=False)]
    r = Reflex(table=ReflexTable.from_rows(rows, parse=parse), running="day")
    r.on_light(120.0)
    swap = r.on_light(5.0)
    assert swap.config is None and swap.elsewhere == "dark_remote" and r.running == "day"
    # Back in the band of what runs: told too, so the manager's band follows.
    back = r.on_light(120.0)
    assert (back.config, back.band, back.from_band, back.elsewhere) == (None, "day", "dark", None)
    assert r.on_light(5.0).config is None and r.on_light(6.0) is None


def _told_only(in_place=("dark",), **settings):
    """Dark running; the bands not in ``in_place`` only another process may take."""
    rows = [row(b, lo, hi, b, in_place=b in in_place) for b, lo, hi in BANDS]
    return Reflex(table=ReflexTable.from_rows(rows, parse=parse), running="dark", settings=ReflexSettings(**settings))


def test_a_frame_caught_while_a_lamp_comes_on_tells_no_band_the_light_only_passes_through():
    # A step dark -> day whose first frame was exposed while the lamp came on (a bench run: 23 of 32 such
    # steps read 17-31): the dusk band, with the day band beyond it, is not told for that frame; day is.
    r = _told_only()
    assert r.on_light(5.0) is None and r.on_light(5.2) is None
    assert r.on_light(19.0) is None and r.band == "dark"  # moved by 13.8 > the margin, day beyond
    swap = r.on_light(120.0)
    assert (swap.config, swap.band, swap.from_band) == (None, "day", "dark")
    # Day -> dark through a frame that reads dusk: dark is told, dusk never.
    r = _told_only(in_place=("day",))
    r.running = "day"
    assert r.on_light(120.0) is None and r.band == "day"
    assert r.on_light(33.0) is None
    swap = r.on_light(5.0)
    assert (swap.config, swap.band, swap.from_band) == (None, "dark", "day")


def test_a_band_the_light_settles_in_is_told_on_the_next_frame_and_a_moving_light_waits_a_bounded_time():
    r = _told_only()
    r.on_light(5.0)
    assert r.on_light(19.0) is None
    swap = r.on_light(21.0)  # within the margin of the last frame: settled in dusk
    assert (swap.config, swap.band, swap.from_band) == (None, "dusk", "dark")
    # Still moving by more than the margin every frame, still in dusk: told after settle_frames frames.
    r = _told_only(settle_frames=2)
    r.on_light(5.0)
    assert r.on_light(19.0) is None and r.on_light(26.0) is None
    swap = r.on_light(33.0)
    assert (swap.band, swap.from_band) == ("dusk", "dark")
    # 0: told at once, as before.
    assert _told_only(settle_frames=0).on_light(5.0) is None
    r = _told_only(settle_frames=0)
    r.on_light(5.0)
    assert r.on_light(19.0).band == "dusk"


def test_a_step_to_the_last_band_a_drift_and_an_in_place_band_are_not_held():
    r = _told_only()
    r.on_light(5.0)
    assert r.on_light(120.0).band == "day"  # nothing beyond day: told on the step's first frame
    r = _told_only()
    for level in (8.0, 11.0, 14.0, 17.5):  # a slow drift past the edge (12) and its margin (5): a frame never
        got = r.on_light(level)            # moves more than the margin
    assert got is not None and got.band == "dusk"
    r = _told_only(in_place=("dark", "dusk"))
    r.on_light(5.0)
    swap = r.on_light(19.0)  # dusk runs here in place: swapped at once, no process to start
    assert (swap.config, swap.band) == ("dusk", "dusk")


def test_settle_frames_below_zero_is_refused():
    with pytest.raises(ConfigError, match="settle_frames"):
        ReflexSettings(settle_frames=-1)


def test_after_a_switch_the_new_one_stays_when_it_finds_the_markers():
    r = Reflex(table=table(), running="day")
    r.on_light(120.0)
    r.on_light(5.0)
    assert r.hedge_for(5.0) == "day"  # the previous one runs beside it on the next frames
    assert r.on_result(4, 1.0, hedge="day", hedge_found=0) is None
    assert r.trial is None and r.running == "dark" and r.hedge_for(5.0) is None


def test_after_a_switch_it_goes_back_when_only_the_old_one_finds_the_markers():
    r = Reflex(table=table(), running="day", settings=ReflexSettings(confirm_frames=2))
    r.on_light(120.0)
    r.on_light(5.0)
    assert r.on_result(0, 1.0, hedge="day", hedge_found=3) is None  # once is not yet evidence
    back = r.on_result(0, 1.03, hedge="day", hedge_found=3)
    assert (back.config, back.evidence) == ("day", ReflexEvidence.REVERT) and r.running == "day"
    assert r.on_light(5.0) is None  # still the dark band: the light alone does not flip it again


def test_near_an_edge_the_neighbouring_configuration_is_the_hedge_and_wins_on_evidence():
    r = Reflex(table=table(), running="day")
    r.on_light(120.0)
    assert r.hedge_for(120.0) is None
    assert r.hedge_for(42.0) == "dusk"  # within the day band's margin of its lower edge
    r.on_result(0, 1.0, hedge="dusk", hedge_found=2)
    swap = r.on_result(0, 1.03, hedge="dusk", hedge_found=2)
    assert (swap.config, swap.evidence) == ("dusk", ReflexEvidence.HEDGE)


def test_a_collapse_after_markers_tries_the_next_candidate_once_and_then_goes_back():
    s = ReflexSettings(collapse_frames=3, trial_frames=4, memory_s=1.0)
    r = Reflex(table=table(), running="dusk", settings=s)
    r.on_light(30.0)
    r.on_result(5, 10.0)
    assert r.on_result(0, 10.03) is None and r.on_result(0, 10.06) is None
    swap = r.on_result(0, 10.1, level=14.0)
    assert (swap.config, swap.evidence) == ("dark", ReflexEvidence.COLLAPSE)  # the nearer neighbour
    # Nothing found by either: back to the band's own choice once the try is over, no cascade down the table.
    swaps = [r.on_result(0, 10.2 + i * 0.03, hedge=r.hedge_for(14.0), hedge_found=0) for i in range(12)]
    back = [x for x in swaps if x is not None]
    assert [(x.config, x.evidence) for x in back] == [("dusk", ReflexEvidence.REVERT)] and r.running == "dusk"
    assert swaps.index(back[0]) == s.trial_frames - 1
    # Markers long gone (left the view): no collapse.
    r2 = Reflex(table=table(), running="dusk", settings=s)
    r2.on_light(30.0)
    r2.on_result(5, 10.0)
    assert all(r2.on_result(0, 12.0 + i * 0.03) is None for i in range(5))


def test_what_the_manager_sets_is_followed_not_fought():
    r = Reflex(table=table(), running="dark")
    r.on_light(5.0)
    r.taken("day", level=5.0)  # the manager reconfigured it (its own reasons)
    assert r.running == "day" and r.on_light(5.0) is None and r.trial is None


def test_a_table_that_arrives_after_the_manager_s_change_follows_the_light_not_the_configuration():
    # The detector's reflex table comes after it said ready; the manager changed it to dark meanwhile, in
    # light the table calls day. The manager's choice is followed (the band is the light's), not undone
    # as a start's stale configuration would be; the light crossing an edge later still counts.
    r = Reflex(table=table(), running="dark", follow_light=True)
    assert r.on_light(120.0) is None and r.band == "day" and r.running == "dark"
    swap = r.on_light(20.0)
    assert (swap.config, swap.from_band, swap.band) == ("dusk", "day", "dusk")
    # The same when the change comes after the table but before its first frame.
    r2 = Reflex(table=table(), running="day")
    r2.taken("dark")
    assert r2.on_light(120.0) is None and r2.running == "dark"


def test_the_shipped_models_give_every_band_an_in_place_configuration_onboard(tmp_path):
    with open_store(f"embedded:{tmp_path / 'store'}") as store:
        load_models(store, [str(models())])
        rows = run_named(store, "reflex_table", {"deployment": "detector_day", "host": "onboard"})
        remote_only = run_named(store, "reflex_table", {"deployment": "detector_hd", "host": "onboard"})
    t = ReflexTable.from_rows(rows, parse=parse)
    assert [(e.band.name, e.margin, e.best.config) for e in t.entries] == [
        ("dark", 5.0, "marker_detection_dark"), ("dusk", 5.0, "marker_detection_dusk"),
        ("day", 5.0, "marker_detection_day")]
    assert t.budget_ms == 33.0
    # detector_hd is not executable onboard: nothing may be taken in place from it there.
    assert remote_only and not any(r["in_place"] for r in remote_only)


def test_the_manager_follows_a_reflex_and_the_smoothed_light_may_undo_it_only_after_the_hold():
    from kgadapt.onboard.adaptation.adaptation import Analyzer, Band, BandTracker
    from kgadapt.shared.states import TriggerKind

    bands = [Band("dark", 0, 12), Band("dusk", 12, 40), Band("day", 40, 255)]
    a = Analyzer(tracker=BandTracker(bands=bands, hysteresis=4.0, dwell_s=1.0))
    a.on_illumination(120.0, 0.0)
    trigger = a.on_reflex("dark", 10.0, {"evidence": "light"}, hold_s=2.0)
    assert trigger.kind == TriggerKind.REFLEX and a.tracker.current.name == "dark"
    assert a.tracker.previous.name == "day"
    # A band moved by a reflex counts as a band change (a standby stopped for memory may come back), one that
    # keeps the band does not.
    from kgadapt.onboard.adaptation import adaptation_policy as P
    same = Analyzer(tracker=BandTracker(bands=bands, hysteresis=4.0, dwell_s=1.0))
    same.on_illumination(5.0, 0.0)
    assert P.band_moved(trigger) and not P.band_moved(same.on_reflex("dark", 1.0, {"evidence": "light"}, hold_s=2.0))
    # The smoothed level still says day (it lags): no band change back while the hold lasts ...
    assert all(a.on_illumination(100.0, 10.0 + t / 10) is None for t in range(20))
    # ... but a light that stays in the day past the hold and the dwell undoes it.
    assert a.on_illumination(100.0, 12.1) is None
    back = a.on_illumination(100.0, 13.2)
    assert back is not None and back.kind == TriggerKind.BAND_CHANGED and back.detail["to"] == "day"


def test_a_reflex_decision_leaves_out_what_receivers_of_the_first_contract_do_not_know():
    # tests/contract's outsider checks trigger_kind and change against the values it was written for.
    from kgadapt.onboard.adaptation.adaptation import Placement, Plan, Trigger
    from kgadapt.onboard.adaptation.adaptation_policy import Outcome, decision_record
    from kgadapt.shared import messages
    from kgadapt.shared.states import Change, TriggerKind

    target = Placement(config="marker_detection_dark", deployment="detector_dark", host="onboard", instance="d1")
    outcome = Outcome(trigger=Trigger(TriggerKind.REFLEX, 1.0, {"evidence": "light", "band": "dark"}),
                      plan=Plan(target=target, reason="the detector's reflex", inputs={"band": "dark"},
                                queries=("reflex_table",)),
                      outcome="reconfigured by reflex", latency_ms=40.0, frames_lost=0,
                      detail={"change": Change.REFLEX, "previous_instance": "d1"})
    params, event = decision_record(outcome, robot="quad1", wall=2.0, seq=1, instance="d1")
    assert params["trigger"].startswith("reflex(evidence=light") and '"change": "reflex"' in params["inputs_json"]
    decoded = messages.decode(messages.encode(event), "adaptation_event")
    assert "trigger_kind" not in decoded["decision"] and "change" not in decoded["decision"]
    assert decoded["trigger"].startswith("reflex(") and decoded["decision"]["config"] == "marker_detection_dark"


# -- a collapse in steady light: motion blur first; a fall of the count, not only zero (issue 29) ------------

def day_band(*, blur=True):
    # The day band as calibration ranks it: day first (cheapest, as good as the others on the band as a
    # whole), dusk second; under motion blur the slower dark one holds best (the synthetic blur scene's
    # figures of a 2 x 2 calibration: dark 48 %, day 12 %, dusk 8 %).
    figures = [("day", 0.99, 3.0, 0.12), ("dusk", 0.985, 3.5, 0.08), ("dark", 0.97, 9.0, 0.48)]
    rows = [{**row("day", 40, 255, c, rate=r, ms=ms), **({"blur_rate": b, "blur_false_per_frame": 0.0} if blur else {})}
            for c, r, ms, b in figures]
    rows += [row("dark", 0, 12, "dark", rate=0.9, ms=9.0), row("dusk", 12, 40, "dusk", rate=0.9, ms=3.5)]
    return ReflexTable.from_rows(rows, parse=parse)


def collapse_after_markers(r, levels):
    """Markers seen at the first level, then none on the next frames at the next levels; the swaps."""
    r.on_light(levels[0])
    r.on_result(6, 10.0, level=levels[0])
    return [r.on_result(0, 10.0 + 0.03 * (i + 1), level=lv) for i, lv in enumerate(levels[1:])]


def test_the_table_carries_each_band_s_order_under_blur_from_the_graph_s_blur_figures():
    t = day_band()
    assert [c.config for c in t.entry("day").choices] == ["day", "dusk", "dark"]
    assert [c.config for c in t.entry("day").blur_order] == ["dark", "day", "dusk"]
    assert day_band(blur=False).entry("day").blur_order == ()


def test_a_collapse_in_steady_light_tries_the_band_s_best_under_blur_first():
    r = Reflex(table=day_band(), running="day")
    swaps = collapse_after_markers(r, [120.0, 121.0, 119.0, 120.5])
    assert swaps[:2] == [None, None]
    assert (swaps[2].config, swaps[2].evidence) == ("dark", ReflexEvidence.COLLAPSE)
    # Without blur figures, or when the light moved (here by more than the band's margin, still in the band),
    # the old order: the band's next choice.
    r = Reflex(table=day_band(blur=False), running="day")
    assert collapse_after_markers(r, [120.0, 121.0, 119.0, 120.5])[2].config == "dusk"
    r = Reflex(table=day_band(), running="day")
    assert collapse_after_markers(r, [120.0, 60.0, 60.0, 60.0])[2].config == "dusk"
    # The one holding best under blur collapsing: nothing better under blur, the old order.
    r = Reflex(table=day_band(), running="dark")
    r.band = "day"
    assert collapse_after_markers(r, [120.0, 121.0, 119.0, 120.5])[2].config == "day"


def feed(r, counts, *, start=0.0, level=120.0, hedge_found=None, beside=True):
    """``counts`` per frame at 30 frames/s (the previous configuration finding ``hedge_found`` beside it
    whenever the reflex compares; ``beside`` False: nothing fits the budget beside it); the swaps that came,
    with their frame."""
    out = []
    for i, n in enumerate(counts):
        hedge = r.hedge_for(level) if beside and (not n or r.comparing) else None
        swap = r.on_result(n, start + i / 30, hedge=hedge,
                           hedge_found=(hedge_found if hedge_found is not None else 0) if hedge else 0, level=level)
        if swap is not None:
            out.append((i, swap.config, swap.evidence))
    return out


def test_a_fall_of_the_count_is_a_collapse_where_the_zero_rule_never_fires():
    # 20 markers a frame in sharp frames, then a motion blur leaves one or two: never zero.
    sharp, blurred = [20] * 30, [1, 2, 1, 1, 2, 1, 1, 1, 2, 1]
    r = Reflex(table=day_band(), running="day")
    r.on_light(120.0)
    swaps = feed(r, sharp + blurred, hedge_found=1)
    assert swaps[0] == (31, "dark", ReflexEvidence.COLLAPSE)  # the second blurred frame (20, 1, 2: below half)
    off = Reflex(table=day_band(), running="day", settings=ReflexSettings(fall_fraction=0.0))
    off.on_light(120.0)
    assert feed(off, sharp + blurred) == []
    # A half is the threshold: a view that keeps half its markers (a turn, markers leaving it) is no collapse.
    calm = Reflex(table=day_band(), running="day")
    calm.on_light(120.0)
    assert feed(calm, sharp + [10] * 10) == []


def test_after_a_fall_the_try_stays_only_when_it_finds_more_on_the_same_frames():
    s = ReflexSettings(trial_frames=6)
    sharp, blurred = [20] * 30, [1, 1]  # a fall on the second blurred frame
    # The try finds 5 a frame where the previous one, run beside it on every frame, finds 1: it stays.
    r = Reflex(table=day_band(), running="day", settings=s)
    r.on_light(120.0)
    feed(r, sharp + blurred, hedge_found=1)
    assert r.running == "dark" and r.comparing
    assert feed(r, [5] * 6, start=2.0, hedge_found=1) == [] and r.running == "dark" and not r.comparing
    # The try finds as many as the previous one: back after the trial, and no second try on the same fall.
    r = Reflex(table=day_band(), running="day", settings=s)
    r.on_light(120.0)
    feed(r, sharp + blurred, hedge_found=1)
    back = feed(r, [1] * 6, start=2.0, hedge_found=1)
    assert back == [(5, "day", ReflexEvidence.REVERT)] and r.running == "day"
    assert feed(r, [1] * 30, start=3.0, hedge_found=1) == []


def test_a_try_judged_against_a_count_still_falling_is_taken_again_when_the_previous_one_finds_fewer():
    # 20 markers a frame, then a blur that keeps taking markers: 6, 5, 4 (a fall), and nothing fits the budget
    # beside the try, so its trial is judged against the count that fell (5 a frame). The try (dark) finds 3 a
    # frame: reverted. Back on the previous configuration the count has gone on falling: 1 a frame, fewer
    # than the try found. The try is taken again and kept.
    sharp, falling = [20] * 30, [6, 5, 4]

    def reverted():
        r = Reflex(table=day_band(), running="day")
        r.on_light(120.0)
        assert feed(r, sharp + falling, beside=False) == [(32, "dark", ReflexEvidence.COLLAPSE)]
        assert feed(r, [3] * 6, start=2.0, beside=False) == [(5, "day", ReflexEvidence.REVERT)]
        return r

    r = reverted()
    assert r.comparing and r.hedge_for(120.0) == "dark"  # the try beside the previous one, within the budget
    assert feed(r, [1] * 3, start=3.0, beside=False) == [(2, "dark", ReflexEvidence.COLLAPSE)]
    assert feed(r, [3] * 30, start=4.0, hedge_found=1) == [] and r.running == "dark"
    # The previous one finds as many as the try did: it was right to go back, and stays.
    r = reverted()
    assert feed(r, [3] * 30, start=3.0, beside=False) == [] and r.running == "day" and not r.comparing
    # The try run beside it on the same frames finds fewer than the previous one: that, not its trial, decides.
    r = reverted()
    assert feed(r, [2] * 30, start=3.0, hedge_found=1) == [] and r.running == "day"


def test_a_fall_s_try_is_judged_against_the_frames_that_fell_not_those_before_the_fall():
    # At a fall rule of a half the fall fires on the second blurred frame, while the window still holds a sharp
    # one (35, 2, 1). The previous configuration's figure for the trial is what it found after the fall (1.5 a
    # frame), not the window's mean (12.7): the try finding 3 a frame stays.
    r = Reflex(table=day_band(), running="day", settings=ReflexSettings(fall_fraction=1 / 2))
    r.on_light(120.0)
    assert feed(r, [35] * 30 + [2, 1], beside=False) == [(31, "dark", ReflexEvidence.COLLAPSE)]
    assert feed(r, [3] * 30, start=2.0, beside=False) == [] and r.running == "dark"


def test_a_fall_of_what_holds_best_under_blur_tries_nothing_that_holds_worse():
    # The dark configuration, best under blur in the day band, runs through a blur (5 a frame), then its
    # count dips (1, 0, 1): a fall, but nothing in the band holds better under blur, so no try.
    r = Reflex(table=day_band(), running="dark")
    r.band = "day"
    assert feed(r, [5] * 30 + [1, 0, 1] + [5] * 10, beside=False) == [] and r.running == "dark"
    # Without blur figures the old order: the band's first choice is tried.
    r = Reflex(table=day_band(blur=False), running="dark")
    r.band = "day"
    assert feed(r, [5] * 30 + [1, 0, 1], beside=False)[0][1:] == ("day", ReflexEvidence.COLLAPSE)
