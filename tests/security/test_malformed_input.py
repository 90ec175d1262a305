"""Subscribers fed malformed msgpack (hypothesis) drop it and keep working.

Covered elsewhere and not repeated here: the knowledge queryables, the
service's status and liveliness subscribers and the squeeze queryable
(tests/zenoh/test_malformed.py), the deployer's queryables (tests/deploy).
Here: the detector program's frame subscriber (a real detector process),
the flight bridge's detections subscriber (with the fake autopilot over
MAVLink), and the adaptation manager's subscribers in a running onboard agent
with ``--adapt`` (illumination, host status, flight state, detections),
which must still adapt afterwards.

Each garbage payload is sent only after the previous one was handled (a drop
logged or counted), so none is skipped as stale and every one is exercised.
"""

from __future__ import annotations

import json
import re
import signal
import socket
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from kgadapt.onboard.flight.flight import BridgeSettings, CameraIntrinsics, FlightBridge, choose_marker, landing_target
from kgadapt.onboard.flight.mavlink import LinkSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.conftest import free_port
from tests.security.conftest import wait_for
from tests.security.fuzz import FUZZ, malformed, packed, wire
from tests.support import Child

DAY_JSON = '{"dictionary": "DICT_4X4_50", "preprocess": [], "parameters": {}}'


def jpeg(width: int = 64, height: int = 48) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((height, width), 128, np.uint8))
    assert ok
    return data.tobytes()


def good_frame(seq: int) -> dict:
    return {"camera": "cam0", "seq": seq, "time": time.time(), "width": 64, "height": 48, "jpeg": jpeg()}


def count_lines(path: Path, pattern: str) -> int:
    try:
        return len(re.findall(pattern, path.read_text(errors="replace")))
    except OSError:
        return 0


# -- the detector program ---------------------------------------------------------------------------------


@pytest.fixture
def detector(tmp_path):
    """A real ``python -m kgadapt.onboard.perception.detector`` (inline configuration), connected to a listening peer session."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    child = Child([sys.executable, "-m", "kgadapt.onboard.perception.detector", "--robot", "fuzzbot", "--host", "onboard",
                   "--instance", "fz", "--connect", endpoint, "--config-json", DAY_JSON], "detector", tmp_path)
    try:
        child.wait_ready(30.0)  # raises with its stderr when it is not
        yield child.process, session, child.stderr_path
    finally:
        child.stop(20.0, first=signal.SIGTERM)
        session.close()


def test_a_detector_process_fed_garbage_frames_drops_each_and_keeps_answering_good_frames(detector):
    process, session, stderr = detector
    answers: list[dict] = []
    sub = session.declare_subscriber(keys.detector_markers("fuzzbot", "fz"),
                                     lambda s: answers.append(messages.decode(s.payload.to_bytes(), "detections")))
    frame_key = keys.camera_frame("fuzzbot", "cam0")

    def put(payload: bytes) -> None:
        # BLOCK: with Zenoh's default (drop) a large frame put on a loaded machine may never leave,
        # and the wait below for the detector to handle it times out (seen with a 1 MB drawn payload).
        session.put(frame_key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    try:
        # The detector's subscription takes a moment to reach this session: send until one is answered.
        wait_for(lambda: (put(messages.encode("frame", good_frame(1))), answers)[1], 10,
                 "the first good frame to be answered")
        dropped = "dropped a frame"
        garbage = st.one_of(
            malformed("frame", good_frame(2)),
            st.binary(min_size=1, max_size=400).map(lambda b: packed(wire("frame", {**good_frame(3), "jpeg": b}))),
            st.integers(1, len(jpeg()) - 1).map(lambda n: packed(wire("frame", {**good_frame(4), "jpeg": jpeg()[:n]}))),
        )

        def answered() -> int:  # answers to the drawn frames whose JPEG may still decode (seq 3 and 4)
            return sum(a["seq"] in (3, 4) for a in answers)

        @FUZZ
        @given(payload=garbage)
        def feed(payload: bytes) -> None:
            drops, before = count_lines(stderr, dropped), answered()
            put(payload)
            # Handled: dropped with a reason, or (a cut JPEG that still decodes) answered like any frame.
            wait_for(lambda: count_lines(stderr, dropped) > drops or answered() > before, 10,
                     f"the detector to handle {payload[:40]!r}")

        feed()
        seq = 10_000
        put(messages.encode("frame", good_frame(seq)))
        wait_for(lambda: any(a["seq"] == seq for a in answers), 10, "the good frame after the garbage to be answered")
    finally:
        sub.undeclare()
    assert process.poll() is None
    log = stderr.read_text(errors="replace")
    assert count_lines(stderr, dropped) >= 30
    assert "Traceback" not in log  # every bad frame was a clean drop, not an exception caught as a last resort


# -- the flight bridge ------------------------------------------------------------------------------------

K = CameraIntrinsics(fx=600.0, fy=500.0, cx=320.0, cy=240.0)
SQUARE = [[380.0, 280.0], [420.0, 280.0], [420.0, 320.0], [380.0, 320.0]]
OUTCOMES = ("malformed", "no_target", "stale", "duplicate", "rate_limited", "targets_sent", "send_failed",
            "unconfirmed")  # unconfirmed: candidates not (yet) steady, onboard/flight/confirmation.py


def good_detections(seq: int, **changes) -> dict:
    now = time.time()
    return {"instance": "det1", "config": "marker_detection_day", "host": "onboard", "seq": seq, "frame_time": now,
            "time": now, "ids": [7], "corners": [SQUARE], "processing_ms": 4.0, **changes}


@pytest.fixture
def bridge():
    """A FlightBridge on one peer session, the fake autopilot over UDP, and a second peer to publish from."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    b = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    part = FlightBridge(BridgeSettings(robot="fuzzbot", intrinsics=K, link=LinkSettings(
        url=f"udpin:127.0.0.1:{port}", heartbeat_timeout_s=1.0)))
    part.setup(a)
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=10),
                              VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR"))
    fc.setup()
    try:
        part.link.wait_for_heartbeat(5)
        yield part, fc, b
    finally:
        fc.shutdown()
        part.shutdown()
        b.close()
        a.close()


