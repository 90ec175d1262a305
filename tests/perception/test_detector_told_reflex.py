"""A reflex is told once the frame's detections are out, whether the running detector takes the band in place or not.

The manager answers a band nothing here takes by starting the band's configuration as a new process; told
before the detection, that start took the two cores from the very frame that showed the new light (the
running dark configuration's detection of a day frame went from about 7 ms to 15-19). A swap in place is
carried out before the frame's detection (the frame is detected with the new configuration) but told after:
its message, log line and the deployer's record wake other threads and processes. A real detector on a real
Zenoh session: the step frame is held open between its detection and the publication of its detections, and
the reflex must not arrive while it is.
"""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from kgadapt.onboard.perception import detector as detector_module
from kgadapt.onboard.perception.detector import Detector, DetectorSettings, ReflexNotifier
from kgadapt.onboard.perception.markers import MarkerDetector
from kgadapt.onboard.perception.reflex import Reflex, ReflexTable
from kgadapt.shared import keys, messages
from kgadapt.shared.readiness import CONFIGURED_TOKEN
from kgadapt.shared.session import ZenohSettings, open_session
from tests.adaptation.test_reflex_rules import CONFIG, parse, row


def _frame(seq: int, shade: int) -> bytes:
    image = np.full((120, 160), shade, np.uint8)
    _ok, jpeg = cv2.imencode(".jpg", image)
    return messages.encode(messages.Frame(camera="cam0", seq=seq, time=time.time(), width=160, height=120,
                                          jpeg=jpeg.tobytes()))


def _dark_detector(session, table: ReflexTable) -> Detector:
    """A real detector running the dark configuration, armed with ``table``, set up on ``session``."""
    detector = Detector(DetectorSettings(robot="r1", host="h1", instance="det1"),
                        parse("dark", CONFIG, "DICT_4X4_50"), deployment="d_dark")
    assert detector.arm(table, deployment="d_dark")
    detector.setup(session)
    return detector


def _two_dark_frames(detector: Detector, answered: dict[int, threading.Event]) -> None:
    for seq in (1, 2):
        detector.slot.put((_frame(seq, 5), time.time()))
        assert answered[seq].wait(5), f"frame {seq} not answered"


@pytest.fixture
def session():
    s = open_session(ZenohSettings(mode="peer", listen=("tcp/127.0.0.1:0",)))
    yield s
    s.close()


