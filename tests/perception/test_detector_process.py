"""The detector program as a child process: frames in over Zenoh, detections out."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest
import zenoh

from kgadapt.onboard.perception.camera import CameraPart, CameraSettings, SyntheticSource
from kgadapt.onboard.perception.markers import score
from kgadapt.onboard.perception.scene import IlluminationProfile, SyntheticScene
from kgadapt.shared import keys, messages
from tests.perception.conftest import DAY_JSON, Collector, wait_for

HAVE_SERVICE = (Path(__file__).resolve().parents[2] / "knowledge" / "service.py").exists()


def detector_args(endpoint: str, robot: str, instance: str, *config: str) -> list[str]:
    return ["--robot", robot, "--host", "onboard", "--instance", instance, "--connect", endpoint, *config]


def frame_payload(seq: int, image: np.ndarray, truth: list | None = None, camera: str = "cam0") -> bytes:
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    body = {"camera": camera, "seq": seq, "time": time.time(), "width": image.shape[1], "height": image.shape[0],
            "jpeg": jpeg.tobytes()}
    if truth is not None:
        body["truth"] = truth
    return messages.encode("frame", body)


def put_until(session, key: str, payload_of, collector: Collector, predicate, timeout: float = 15.0):
    """Publish frames (10 ms apart) until a detection satisfies ``predicate``: the detector's
    subscription takes a moment to reach this session after it says it is ready."""
    deadline = time.monotonic() + timeout
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        session.put(key, payload_of(seq))
        try:
            found = collector.next(timeout=0.01)
        except Exception:
            continue
        if predicate(found):
            return found
    raise AssertionError(f"no matching detection within {timeout} s")


def test_detections_from_a_detector_process_match_the_ground_truth(endpoint_session, robot, detectors):
    endpoint, session = endpoint_session
    frames = Collector(session, keys.camera_frame(robot, "cam0"), "frame")
    markers = Collector(session, keys.detector_markers(robot, "d1"), "detections")
    child = detectors(*detector_args(endpoint, robot, "d1", "--config-json", DAY_JSON))
    child.wait_ready()
    camera = CameraPart(CameraSettings(robot=robot, fps=30), SyntheticSource(IlluminationProfile.constant(120)))
    truth_by_seq: dict[int, list] = {}
    checked = 0
    try:
        camera.setup(session)
        deadline = time.monotonic() + 20
        while checked < 8 and time.monotonic() < deadline:
            while not frames.items.empty():
                f = frames.next()
                truth_by_seq[f["seq"]] = f["truth"]
            d = markers.next(timeout=5)
            while not frames.items.empty():
                f = frames.next()
                truth_by_seq[f["seq"]] = f["truth"]
            truth = truth_by_seq.get(d["seq"])
            if truth is None:
                continue
            result = score(d["ids"], d["corners"], truth, tolerance_px=3.0)
            assert result.hits == 6 and result.false == 0, d
            assert max(result.corner_error_px) < 1.5
            assert d["instance"] == "d1" and d["config"] == "inline" and d["host"] == "onboard"
            assert d["frame_time"] <= d["received"] <= d["time"] and d["processing_ms"] > 0
            checked += 1
    finally:
        camera.shutdown()
        frames.close()
        markers.close()
    assert checked == 8


def test_a_burst_of_frames_is_dropped_not_queued_and_memory_stays_bounded(endpoint_session, robot, detectors):
    endpoint, session = endpoint_session
    markers = Collector(session, keys.detector_markers(robot, "burst"), "detections")
    child = detectors(*detector_args(endpoint, robot, "burst", "--config-json", DAY_JSON))
    child.wait_ready()
    scene = SyntheticScene()
    frame = scene.render(0.0, IlluminationProfile.constant(120), np.random.default_rng(0))
    key = keys.camera_frame(robot, "cam0")
    try:
        put_until(session, key, lambda seq: frame_payload(seq, frame.image), markers, lambda d: len(d["ids"]) == 6)
        for seq in range(100, 121):  # settle OpenCV's buffers before measuring; none may be dropped on the way
            session.put(key, frame_payload(seq, frame.image), congestion_control=zenoh.CongestionControl.BLOCK)
        # The newest frame is always processed: once 120 is done, the warm-up has drained.
        markers.wait_for(lambda d: d["seq"] == 120, timeout=10, what="the warm-up's last frame")
        process = psutil.Process(child.process.pid)
        before = process.memory_info().rss
        # 900 frames (about 27 MiB): queued they would hold all of it, well apart from Zenoh's own
        # receive buffers (up to 5.3 MiB seen with shared memory off, whatever the burst's size).
        payloads = [frame_payload(1000 + i, frame.image) for i in range(900)]
        start = time.monotonic()
        for payload in payloads[:-1]:  # as fast as Zenoh takes them (it may drop some itself when congested)
            session.put(key, payload)
        # The last one must reach the detector: without shared memory a loaded machine's transport
        # drops congested puts, and the point here is what the detector does with what it gets.
        session.put(key, payloads[-1], congestion_control=zenoh.CongestionControl.BLOCK)
        burst_s = time.monotonic() - start
        last = markers.wait_for(lambda d: d["seq"] == 1899, timeout=30, what="the burst's last frame")
        after = process.memory_info().rss
    finally:
        markers.close()
    assert last["dropped"] > 0, "the detector processed every frame of the burst: it queued instead of dropping"
    burst_mib = sum(len(p) for p in payloads) / 2**20
    growth_mib = (after - before) / 2**20
    # Queuing the burst would hold at least its payloads; the slot holds one frame, plus Zenoh's buffers.
    assert growth_mib < burst_mib / 3, (
        f"RSS grew by {growth_mib:.1f} MiB over a {burst_s * 1e3:.0f} ms burst of {burst_mib:.1f} MiB")
    assert child.process.poll() is None


def test_a_malformed_frame_is_dropped_with_a_log_line_and_the_detector_goes_on(endpoint_session, robot, detectors):
    endpoint, session = endpoint_session
    markers = Collector(session, keys.detector_markers(robot, "tough"), "detections")
    child = detectors(*detector_args(endpoint, robot, "tough", "--config-json", DAY_JSON))
    child.wait_ready()
    scene = SyntheticScene()
    image = scene.render(0.0, IlluminationProfile.constant(120), np.random.default_rng(0)).image
    key = keys.camera_frame(robot, "cam0")
    try:
        put_until(session, key, lambda seq: frame_payload(seq, image), markers, lambda d: True)
        bad = [
            b"\xc1 not msgpack",
            messages.encode("illumination", {"camera": "cam0", "seq": 1, "time": 1.0, "mean": 1,
                                             "p5": 1, "p50": 1, "p95": 1, "smoothed": 1}),
            messages.encode("frame", {"camera": "cam0", "seq": 7, "time": 1.0, "width": 4, "height": 4,
                                      "jpeg": b"not a jpeg"}),
        ]
        for n, payload in enumerate(bad, start=1):
            session.put(key, payload)  # one at a time, so none replaces another in the slot
            wait_for(lambda: child.stderr().count("dropped a frame") >= n, 10, f"drop number {n}")
        after = put_until(session, key, lambda seq: frame_payload(5000 + seq, image), markers,
                          lambda d: d["seq"] > 5000)
    finally:
        markers.close()
    assert len(after["ids"]) == 6
    assert child.process.poll() is None
    log = child.stderr()
    assert "not valid msgpack" in log and "expected a frame message" in log and "JPEG does not decode" in log


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_detector_cleanly(endpoint_session, robot, detectors, sig):
    endpoint, _ = endpoint_session
    child = detectors(*detector_args(endpoint, robot, "quit", "--config-json", DAY_JSON))
    child.wait_ready()
    start = time.monotonic()
    assert child.stop(sig) == 0
    assert time.monotonic() - start < 5


def test_a_bad_inline_configuration_exits_1_naming_the_parameter(endpoint_session, robot, detectors):
    endpoint, _ = endpoint_session
    child = detectors(*detector_args(endpoint, robot, "bad", "--config-json", '{"parameters": {"nosuch": 1}}'))
    assert child.wait(20) == 1
    assert "'nosuch'" in child.stderr()


def test_config_and_config_json_cannot_both_be_given(endpoint_session, robot, detectors):
    endpoint, _ = endpoint_session
    child = detectors(*detector_args(endpoint, robot, "both", "--config", "x", "--config-json", "{}"))
    assert child.wait(20) != 0
    assert "not allowed with argument" in child.stderr()


@pytest.fixture
def knowledge(resp_store, endpoint_session, robot):
    """The shipped models behind a real knowledge service on the test's session."""
    if not HAVE_SERVICE:
        pytest.skip("knowledge/service.py is not there yet")
    from kgadapt.knowledge.loader import load_models
    from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
    from kgadapt.shared.resources import models

    load_models(resp_store, [models()])
    service = KnowledgeService(resp_store, ServiceSettings(robot=robot))
    service.setup(endpoint_session[1])
    yield service
    service.shutdown()


def test_an_unknown_configuration_exits_2_naming_it(knowledge, endpoint_session, robot, detectors):
    endpoint, _ = endpoint_session
    child = detectors(*detector_args(endpoint, robot, "ghost", "--config", "marker_detection_moonlight"))
    assert child.wait(30) == 2
    assert "'marker_detection_moonlight' is not in the knowledge store" in child.stderr()


def test_a_configuration_from_the_store_detects_markers(knowledge, endpoint_session, robot, detectors):
    endpoint, session = endpoint_session
    markers = Collector(session, keys.detector_markers(robot, "store"), "detections")
    child = detectors(*detector_args(endpoint, robot, "store", "--config", "marker_detection_dark"))
    child.wait_ready()
    image = SyntheticScene().render(0.0, IlluminationProfile.constant(6), np.random.default_rng(0)).image
    try:
        found = put_until(session, keys.camera_frame(robot, "cam0"), lambda seq: frame_payload(seq, image), markers,
                          lambda d: True)
    finally:
        markers.close()
    assert found["config"] == "marker_detection_dark"
    assert len(found["ids"]) >= 5  # level 6 is dark: the dark configuration still finds (nearly) all six