def send_until_a_target_arrives(session, fc, key: str, seq: int, timeout: float = 10.0) -> None:
    before = len(fc.received("LANDING_TARGET"))
    wait_for(lambda: (session.put(key, messages.encode("detections", good_detections(seq))),
                      len(fc.received("LANDING_TARGET")) > before)[1], timeout, "a LANDING_TARGET at the autopilot")


def drain(part: FlightBridge, session, key: str) -> None:
    """Return once everything put on ``key`` before was handled: one publisher's samples arrive in order."""
    before = part.counters["no_target"]
    session.put(key, messages.encode("detections", good_detections(0, ids=[], corners=[])))
    wait_for(lambda: part.counters["no_target"] > before, 5, "the bridge to work through what was sent")


def test_the_flight_bridge_fed_garbage_detections_drops_each_and_still_steers_the_autopilot(bridge):
    part, fc, session = bridge
    key = keys.detector_markers("fuzzbot", "det1")
    send_until_a_target_arrives(session, fc, key, 1)
    drain(part, session, key)
    number = st.one_of(st.integers(-(2**31), 2**31), st.floats(allow_nan=False, allow_infinity=False, width=32))
    shapeless = st.recursive(st.one_of(number, st.text(max_size=3), st.none()), lambda inner: st.lists(inner, max_size=5),
                             max_leaves=12)
    garbage = st.one_of(
        malformed("detections", good_detections(2)),
        # Valid messages whose ids and corners make no marker: refused past the schema.
        st.tuples(st.lists(shapeless, min_size=1, max_size=3), st.lists(shapeless, max_size=3)).map(
            lambda pair: packed(wire("detections", good_detections(3, ids=pair[0], corners=pair[1])))),
    )
    unexpected = []

    def settled() -> int:  # every way a detections message can end is counted, except an exception
        return sum(part.counters[c] for c in OUTCOMES)

    @FUZZ
    @given(payload=garbage)
    def feed(payload: bytes) -> None:
        before = settled()
        dropped = part.counters["malformed"] + part.counters["no_target"] + part.counters["unconfirmed"]
        session.put(key, payload)
        wait_for(lambda: settled() > before, 5, f"the bridge to handle {payload[:40]!r} (an exception counts nothing)")
        if part.counters["malformed"] + part.counters["no_target"] + part.counters["unconfirmed"] == dropped:
            unexpected.append(payload)  # handled, but not dropped: it made a target

    feed()
    send_until_a_target_arrives(session, fc, key, 10_000)
    assert part._worker is not None and part._worker.is_alive()
    targets_from_garbage = [p for p in unexpected if _makes_a_marker(p)]
    assert [p for p in unexpected if p not in targets_from_garbage] == []


def _makes_a_marker(payload: bytes) -> bool:
    """A drawn message that happens to be a valid detection (four numeric corners): a target is right."""
    try:
        body = messages.decode_as(payload, messages.Detections)
        index = choose_marker(body, None)
        return index is not None and landing_target(body.corners[index], K, frame_time=body.frame_time) is not None
    except Exception:
        return False


