"""A detector's reflex table, armed after ready, gives way to a stop.

A plain start says ready and then asks the graph for its reflex table, compiles it and builds a detector
for each candidate: about 21 ms of imports and builds. A stop that came meanwhile ran beside that work and
waited for the interpreter (a stop at ready took 33-49 ms p50 against 24 ms 0.3 s later). Against the
real knowledge service over the shipped models: once told to stop, the arming does nothing more.
"""

from __future__ import annotations

import itertools

import pytest

from kgadapt.knowledge.loader import load_models
from kgadapt.onboard.perception.detector import Armed, Detector, DetectorSettings, arm, fetch_config_row
from tests.deploy.conftest import ROBOT
from tests.deploy.test_real_detector import MODELS

DEPLOYMENT = "detector_day"


@pytest.fixture
def graph(resp_store):
    load_models(resp_store, [MODELS])
    return resp_store


@pytest.fixture
def detector(test_session) -> Detector:
    config, row = fetch_config_row(test_session, ROBOT, "marker_detection_day", wait_s=5.0)
    assert row["deployment"] == DEPLOYMENT
    return Detector(DetectorSettings(robot=ROBOT, host="onboard", instance="det1"), config, deployment=DEPLOYMENT)


def test_a_stop_told_while_the_table_is_asked_for_leaves_it_uncompiled_and_unbuilt(test_session, detector):
    asked: list[int] = []

    def stopping() -> bool:
        asked.append(len(asked))
        return True  # told to stop while the question was out

    assert arm(detector, test_session, wait_s=5.0, stopping=stopping) is Armed.STOPPED
    assert asked == [0], "asked before the answer was in, or again after it said stop"
    assert detector.candidates() == []
    # The same table when nothing stops it: candidates to build, so the stop above skipped real work.
    assert arm(detector, test_session, wait_s=5.0) is Armed.ARMED
    assert len(detector.candidates()) >= 2


def test_a_stop_told_between_two_candidates_builds_no_more_and_arms_nothing(test_session, detector):
    counts = itertools.count()
    asked: list[int] = []

    def stopping() -> bool:
        n = next(counts)
        asked.append(n)
        return n >= 2  # after the answer (0) and the first candidate (1): stop before the second

    assert arm(detector, test_session, wait_s=5.0, stopping=stopping) is Armed.STOPPED
    assert asked == [0, 1, 2], "the builds did not look at the stop before each candidate"
    assert detector.candidates() == []
