"""Forged messages on the robot's own keys: only the right source counts.

- Detections from any instance but the one the adaptation manager chose never
  steer the landing (real flight bridge, real fake autopilot over UDP).
- Forged or implausible host statuses never move the detector (the whole
  robot in real processes; the forger publishes as an outsider would).
"""

from __future__ import annotations

import time

import msgpack
import pytest

from kgadapt.onboard.flight.flight import BridgeSettings, FlightBridge
from kgadapt.onboard.flight.mavlink import LinkSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.adaptation.test_adaptation_e2e import Run
from tests.conftest import free_port
from tests.flight.conftest import FAST_STREAMS, free_udp_port, wait_until
from tests.flight.test_landing_target import ANGLE_X, ANGLE_Y, SQUARE, K

ROBOT = "quadforge"
FAR = [[10.0, 10.0], [50.0, 10.0], [50.0, 50.0], [10.0, 50.0]]  # a marker in the corner: very different angles


def _detections(instance: str, seq: int, corners) -> bytes:
    now = time.time()
    return messages.encode("detections", {
        "instance": instance, "config": "marker_detection_day", "host": "onboard", "seq": seq,
        "frame_time": now, "time": now, "ids": [7], "corners": [corners], "processing_ms": 4.0,
    })


def test_only_the_chosen_detector_steers_the_landing(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    b = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    port = free_udp_port()
    chosen = {"instance": "det1"}
    bridge = FlightBridge(
        BridgeSettings(robot=ROBOT, intrinsics=K, link=LinkSettings(url=f"udpin:127.0.0.1:{port}",
                                                                     stream_rates=FAST_STREAMS)),
        chosen_detector=lambda: chosen["instance"],
    )
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=10),
                              VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR"))
    try:
        wait_until(lambda: list(a.info.peers_zid()) and list(b.info.peers_zid()), 5, "the peers to connect")
        bridge.setup(a)
        fc.setup()
        bridge.link.wait_for_heartbeat(5)
        real = b.declare_publisher(keys.detector_markers(ROBOT, "det1"))
        forged = b.declare_publisher(keys.detector_markers(ROBOT, "outsider"))
        seq = 0
        deadline = time.monotonic() + 10
        while len(fc.received("LANDING_TARGET")) < 10 and time.monotonic() < deadline:
            # The forger sends three times as often, on its own key and claiming the real instance's name.
            for _ in range(3):
                forged.put(_detections("outsider", 1000 + seq, FAR))
                forged.put(_detections("det1", 2000 + seq, FAR))
            real.put(_detections("det1", seq, SQUARE))
            seq += 1
            time.sleep(0.05)
        targets = fc.received("LANDING_TARGET")
        assert len(targets) >= 10
        assert all(t.fields["angle_x"] == pytest.approx(ANGLE_X, abs=1e-6)
                   and t.fields["angle_y"] == pytest.approx(ANGLE_Y, abs=1e-6) for t in targets)
        assert bridge.counters["not_chosen"] >= 2 * len(targets)
        # A new choice is followed at once: the old instance no longer steers.
        chosen["instance"] = "det2"
        fc.clear_received()
        for i in range(10):
            real.put(_detections("det1", 5000 + i, SQUARE))
            time.sleep(0.02)
        time.sleep(0.3)
        assert fc.received("LANDING_TARGET") == []
    finally:
        bridge.shutdown()
        fc.shutdown()
        b.close()
        a.close()


def _status(host: str, free: float, total: float = 700.0) -> bytes:
    return msgpack.packb({"kind": "host_status", "v": 1, "host": host, "time": time.time(),
                          "memory_total_mb": total, "memory_free_mb": free, "cpu_load": 5.0, "cpu_cores": 2})


@pytest.mark.slow
def test_forged_and_implausible_statuses_never_move_the_detector(tmp_path):
    with Run(tmp_path, [[0, 5], [120, 5]]) as run:  # dark: the 324 MiB detector, onboard
        first = run.wait_for(run.decision("startup"), 20, "the first detector")
        assert first.host == "onboard"
        forger = open_session(ZenohSettings(mode="peer", connect=(run.cluster.endpoint,)))
        try:
            put = forger.put
            for _ in range(3):
                # Implausible: refused by the service and the manager alike.
                put(keys.host_status("quad1", "ghost"), _status("onboard", -100000.0))  # key and body disagree
                put(keys.host_status("quad1", "onboard"), _status("onboard", 800.0))  # more free than total
                put(keys.host_status("quad1", "onboard"), _status("onboard", -5.0))
                # Plausible but single: "onboard is full", "remote has room"; the real monitors say otherwise.
                put(keys.host_status("quad1", "onboard"), _status("onboard", 0.0))
                put(keys.host_status("quad1", "remote"), _status("remote", 60000.0, total=60000.0))
                put(keys.host_status("quad1", "ghost"), _status("ghost", 60000.0, total=60000.0))  # no liveliness
                time.sleep(1.0)  # each forgery alone, between two real statuses
        finally:
            forger.close()
        time.sleep(1.0)
        assert run.running(time.time() - 1.0) == {("marker_detection_dark", "onboard")}
    assert [d.kind for d in run.recorder.decisions] == ["startup"], run.recorder.decisions


