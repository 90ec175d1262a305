"""The onboard agent as the README starts it: site and intrinsics from the graph, no site file, no rangefinder.

Real FalkorDB holding the shipped models, the real knowledge service on one Zenoh peer, the agent's
flight part (built from ``kgadapt onboard --fc URL`` exactly as the command builds it) on another,
detections of a site marker over Zenoh, the fake ArduCopter over UDP without a rangefinder.
"""

from __future__ import annotations

import logging
import shutil
import threading

import pytest

from kgadapt.cli import build_parser
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.onboard.cli import FlightPart, build_parts
from kgadapt.onboard.flight.geometry import ned_to_body
from kgadapt.onboard.flight.landing_targets import CameraModel
from kgadapt.onboard.flight.site import ANGLES_ONLY
from kgadapt.operator import status
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from kgadapt.sim.landing_scene import MarkerScene, fake_pose, run_detections
from tests.conftest import REPO, free_port
from tests.flight.conftest import free_udp_port, wait_until

ROBOT = "quadstart"
SHIPPED = REPO / "knowledge" / "models"
MARKER = 7  # demo-hall's pad 7: 0.18 m (knowledge/models/sites/demo.site)


@pytest.fixture
def robot(resp_store, tmp_path):
    """``robot(with_site)`` -> (fc, flight part, agent session, observer); everything stopped after."""
    opened: list = []

    def start(*, with_site: bool):
        models = tmp_path / "models"
        shutil.copytree(SHIPPED, models)
        if not with_site:
            shutil.rmtree(models / "sites")
        load_models(resp_store, [models])
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        server = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
        opened.append(server.close)
        service = KnowledgeService(resp_store, ServiceSettings(robot=ROBOT, mark_offline_at_start=False, workers=1))
        service.setup(server)
        opened.append(service.shutdown)
        agent = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
        opened.append(agent.close)
        port = free_udp_port()
        args = build_parser().parse_args(["onboard", "--robot", ROBOT, "--host", "onboard",
                                          "--fc", f"udpin:127.0.0.1:{port}"])
        flight = next(p for p in build_parts(args) if isinstance(p, FlightPart))
        flight.setup(agent)
        opened.append(flight.shutdown)
        fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=5.0, rangefinder=False,
                                                 drain_pct_per_min=0.0),
                                  VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=6.0, yaw=0.4))
        fc.setup()
        opened.append(fc.shutdown)
        wait_until(lambda: flight.bridge.state.attitude is not None and flight.bridge.state.position_ned is not None,
                   10, "the vehicle's pose")
        return fc, flight, agent

    yield start
    for close in reversed(opened):
        close()


def _fly_over_marker(agent, fc, flight, stop: threading.Event) -> MarkerScene:
    rows = KnowledgeClient(agent, ROBOT, own=True).query("camera_intrinsics", {"camera": "camera"})
    k = rows[0]
    scene = MarkerScene(CameraModel(fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"]), north=0.8, east=-0.5,
                        size_m=0.18, marker_id=MARKER)
    threading.Thread(target=run_detections, args=(agent, ROBOT, scene, fake_pose(fc)),
                     kwargs=dict(rate_hz=10.0, stop=stop), daemon=True).start()
    return scene


def test_the_default_start_sends_positions_from_the_graphs_site_without_a_rangefinder(robot):
    fc, flight, agent = robot(with_site=True)
    assert flight.bridge.settings.markers.site == "demo-hall"  # from the graph, no file given
    stop = threading.Event()
    try:
        _fly_over_marker(agent, fc, flight, stop)
        targets = fc.wait_for("LANDING_TARGET", 5, timeout=15)
    finally:
        stop.set()
    v = fc.vehicle
    truth = ned_to_body((v.roll, v.pitch, v.yaw), (0.8, -0.5, v.alt))
    fresh = [t.fields for t in targets if t.fields["target_num"] == MARKER]
    assert fresh and all(f["position_valid"] == 1 and f["frame"] == 12 for f in fresh)
    for f in fresh:
        assert (f["x"], f["y"], f["z"]) == pytest.approx(truth, abs=0.05)  # from the 0.18 m size in the graph
        assert f["distance"] == pytest.approx(sum(c * c for c in truth) ** 0.5, rel=0.02)
    assert flight.bridge.angles_only is False


def test_without_sizes_or_a_rangefinder_the_agent_warns_once_and_status_lists_it(robot, caplog):
    caplog.set_level(logging.WARNING, logger="kgadapt.onboard.flight")
    fc, flight, agent = robot(with_site=False)
    assert flight.bridge.settings.markers is None
    heard: list[dict] = []
    observer = agent.declare_subscriber(keys.flight_state(ROBOT),
                                        lambda s: heard.append(messages.decode(s.payload.to_bytes(), "flight_state")))
    stop = threading.Event()
    try:
        _fly_over_marker(agent, fc, flight, stop)
        targets = fc.wait_for("LANDING_TARGET", 4, timeout=15)
        assert all(t.fields["position_valid"] == 0 and t.fields["distance"] == 0 for t in targets)
        wait_until(lambda: any(m.get("angles_only") for m in heard), 5, "angles_only in flight_state")
        data = status.gather(agent, ROBOT, listen_s=1.0)
    finally:
        stop.set()
        observer.undeclare()
    assert ANGLES_ONLY in data["problems"] and data["flight"]["angles_only"] is True
    assert caplog.text.count(ANGLES_ONLY) == 1  # once, not once a target


def test_the_bridge_command_takes_the_graphs_site_as_the_sitl_runs_start_it(tmp_path):
    """``kgadapt knowledge load`` + ``kgadapt knowledge serve`` + ``kgadapt flight bridge --camera camera``, as
    child processes, no site file: positions from the graph's marker size, without a rangefinder."""
    from kgadapt.operator.cluster import ClusterSettings, LocalCluster, free_tcp_port

    cluster = LocalCluster(ClusterSettings(workdir=tmp_path, robot=ROBOT, calibrate=False))
    cluster.prepare_store()
    cluster.port = free_tcp_port()
    port = free_udp_port()
    session = None
    fc = None
    stop = threading.Event()
    try:
        cluster.spawn("service", cluster.kgadapt("knowledge", "serve", "--robot", ROBOT, "--store",
                                                 cluster.store_url, "--listen", cluster.endpoint))
        cluster.spawn("bridge", cluster.kgadapt("flight", "bridge", "--robot", ROBOT, "--url",
                                                f"udpin:127.0.0.1:{port}", "--camera", "camera",
                                                "--connect", cluster.endpoint))
        fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=5.0, rangefinder=False,
                                                 drain_pct_per_min=0.0),
                                  VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=6.0, yaw=0.4))
        fc.setup()
        session = open_session(ZenohSettings(mode="peer", connect=(cluster.endpoint,)))
        wait_until(lambda: fc.stream_rate("ATTITUDE") and fc.stream_rate("LOCAL_POSITION_NED"), 15, "streams asked")
        _fly_over_marker(session, fc, None, stop)
        targets = fc.wait_for("LANDING_TARGET", 3, timeout=20)
    finally:
        stop.set()
        if fc is not None:
            fc.shutdown()
        if session is not None:
            session.close()
        cluster.stop()
    assert all(t.fields["position_valid"] == 1 and t.fields["distance"] > 0 for t in targets)
    log = (tmp_path / "bridge.log").read_text()
    assert "landing site demo-hall from graph" in log and ANGLES_ONLY not in log
