"""FlightBridge over two real Zenoh sessions on loopback and the fake autopilot over UDP."""

from __future__ import annotations

import threading
import time

import pytest

from kgadapt.onboard.flight.flight import BridgeSettings, CameraIntrinsics, FlightBridge
from kgadapt.onboard.flight.landing_targets import CameraModel
from kgadapt.onboard.flight.mavlink import LINK_LOST, LINK_RESTORED, LinkSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.conftest import free_port
from tests.flight.conftest import FAST_STREAMS, free_udp_port, wait_until
from tests.flight.test_landing_target import ANGLE_X, ANGLE_Y, SQUARE, K

ROBOT = "quadtest"


@pytest.fixture
def sessions():
    """(bridge side, detector/observer side): two peers, one listening, one connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    b = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    try:
        wait_until(lambda: list(a.info.peers_zid()) and list(b.info.peers_zid()), 5, "the peers to connect")
        yield a, b
    finally:
        b.close()
        a.close()


@pytest.fixture
def rig(sessions):
    """Start ``rig(**bridge_settings)`` -> (bridge, fc, observer session); everything stopped after."""
    parts: list = []

    def _start(*, vehicle: VehicleState = VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR"),
               on_state=None, heartbeat_timeout_s: float = 0.5, **overrides):
        port = free_udp_port()
        settings = BridgeSettings(
            robot=ROBOT, intrinsics=K,
            link=LinkSettings(url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=heartbeat_timeout_s,
                              stream_rates=FAST_STREAMS),
            **overrides,
        )
        bridge = FlightBridge(settings, on_state=on_state)
        bridge.setup(sessions[0])
        parts.append(bridge)
        fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=10, sys_status_hz=10,
                                                 battery_hz=10, extended_state_hz=10), vehicle)
        fc.setup()
        parts.append(fc)
        bridge.link.wait_for_heartbeat(5)
        return bridge, fc, sessions[1]

    yield _start
    for part in reversed(parts):
        part.shutdown()


class Inbox:
    """Collects decoded flight_state messages from a subscriber (handler only appends)."""

    def __init__(self, session) -> None:
        self.items: list[tuple[float, dict]] = []
        self.errors: list[str] = []
        self._sub = session.declare_subscriber(keys.flight_state(ROBOT), self._on_sample)

    def _on_sample(self, sample) -> None:
        try:
            self.items.append((time.monotonic(), messages.decode(sample.payload.to_bytes(), "flight_state")))
        except Exception as exc:
            self.errors.append(str(exc))

    def find(self, **fields):
        return next((m for _, m in reversed(self.items) if all(m.get(k) == v for k, v in fields.items())), None)

    def close(self) -> None:
        self._sub.undeclare()


def _detections(seq: int, corners=SQUARE, ids=(7,), frame_time: float | None = None, **extra) -> bytes:
    now = time.time()
    return messages.encode("detections", {
        "instance": "det1", "config": "marker_detection_day", "host": "onboard", "seq": seq,
        "frame_time": now if frame_time is None else frame_time, "time": now,
        "ids": list(ids), "corners": [corners] * len(ids), "processing_ms": 4.0, **extra,
    })


def _publish_until_received(session, fc, *, count: int = 1, timeout: float = 5.0) -> int:
    """Publish fresh detections at 10 Hz until the autopilot has ``count`` targets (the route needs a moment)."""
    publisher = session.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    seq = 0
    try:
        deadline = time.monotonic() + timeout
        while len(fc.received("LANDING_TARGET")) < count:
            assert time.monotonic() < deadline, "no LANDING_TARGET reached the autopilot"
            publisher.put(_detections(seq))
            seq += 1
            time.sleep(0.1)
    finally:
        publisher.undeclare()
    return seq


def test_bridge_publishes_the_flight_state_over_zenoh_about_five_times_a_second(rig):
    bridge, fc, observer = rig(vehicle=VehicleState(armed=True, mode="GUIDED", landed_state="IN_AIR",
                                                   battery_pct=64.0, load_pct=40.0))
    inbox = Inbox(observer)
    try:
        message = wait_until(lambda: inbox.find(landed_state="IN_AIR", battery_pct=64.0, onboard_load=40.0), 5,
                             "a complete flight_state")
        assert message["link"] is True and message["armed"] is True and message["mode"] == "GUIDED"
        assert message["battery_v"] == pytest.approx(fc.battery_v, abs=0.01)
        start, started = len(inbox.items), time.monotonic()
        wait_until(lambda: len(inbox.items) - start >= 5, 10, "five more periodic flight states")
        # Periodic, not a flood: at most 15 a second whatever the machine's load (a late one is no flood).
        assert (len(inbox.items) - start) / (time.monotonic() - started) <= 15
        assert not inbox.errors
    finally:
        inbox.close()


def test_bridge_publishes_a_mode_change_at_once_not_at_the_next_period(rig):
    bridge, fc, observer = rig(state_period_s=120.0)
    inbox = Inbox(observer)
    try:
        wait_until(lambda: bridge.counters["published"] >= 1, 3, "the first publication")
        fc.set(mode="LAND", landed_state="LANDING")
        # The period is 120 s: seen within the wait, the change was published on its own.
        wait_until(lambda: inbox.find(mode="LAND", landed_state="LANDING"), 20, "the change on Zenoh")
    finally:
        inbox.close()


def test_bridge_publishes_link_lost_and_restored_events(rig):
    bridge, fc, observer = rig(heartbeat_timeout_s=0.3)
    inbox = Inbox(observer)
    try:
        wait_until(lambda: bridge.counters["published"] >= 1, 3, "the first publication")
        fc.pause()
        lost = wait_until(lambda: inbox.find(event=LINK_LOST), 3, "link_lost on Zenoh")
        assert lost["link"] is False
        fc.resume()
        back = wait_until(lambda: inbox.find(event=LINK_RESTORED), 3, "link_restored on Zenoh")
        assert back["link"] is True
    finally:
        inbox.close()


def test_bridge_turns_detections_into_landing_targets_with_the_hand_computed_angles_at_the_detection_rate(rig):
    bridge, fc, observer = rig()
    _publish_until_received(observer, fc)
    publisher = observer.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    fc.clear_received()
    try:
        started = time.monotonic()
        for seq in range(15):  # 1.5 s at 10 Hz
            publisher.put(_detections(100 + seq))
            time.sleep(0.1)
        elapsed = time.monotonic() - started
    finally:
        publisher.undeclare()
    targets = fc.wait_for("LANDING_TARGET", 12, timeout=2)
    rate = len(targets) / elapsed
    assert rate >= 1.0 and len(targets) >= 12, (len(targets), elapsed)
    f = targets[-1].fields
    assert f["angle_x"] == pytest.approx(ANGLE_X, abs=1e-6)  # float32 on the wire
    assert f["angle_y"] == pytest.approx(ANGLE_Y, abs=1e-6)
    assert f["target_num"] == 7 and f["position_valid"] == 0 and f["frame"] == 12
    assert targets[-1].mavlink2


def test_a_pose_in_the_detections_is_sent_as_a_valid_position(rig):
    bridge, fc, observer = rig()
    _publish_until_received(observer, fc)
    fc.clear_received()
    publisher = observer.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    try:
        publisher.put(_detections(500, poses=[{"tvec": [0.3, 0.2, 4.0]}]))
        f = fc.wait_for("LANDING_TARGET", 1, timeout=2)[0].fields
    finally:
        publisher.undeclare()
    assert f["position_valid"] == 1
    assert (f["x"], f["y"], f["z"]) == pytest.approx((-0.2, 0.3, 4.0), abs=1e-6)


def test_a_pose_in_the_detections_goes_through_the_cameras_mounting(rig):
    # The camera turned 90° clockwise (the top of the image to the right) and 5 cm forward, 2 cm down of
    # the body's origin: the detector's pose in the optical frame is moved and turned like a solved one.
    camera = CameraModel(fx=K.fx, fy=K.fy, cx=K.cx, cy=K.cy, yaw_deg=90.0, offset_m=(0.05, 0.0, 0.02))
    bridge, fc, observer = rig(camera=camera)
    _publish_until_received(observer, fc)
    fc.clear_received()
    publisher = observer.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    try:
        publisher.put(_detections(500, poses=[[0.3, 0.2, 4.0]]))
        f = fc.wait_for("LANDING_TARGET", 1, timeout=2)[0].fields
    finally:
        publisher.undeclare()
    assert f["position_valid"] == 1
    # forward -y = -0.2, right x = 0.3, turned 90°: forward -0.3, right -0.2; plus the offset
    assert (f["x"], f["y"], f["z"]) == pytest.approx((-0.25, -0.2, 4.02), abs=1e-6)


def test_malformed_stale_duplicate_and_empty_detections_send_nothing_and_the_bridge_carries_on(rig):
    bridge, fc, observer = rig()
    _publish_until_received(observer, fc)
    fc.clear_received()
    publisher = observer.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    try:
        before = dict(bridge.counters)
        publisher.put(b"\x93not msgpack at all")
        publisher.put(messages.encode("illumination", {"camera": "c", "seq": 1, "time": 1.0, "mean": 1, "p5": 1,
                                                       "p50": 1, "p95": 1, "smoothed": 1}))
        publisher.put(_detections(600, corners=[[1, 2], [3, 4]]))
        publisher.put(_detections(601, frame_time=time.time() - 10))  # seen 10 s ago
        publisher.put(_detections(602, ids=()))  # nothing seen
        frame_time = time.time()
        publisher.put(_detections(603, frame_time=frame_time))
        publisher.put(_detections(604, frame_time=frame_time))  # the same frame from a second detector
        wait_until(lambda: bridge.counters["detections"] - before["detections"] >= 7, 3, "all seven handled")
        targets = fc.wait_for("LANDING_TARGET", 1, timeout=2)
        time.sleep(0.2)  # give a wrongly sent second target the time to arrive
    finally:
        publisher.undeclare()
    assert len(fc.received("LANDING_TARGET")) == 1 and targets[0].fields["time_usec"] == int(frame_time * 1e6)
    assert bridge.counters["malformed"] - before["malformed"] == 3
    assert bridge.counters["stale"] - before["stale"] == 1
    assert bridge.counters["no_target"] - before["no_target"] == 1
    assert bridge.counters["duplicate"] - before["duplicate"] == 1
    assert bridge._worker is not None and bridge._worker.is_alive()


def test_on_state_runs_with_published_states_and_a_failing_callback_does_not_stop_the_bridge(rig):
    seen: list = []
    called = threading.Event()

    def on_state(state):
        seen.append(state)
        called.set()
        raise RuntimeError("the graph is down")

    bridge, fc, observer = rig(on_state=on_state)
    assert called.wait(3)
    wait_until(lambda: len(seen) >= 3, 3, "several callbacks despite the failures")
    assert seen[-1].mode == "LOITER" and seen[-1].link is True


def test_bridge_settings_with_a_bad_robot_name_are_refused():
    from kgadapt.shared.errors import ConfigError

    with pytest.raises(ConfigError, match="robot"):
        FlightBridge(BridgeSettings(robot="a/b", intrinsics=K, link=LinkSettings(url="udpin:127.0.0.1:1")))


def test_bridge_setup_with_a_bad_url_fails_with_flight_link_error_naming_it():
    from kgadapt.shared.errors import FlightLinkError

    with pytest.raises(FlightLinkError, match="udpin:nowhere"):
        FlightBridge(BridgeSettings(robot=ROBOT, intrinsics=CameraIntrinsics(fx=1, fy=1, cx=0, cy=0),
                                    link=LinkSettings(url="udpin:nowhere")))


def test_landing_targets_are_capped_at_max_target_hz_when_detections_come_faster(rig):
    bridge, fc, observer = rig(max_target_hz=5.0)
    _publish_until_received(observer, fc)
    publisher = observer.declare_publisher(keys.detector_markers(ROBOT, "det1"))
    fc.clear_received()
    before = bridge.counters["detections"]
    try:
        started = time.monotonic()
        for seq in range(60):  # about 100 Hz
            publisher.put(_detections(700 + seq))
            time.sleep(0.01)
        wait_until(lambda: bridge.counters["detections"] - before >= 60, 3, "all detections handled")
        elapsed = time.monotonic() - started
    finally:
        publisher.undeclare()
    sent = len(fc.received("LANDING_TARGET"))
    assert 1 <= sent <= 5.0 * elapsed + 2, (sent, elapsed)
    assert bridge.counters["rate_limited"] > 0
