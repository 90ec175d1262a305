"""The adaptation bench's light steps (kgadapt.operator.timeline.Recorder.light_steps) over recorded values:
a frame exposed during a step, and a reflex to a band the light only passed through, are counted per step."""

from __future__ import annotations

from kgadapt.bench.adaptation_bench import band_of, classify
from kgadapt.operator.timeline import Recorder, ReflexSeen

IDS = frozenset({1})


def _reflex(band: str, seq: int, frame_time: float) -> ReflexSeen:
    return ReflexSeen(time=frame_time + 0.02, instance="det", previous="marker_detection_dark", config=None,
                      band=band, evidence="light", level=None, seq=seq, frame_time=frame_time)


def test_a_step_with_a_frame_exposed_during_it_and_a_reflex_to_the_band_between_is_counted():
    rec = Recorder(robot="r1")
    levels = [5.0, 5.0, 18.7, 120.0, 120.0, 120.0, 5.0, 5.0, 120.0]  # dark, caught, day; day -> dark; -> day clean
    for seq, level in enumerate(levels, start=1):
        rec.frames[seq] = (100.0 + seq / 30, level, IDS)
        rec.found.append((seq, 100.0 + seq / 30 + 0.015, IDS))
    rec.reflexes += [_reflex("dusk", 3, 100.0 + 3 / 30), _reflex("day", 4, 100.0 + 4 / 30),
                     _reflex("dark", 7, 100.0 + 7 / 30), _reflex("day", 9, 100.0 + 9 / 30)]
    steps = rec.light_steps(classify, band_of=band_of)
    assert [(s.kind, s.frame_seq, s.between, s.bands_between) for s in steps] == [
        ("dark->day", 4, True, 1), ("day->dark", 7, False, 0), ("dark->day", 9, False, 0)]
    assert [round(s.blind_ms, 1) for s in steps] == [15.0, 15.0, 15.0]
    assert band_of("window-dark") == "dark" and band_of("day") == "day"
