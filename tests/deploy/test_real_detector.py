"""The deployer with the shipped models and the real marker detector (kgadapt.onboard.perception.detector).

Slower than the echo-detector tests (OpenCV loads in each detector), so one
test covers the whole path: start from the models' deployment, detections on
real JPEG frames, migration to the other host with output before the source stops.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.migration import migrate
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.loader import load_models
from kgadapt.shared import keys
from tests.deploy.conftest import ROBOT, Collector, FrameSource

MODELS = Path(S.__file__).resolve().parent / "models"


@pytest.fixture
def graph(resp_store):
    """The shipped models: detector deployments, configurations, platforms."""
    load_models(resp_store, [MODELS])
    return resp_store


def marker_jpeg() -> bytes:
    """A 320x240 grey frame with ArUco marker 7 (DICT_4X4_50) in the middle."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    marker = cv2.aruco.generateImageMarker(dictionary, 7, 100)
    image = np.full((240, 320), 200, np.uint8)
    image[70:170, 110:210] = marker
    ok, jpeg = cv2.imencode(".jpg", image)
    assert ok
    return jpeg.tobytes()


def test_the_shipped_day_detector_starts_detects_and_migrates_without_a_gap_in_output(hosts, client_session):
    frames = FrameSource(client_session, fps=30.0, jpeg=marker_jpeg(), size=(320, 240))
    markers = Collector(client_session, keys.detector_markers(ROBOT, "*"), "detections")
    events = Collector(client_session, keys.deployer_events(ROBOT, "*"), "deploy_event")
    try:
        client = DeployerClient(client_session, ROBOT)
        info = client.start("onboard", "detector_day", "marker_detection_day", instance="day1")
        assert info.argv[1:3] == ["-m", "kgadapt.onboard.perception.detector"]
        _, first = markers.wait_for(lambda d: d["instance"] == "day1" and d["ids"])
        assert first["ids"] == [7] and first["config"] == "marker_detection_day" and first["host"] == "onboard"

        report = migrate(client_session, ROBOT, "day1", "remote", new_instance="day2")

        assert report.first_output_ms <= report.source_stopped_ms
        first_new, _ = markers.wait_for(lambda d: d["instance"] == "day2" and d["host"] == "remote")
        source_exit, ended = events.wait_for(lambda e: e["instance"] == "day1" and e["event"] == "exited")
        assert first_new < source_exit
        assert ended["returncode"] == 0  # the detector stops cleanly on SIGINT
        client.stop("remote", "day2")
    finally:
        events.close()
        markers.close()
        frames.close()
