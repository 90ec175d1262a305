"""The camera part: frames with ground truth and illumination over Zenoh; sources; bounded queues."""

from __future__ import annotations

import queue

import cv2
import numpy as np
import pytest

from kgadapt.onboard.perception.camera import (
    CameraPart,
    CameraSettings,
    CapturedFrame,
    OpenCVSource,
    SyntheticSource,
    make_source,
)
from kgadapt.onboard.perception.scene import IlluminationProfile
from kgadapt.shared import keys
from kgadapt.shared.errors import ConfigError, ModelError
from tests.perception.conftest import Collector


def test_the_camera_publishes_jpeg_frames_with_truth_and_matching_illumination(endpoint_session, robot):
    _, session = endpoint_session
    frames = Collector(session, keys.camera_frame(robot, "cam0"), "frame")
    light = Collector(session, keys.camera_illumination(robot, "cam0"), "illumination")
    part = CameraPart(CameraSettings(robot=robot, fps=60, jpeg_quality=70),
                      SyntheticSource(IlluminationProfile.constant(90.0)))
    try:
        part.setup(session)
        first = frames.next()
        later = frames.next()
        reading = light.wait_for(lambda m: m["seq"] == later["seq"])
    finally:
        part.shutdown()
        frames.close()
        light.close()
    assert later["seq"] > first["seq"] and later["time"] >= first["time"]
    image = cv2.imdecode(np.frombuffer(later["jpeg"], np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (480, 640) == (later["height"], later["width"])
    assert sorted(t["id"] for t in later["truth"]) == [3, 7, 12, 21, 33, 42]
    assert later["level"] == 90.0
    assert reading["mean"] == pytest.approx(90, rel=0.08)
    assert reading["p5"] <= reading["p50"] <= reading["p95"]
    assert reading["smoothed"] == pytest.approx(90, rel=0.1)


def test_each_frame_is_out_before_its_light_is_reckoned(endpoint_session, robot, monkeypatch):
    # Every detection waits for the frame; only the illumination message needs the light figures.
    import threading

    from kgadapt.onboard.perception import camera

    _, session = endpoint_session
    published = threading.Condition()
    count = [0]

    def on_frame(_sample) -> None:
        with published:
            count[0] += 1
            published.notify_all()

    subscriber = session.declare_subscriber(keys.camera_frame(robot, "cam0"), on_frame)
    reckoned: list[bool] = []  # per light estimate: was its frame (the camera's k-th) out already?
    real = camera.estimate_light

    def estimate_light(*args, **kwargs):
        k = len(reckoned) + 1
        with published:
            reckoned.append(published.wait_for(lambda: count[0] >= k, timeout=2.0))
        return real(*args, **kwargs)

    monkeypatch.setattr(camera, "estimate_light", estimate_light)
    part = CameraPart(CameraSettings(robot=robot, fps=60), SyntheticSource(IlluminationProfile.constant(90.0)))
    heard: queue.Queue = queue.Queue()
    part.add_listener(heard.put)
    try:
        part.setup(session)
        for _ in range(3):
            heard.get(timeout=10)
    finally:
        part.shutdown()
        subscriber.undeclare()
    assert reckoned[:3] == [True, True, True], "the light was reckoned before its frame went out"


def test_the_queue_between_capture_and_publish_keeps_only_the_newest_frames():
    part = CameraPart(CameraSettings(robot="r", queue_size=2), SyntheticSource(IlluminationProfile.constant(50)))
    blank = np.zeros((4, 4), np.uint8)
    for seq in range(1, 101):  # a publisher that never catches up
        part._offer((seq, CapturedFrame(blank, float(seq))))
    kept = []
    while True:
        try:
            kept.append(part._queue.get_nowait()[0])
        except queue.Empty:
            break
    assert kept == [99, 100]
    assert part.stats.dropped_queue == 98


def test_listeners_hear_every_illumination_reading_off_the_zenoh_threads(endpoint_session, robot):
    _, session = endpoint_session
    heard: queue.Queue = queue.Queue()
    part = CameraPart(CameraSettings(robot=robot, fps=50), SyntheticSource(IlluminationProfile.constant(20.0)))
    part.add_listener(heard.put)
    try:
        part.setup(session)
        readings = [heard.get(timeout=5) for _ in range(3)]
    finally:
        part.shutdown()
    assert [r.seq for r in readings] == sorted(r.seq for r in readings)
    assert all(r.figures.mean == pytest.approx(20, rel=0.1) for r in readings)


def test_a_video_file_is_published_resized_to_the_configured_size(endpoint_session, robot, tmp_path):
    _, session = endpoint_session
    video = tmp_path / "hall.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (320, 240), True)
    for i in range(5):
        writer.write(np.full((240, 320, 3), 40 * i, np.uint8))
    writer.release()
    frames = Collector(session, keys.camera_frame(robot, "file"), "frame")
    part = CameraPart(CameraSettings(robot=robot, camera="file", fps=100, width=160, height=120),
                      make_source(f"file:{video}"))
    try:
        part.setup(session)
        got = [frames.next() for _ in range(8)]  # more than the file has: it loops
    finally:
        part.shutdown()
        frames.close()
    assert all((m["width"], m["height"]) == (160, 120) and "truth" not in m for m in got)
    image = cv2.imdecode(np.frombuffer(got[-1]["jpeg"], np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image.shape == (120, 160)


def test_sources_are_chosen_by_spec_and_bad_ones_are_named(tmp_path):
    assert isinstance(make_source("synthetic"), SyntheticSource)
    assert isinstance(make_source("device:2"), OpenCVSource) and make_source("3").target == 3
    missing = make_source(f"file:{tmp_path}/none.mp4")
    with pytest.raises(ConfigError, match="none.mp4 does not exist"):
        missing.open()
    with pytest.raises(ConfigError, match="device:N needs a device number"):
        make_source("device:front")


@pytest.mark.parametrize(
    "kwargs, words",
    [({"fps": 0}, "camera rate"), ({"jpeg_quality": 101}, "JPEG quality"), ({"camera": "a/b"}, "camera name"),
     ({"width": 8}, "resolution")],
)
def test_bad_camera_settings_are_refused_by_name(kwargs, words):
    with pytest.raises(ConfigError, match=words):
        CameraSettings(robot="r", **kwargs)


def test_the_synthetic_source_replays_the_demo_profile_on_its_clock_with_truth():
    now = [1000.0]
    source = SyntheticSource(speed=2.0, clock=lambda: now[0])
    source.open()
    try:
        levels, seen = [], []
        for wall in (0.0, 9.0, 15.0, 22.0):  # scenario times 0, 18, 30, 44 s
            now[0] = 1000.0 + wall
            frame = source.read()
            assert frame.time == now[0]
            levels.append(frame.level)
            seen.append(len(frame.truth))
    finally:
        source.close()
    assert levels == [120.0, 16.0, 5.0, 60.0]  # day, dusk, dark, flicker (base level)
    assert seen == [6, 6, 4, 6]  # at 30 s the window (29-34 s) hides the two top markers it covers


def test_a_missing_profile_is_named_when_the_source_opens(tmp_path):
    source = make_source(f"synthetic:{tmp_path}/gone.json")  # nothing read yet
    with pytest.raises(ModelError, match="gone.json"):
        source.open()


def test_a_window_lifts_the_published_mean_but_not_the_level_bands_are_read_from(endpoint_session, robot):
    from kgadapt.onboard.perception.scene import LightLayout
    from kgadapt.shared import messages

    _, session = endpoint_session
    light = Collector(session, keys.camera_illumination(robot, "cam0"), "illumination")
    part = CameraPart(CameraSettings(robot=robot, fps=60),
                      SyntheticSource(IlluminationProfile.constant(6.0, light=LightLayout(window=0.15))))
    publisher = session.declare_publisher(keys.detector_markers(robot, "det1"))
    try:
        part.setup(session)
        first = light.next()
        assert first["mean"] > 40 and first["level"] < 12 and first["smoothed"] < 12
        assert first["saturated"] == pytest.approx(0.15, abs=0.01) and first["source"] == "frame"
        # A detector reports a marker: the estimate weighs the light around it from then on.
        now = first["time"]  # the frame it was seen in: within marker_memory_s of the next frames
        publisher.put(messages.encode("detections", {
            "instance": "det1", "config": "c", "host": "h", "seq": 1, "frame_time": now, "time": now,
            "ids": [33], "corners": [[[340, 280], [420, 280], [420, 360], [340, 360]]], "processing_ms": 1.0}))
        weighed = light.wait_for(lambda m: m.get("source") == "markers")
    finally:
        part.shutdown()
        publisher.undeclare()
        light.close()
    assert weighed["markers"] == 1 and weighed["marker_level"] is not None and weighed["level"] < 12