@pytest.mark.parametrize("step_to", ["day", "dusk", "dusk in place"])
def test_a_reflex_is_told_once_the_step_frame_s_detections_are_out(session, monkeypatch, capsys, step_to):
    # day: dusk may be taken in place, day only elsewhere; dusk: the top band, only elsewhere (a band with one
    # beyond it waits for the light to settle when it was reached by a step: test_reflex_rules); dusk in
    # place: the top band, taken here.
    in_place = step_to == "dusk in place"
    rows = [row("dark", 0, 12, "dark", budget=None),  # no hedging
            row("dusk", 12, 40 if step_to == "day" else 256, "dusk", in_place=step_to != "dusk", budget=None)]
    if step_to == "day":
        rows.append(row("day", 40, 256, "day", in_place=False, budget=None))
    table = ReflexTable.from_rows(rows, parse=parse)
    shade = {"day": 200, "dusk": 25, "dusk in place": 25}[step_to]
    step_config: list[str] = []
    reflexes: list[messages.Reflex] = []
    arrived = threading.Event()
    after_detections: list[bool] = []  # per reflex: were the step frame's detections out before it?
    step_seq = 3
    answered: dict[int, threading.Event] = {seq: threading.Event() for seq in (1, 2, 3)}

    # One subscriber for both keys: Zenoh runs each subscriber's callbacks on a thread of its own, so only
    # one subscriber sees two puts in the order they were made.
    def on_sample(sample) -> None:
        if str(sample.key_expr).endswith("/markers"):
            detections = messages.decode_as(sample.payload.to_bytes(), messages.Detections)
            if detections.seq == step_seq:
                step_config.append(detections.config)
            answered[detections.seq].set()
        elif str(sample.key_expr).endswith("/reflex"):
            reflexes.append(messages.decode_as(sample.payload.to_bytes(), messages.Reflex))
            after_detections.append(answered[step_seq].is_set())
            arrived.set()

    listener = session.declare_subscriber(f"{keys.robot_root('r1')}/detector/det1/*", on_sample)
    # The step frame's result is judged after its detection and before its detections go out: held open
    # there long enough for a reflex put any earlier to arrive.
    during: list[bool] = []
    real_on_result = Reflex.on_result

    def on_result(self, found, now, **kwargs):
        if kwargs.get("level") is not None and kwargs["level"] > 20 and not during:  # the step frame
            during.append(arrived.wait(0.5))
        return real_on_result(self, found, now, **kwargs)

    monkeypatch.setattr(Reflex, "on_result", on_result)
    # What the detector had published when it handed the reflex to its notifier: decided on the worker's
    # own thread, where the subscriber's arrival order above also depends on the notifier's thread.
    published_when_handed: list[int] = []
    real_put = ReflexNotifier.put

    def put(self, payload):
        if payload:  # not the empty message that ends the notifier at shutdown
            published_when_handed.append(detector.processed)
        return real_put(self, payload)

    monkeypatch.setattr(ReflexNotifier, "put", put)
    recorded_when: list[int] = []  # what the detector had published when it told its deployer the swap
    real_announce = detector_module.announce_configured

    def announce(config, deployment, **kwargs):
        recorded_when.append(detector.processed)
        return real_announce(config, deployment, **kwargs)

    monkeypatch.setattr(detector_module, "announce_configured", announce)
    detector = _dark_detector(session, table)
    try:
        _two_dark_frames(detector, answered)
        assert not reflexes  # dark frames in the dark band: nothing to tell
        detector.slot.put((_frame(step_seq, shade), time.time()))
        assert arrived.wait(5), "no reflex for the step into a band nothing here takes in place"
        assert answered[step_seq].wait(5)  # and the step frame's detections published
    finally:
        detector.shutdown()
        listener.undeclare()
    told = reflexes[0]
    if in_place:
        assert told.config == "dusk" and told.band == "dusk" and told.from_band == "dark" and told.seq == step_seq
        assert step_config == ["dusk"], "the step frame was not detected with the configuration the reflex took"
        assert f"{CONFIGURED_TOKEN} dusk d_dusk" in capsys.readouterr().out  # the deployer's record ...
        assert recorded_when == [step_seq], "the deployer's record was told before the step frame's detections went out"
    else:
        assert told.config is None and told.band == step_to and told.from_band == "dark" and told.seq == step_seq
        assert step_config == ["dark"]
    assert during == [False], "the reflex arrived before the step frame's detections went out"
    assert after_detections == [True], "the reflex went out before the step frame's detections"
    assert published_when_handed == [step_seq], "the reflex was handed over before the step frame's detections went out"


def test_a_swap_in_place_is_told_even_when_the_step_frame_s_detection_fails(session, monkeypatch, capsys):
    # The swap is carried out before the frame's detection; should that detection fail, the detector runs
    # the new configuration all the same, so the manager and the deployer's record must still hear of it.
    rows = [row("dark", 0, 12, "dark", budget=None), row("dusk", 12, 256, "dusk", budget=None)]
    table = ReflexTable.from_rows(rows, parse=parse)
    reflexes: list[messages.Reflex] = []
    arrived = threading.Event()
    answered: dict[int, threading.Event] = {seq: threading.Event() for seq in (1, 2, 3, 4)}

    def on_sample(sample) -> None:
        if str(sample.key_expr).endswith("/markers"):
            answered[messages.decode_as(sample.payload.to_bytes(), messages.Detections).seq].set()
        elif str(sample.key_expr).endswith("/reflex"):
            reflexes.append(messages.decode_as(sample.payload.to_bytes(), messages.Reflex))
            arrived.set()

    listener = session.declare_subscriber(f"{keys.robot_root('r1')}/detector/det1/*", on_sample)
    real_detect = MarkerDetector.detect
    failed: list[int] = []

    def detect(self, gray, *args, **kwargs):
        if self.config.name == "dusk" and not failed:
            failed.append(1)  # the step frame's, once
            raise RuntimeError("a detection that fails")
        return real_detect(self, gray, *args, **kwargs)

    monkeypatch.setattr(MarkerDetector, "detect", detect)
    detector = _dark_detector(session, table)
    try:
        _two_dark_frames(detector, answered)
        detector.slot.put((_frame(3, 25), time.time()))
        assert arrived.wait(5), "the swap carried out before the failed detection was never told"
        detector.slot.put((_frame(4, 25), time.time()))
        assert answered[4].wait(5), "the detector stopped after the failed frame"
    finally:
        detector.shutdown()
        listener.undeclare()
    assert not answered[3].is_set() and detector.malformed == 1
    assert [(r.config, r.seq) for r in reflexes] == [("dusk", 3)]
    assert f"{CONFIGURED_TOKEN} dusk d_dusk" in capsys.readouterr().out
    assert detector.config.name == "dusk"