def test_a_detection_stamped_in_the_future_does_not_silence_the_landing_targets(bridge):
    part, fc, session = bridge
    key = keys.detector_markers("fuzzbot", "det1")
    # The route is up once a bad message is counted; no target sent yet, so the rate limit has room.
    wait_for(lambda: (session.put(key, b"\xc1"), part.counters["malformed"])[1], 10, "the bridge to hear us")
    session.put(key, messages.encode("detections", good_detections(2, frame_time=time.time() + 3600)))
    wait_for(lambda: part.counters.get("future"), 5, "the future-stamped detection to be refused")
    assert part.counters["targets_sent"] == 0  # a clock an hour ahead is not taken at its word
    send_until_a_target_arrives(session, fc, key, 3, timeout=3.0)


# -- the adaptation manager in a running onboard agent ------------------------------------------------------


def test_an_onboard_agent_with_adapt_fed_garbage_on_every_subscription_still_adapts(tmp_path):
    from kgadapt.operator.cluster import ClusterSettings, LocalCluster
    from kgadapt.operator.timeline import Recorder
    from kgadapt.shared.hostmonitor import squeeze

    profile = tmp_path / "dark.json"
    profile.write_text(json.dumps({"points": [[0, 5], [600, 5]], "noise": 2.0, "gradient": 0.2, "loop": False}))
    cluster = LocalCluster(ClusterSettings(workdir=tmp_path / "run", profile=str(profile), calibrate=False,
                                           log_level="INFO", fps=15.0))
    cluster.prepare_store()
    recorder = Recorder(robot="quad1", t0=time.time())
    cluster.start()
    session = None
    try:
        session = open_session(ZenohSettings(mode="peer", connect=(cluster.endpoint,)))
        recorder.setup(session)

        def decision(kind: str):
            return lambda: next((d for d in recorder.decisions if d.kind == kind), None)

        first = wait_for(decision("startup"), 30, "the first detector")
        assert (first.config, first.host) == ("marker_detection_dark", "onboard")
        now = time.time()
        targets = {
            "illumination": (keys.camera_illumination("quad1", "cam0"), {
                "camera": "cam0", "seq": 1, "time": now, "mean": 5.0, "p5": 1.0, "p50": 5.0, "p95": 9.0,
                "smoothed": 5.0}),
            "host_status": (keys.host_status("quad1", "onboard"), {
                "host": "onboard", "time": now, "memory_total_mb": 700.0, "memory_free_mb": 500.0, "cpu_load": 10.0}),
            "flight_state": (keys.flight_state("quad1"), {"time": now, "link": True}),
            "detections": (keys.detector_markers("quad1", "fuzz"), good_detections(1)),
        }
        onboard_log = cluster.children["onboard"].log_path
        sent = dict.fromkeys(targets, 0)
        # BLOCK: a put that Zenoh's default (DROP) sheds under load is never received, so never dropped.
        publishers = {kind: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                      for kind, (key, _) in targets.items()}

        def drops(kind: str) -> int:
            return count_lines(onboard_log, rf"adaptation: dropped a {kind} message")

        # The manager's subscriptions reach this session a moment after it decided: wait until a drop shows.
        wait_for(lambda: (publishers["flight_state"].put(b"\xc1"), drops("flight_state"))[1], 10,
                 "the adaptation manager to drop a first bad message")
        sent["flight_state"] = drops("flight_state")
        garbage = st.sampled_from(sorted(targets)).flatmap(
            lambda kind: malformed(kind, targets[kind][1]).map(lambda payload: (kind, payload)))

        @FUZZ
        @given(item=garbage)
        def feed(item: tuple[str, bytes]) -> None:
            kind, payload = item
            publishers[kind].put(payload)
            sent[kind] += 1

        feed()
        for kind in targets:
            wait_for(lambda k=kind: drops(k) >= sent[k], 30, f"every bad {kind} message to be dropped")
        assert all(count > 0 for count in sent.values()), sent
        for publisher in publishers.values():
            publisher.undeclare()

        squeeze(session, "quad1", "onboard", 350.0)  # the dark detector no longer fits onboard
        first_short = wait_for(decision("memory_short"), 20, "the squeeze to be acted on")
        if first_short.outcome.startswith("kept"):
            # Known race (reported): the manager plans from the graph, which may not hold the squeezed
            # status yet, and the host monitor sends no further status until something changes.
            squeeze(session, "quad1", "onboard", 360.0)
        moved = wait_for(lambda: next((d for d in recorder.decisions if d.kind == "memory_short"
                                       and d.outcome == "migrated"), None), 20, "the detector to move")
        assert (moved.config, moved.host) == ("marker_detection_dark", "remote")
        assert cluster.children["onboard"].process.poll() is None
        log = onboard_log.read_text(errors="replace")
        assert "adaptation: handling" not in log  # no bad message reached the loop's last-resort handler
    finally:
        recorder.shutdown()
        if session is not None:
            session.close()
        cluster.stop()