@pytest.mark.slow
def test_a_forged_final_descent_does_not_hold_back_a_band_change(tmp_path):
    # The fake autopilot reports IN_AIR throughout; a forger says LANDING ten times a second. The graph
    # allows no in-place change, so the step into the dark is a planned change (a new process), which the
    # detector's reflex asks for at once.
    from kgadapt.operator.cluster import models_without_in_place

    # A step of 1 µs: with 1 ms, one frame in 33 fell on the ramp, read dusk, and the first reflex was to dusk.
    with Run(tmp_path, [[0, 120], [5, 120], [5.000001, 5], [40, 5]],
             models=models_without_in_place(tmp_path / "models")) as run:
        run.wait_for(run.decision("startup"), 20, "the first detector")
        forger = open_session(ZenohSettings(mode="peer", connect=(run.cluster.endpoint,)))
        stop = time.time() + 12
        try:
            while time.time() < stop and not run.decision("reflex")():
                forger.put(keys.flight_state("quad1"), messages.encode(
                    "flight_state", {"time": time.time(), "link": True, "armed": True, "landed_state": "LANDING"}))
                time.sleep(0.1)
        finally:
            forger.close()
        changed = run.wait_for(run.decision("reflex"), 10, "the change to dark")
    assert changed.outcome.startswith("migrated") and changed.config == "marker_detection_dark", changed
    assert [d.kind for d in run.recorder.decisions] == ["startup", "reflex"]


@pytest.mark.slow
def test_forged_detections_and_a_forged_descent_heard_on_zenoh(tmp_path):
    """No flight bridge in the manager's process (it hears flight states on Zenoh, which the shipped ACL
    lets only the onboard certificate, the bridge's, and operators put). A forger holding such a
    certificate first sends empty detections fifty a second in the running instance's name on another
    instance's key: the manager counts only frames whose key and body name the instance it started, so
    the rate it watches does not collapse. Then it says LANDING twenty times a second while the light
    flaps between dusk and day every 3 s: each kind of change is deferred, and recorded, once. (The graph
    allows no in-place change here, so each flap is a planned change the detector's reflex asks for.)"""
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.operator.cluster import models_without_in_place

    light = [[0, 120], [7, 120], [8, 16], [15, 16], [16, 120], [18, 120], [19, 16], [21, 16], [22, 120],
             [24, 120], [25, 16], [60, 16]]
    with Run(tmp_path, light, fake_fc=False, models=models_without_in_place(tmp_path / "models")) as run:
        started = time.monotonic()  # about when the light profile began
        run.wait_for(run.decision("startup"), 20, "the first detector")
        forger = open_session(ZenohSettings(mode="peer", connect=(run.cluster.endpoint,)))
        try:
            # A promise to compare the rate with (the run is not calibrated), planned at the change to dusk.
            KnowledgeClient(forger, "quad1", timeout=5.0).write("calibration", {
                "config": "marker_detection_dusk", "band": "dusk", "detection_rate": 0.6, "ms_per_frame": 10.0,
                "time": time.time()})
            dusk = run.wait_for(run.decision("reflex"), 20, "the change to dusk")
            assert dusk.config == "marker_detection_dusk", run.recorder.decisions
            run.wait_for(lambda: any(n for t, i, *_, n in run.recorder.detections
                                     if i == dusk.instance and t > dusk.time), 10, "markers found at dusk")
            for seq in range(150):
                forger.put(keys.detector_markers("quad1", "outsider"), messages.encode("detections", {
                    "instance": dusk.instance, "config": dusk.config, "host": dusk.host, "seq": 10**6 + seq,
                    "frame_time": time.time(), "time": time.time(), "ids": [], "corners": [],
                    "processing_ms": 1.0}))
                time.sleep(0.02)
            assert run.running(time.time() - 1.0) == {(dusk.config, dusk.host)}
            assert [d.kind for d in run.recorder.decisions] == ["startup", "reflex"], run.recorder.decisions
            while time.monotonic() < started + 29:  # past the last flap and its dwell
                forger.put(keys.flight_state("quad1"), messages.encode(
                    "flight_state", {"time": time.time(), "link": True, "armed": True, "landed_state": "LANDING"}))
                time.sleep(0.05)
        finally:
            forger.close()
    kinds = [(d.kind, d.outcome) for d in run.recorder.decisions]
    assert "rate_collapsed" not in [k for k, _ in kinds], kinds
    assert [k for k, o in kinds if o.startswith("deferred")] == ["reflex"], kinds  # once, not per change
