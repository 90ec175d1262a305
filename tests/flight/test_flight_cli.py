"""``kgadapt flight fake-fc | monitor | bridge`` as real child processes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from kgadapt.sim.fake_fc import FakeFCSettings, FakeFlightController, VehicleState
from tests.conftest import REPO, free_port
from tests.flight.conftest import free_udp_port, wait_until
from tests.flight.test_landing_target import ANGLE_X, ANGLE_Y, SQUARE
from tests.support import Child


def _spawn(kgadapt_cmd, log_dir: Path, *args: str) -> Child:
    return Child([*kgadapt_cmd, *args], args[1], log_dir)


def _wait_ready(child: Child, timeout: float = 15.0) -> None:
    child.wait_ready(timeout)


def _stop(child: Child) -> int:
    return child.stop(10.0, first=signal.SIGTERM)  # SIGTERM, 5 s, then SIGKILL


def test_monitor_prints_the_state_of_the_fake_fc_run_as_a_command(kgadapt_cmd, tmp_path):
    port = free_udp_port()
    fc = _spawn(kgadapt_cmd, tmp_path, "flight", "fake-fc", "--url", f"udpout:127.0.0.1:{port}", "--armed", "--mode", "GUIDED",
                "--battery-pct", "55", "--rate-scale", "5")
    try:
        _wait_ready(fc)
        out = subprocess.run([*kgadapt_cmd, "flight", "monitor", "--url", f"udpin:127.0.0.1:{port}", "--json",
                              "--duration", "1.0", "--every", "0.2", "--wait", "5"],
                             cwd=REPO, capture_output=True, text=True, timeout=30)
        assert out.returncode == 0, out.stderr
        states = [json.loads(line) for line in out.stdout.splitlines()]
        assert states[0]["link"] is True and states[0]["event"] == "link_up"
        last = states[-1]
        assert (last["armed"], last["mode"], last["landed_state"]) == (True, "GUIDED", "IN_AIR")
        assert last["battery_pct"] == 55.0 and last["onboard_load"] == 22.0
    finally:
        assert _stop(fc) == 0  # SIGTERM ends it cleanly


def test_monitor_with_a_bad_url_exits_1_with_one_line_naming_it(kgadapt_cmd):
    out = subprocess.run([*kgadapt_cmd, "flight", "monitor", "--url", "udpin:127.0.0.1"],
                         cwd=REPO, capture_output=True, text=True, timeout=30)
    assert out.returncode == 1
    assert out.stderr.strip().count("\n") == 0 and "'udpin:127.0.0.1'" in out.stderr


def test_the_bridge_command_turns_detections_into_landing_targets_and_publishes_flight_state(kgadapt_cmd, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    observer = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    port = free_udp_port()
    states: list[dict] = []
    sub = observer.declare_subscriber(
        keys.flight_state("clitest"), lambda s: states.append(messages.decode(s.payload.to_bytes(), "flight_state"))
    )
    bridge = _spawn(kgadapt_cmd, tmp_path, "flight", "bridge", "--robot", "clitest", "--url", f"udpin:127.0.0.1:{port}",
                    "--fx", "600", "--fy", "500", "--cx", "320", "--cy", "240", "--connect", endpoint)
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=5),
                              VehicleState(armed=True, mode="LAND", landed_state="LANDING"))
    publisher = observer.declare_publisher(keys.detector_markers("clitest", "det9"))
    try:
        _wait_ready(bridge)
        fc.setup()
        wait_until(lambda: any(s.get("landed_state") == "LANDING" for s in states), 10, "flight_state from the bridge")
        seq = 0

        def targets():
            nonlocal seq
            seq += 1
            now = time.time()
            publisher.put(messages.encode("detections", {
                "instance": "det9", "config": "c", "host": "onboard", "seq": seq, "frame_time": now, "time": now,
                "ids": [3], "corners": [SQUARE], "processing_ms": 3.0}))
            return fc.received("LANDING_TARGET")

        got = wait_until(targets, 10, "LANDING_TARGET from the bridge process", interval=0.1)
        assert got[0].fields["angle_x"] == pytest.approx(ANGLE_X, abs=1e-6)
        assert got[0].fields["angle_y"] == pytest.approx(ANGLE_Y, abs=1e-6)
    finally:
        publisher.undeclare()
        fc.shutdown()
        code = _stop(bridge)
        sub.undeclare()
        observer.close()
    assert code == 0


@pytest.mark.parametrize("sub", ["fake-fc", "monitor", "status", "bridge"])
def test_every_flight_subcommand_has_help(kgadapt_cmd, sub):
    out = subprocess.run([*kgadapt_cmd, "flight", sub, "--help"], cwd=REPO, capture_output=True, text=True, timeout=30,
                         env={**os.environ})
    assert out.returncode == 0 and "--url" in out.stdout


def test_the_bridge_command_without_intrinsics_or_camera_exits_1_saying_what_is_missing(kgadapt_cmd):
    out = subprocess.run([*kgadapt_cmd, "flight", "bridge", "--robot", "clitest", "--fx", "600"],
                         cwd=REPO, capture_output=True, text=True, timeout=30)
    assert out.returncode == 1 and "--camera" in out.stderr and "--cy" in out.stderr


def test_status_prints_every_field_with_its_age_and_the_missing_streams(kgadapt_cmd):
    port = free_udp_port()
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=5, rangefinder=False),
                              VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=4.0))
    with fc:
        done = subprocess.run([*kgadapt_cmd, "flight", "status", "--url", f"udpin:127.0.0.1:{port}", "--json",
                               "--settle", "4"], cwd=REPO, capture_output=True, text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        state = json.loads(done.stdout)
        assert state["mode"] == "LOITER" and state["landed_state"] == "IN_AIR"
        assert state["alt_rel_m"] == pytest.approx(4.0) and state["position_ned"][2] == pytest.approx(-4.0)
        assert len(state["attitude"]) == 3 and state["home"][0] == pytest.approx(fc.settings.home[0])
        assert "rangefinder_m" not in state  # no rangefinder: unknown, not 0
        assert "DISTANCE_SENSOR" in state["missing"] and "DISTANCE_SENSOR" not in state["heard"]
        assert state["timeouts"]["ATTITUDE"] == pytest.approx(1.0)
        text = subprocess.run([*kgadapt_cmd, "flight", "status", "--url", f"udpin:127.0.0.1:{port}", "--settle", "2"],
                              cwd=REPO, capture_output=True, text=True, timeout=30)
        assert text.returncode == 0, text.stderr
        assert "altitude 4.00 m above home" in text.stdout
        assert "DISTANCE_SENSOR      never heard" in text.stdout and "missing    DISTANCE_SENSOR" in text.stdout


def test_the_bridge_command_with_camera_and_marker_files_sends_positions_and_holds_them(kgadapt_cmd, tmp_path):
    from kgadapt.onboard.flight.landing_targets import CameraModel
    from kgadapt.sim.landing_scene import MarkerScene

    camera = CameraModel(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480, yaw_deg=90.0)
    (tmp_path / "camera.json").write_text(json.dumps(camera.as_dict()))
    (tmp_path / "markers.json").write_text(json.dumps({"site": "t", "markers": [{"id": 7, "size_m": 0.5}]}))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    observer = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    port = free_udp_port()
    bridge = _spawn(kgadapt_cmd, tmp_path, "flight", "bridge", "--robot", "clitest", "--url", f"udpin:127.0.0.1:{port}",
                    "--camera-file", str(tmp_path / "camera.json"), "--site", str(tmp_path / "markers.json"),
                    "--connect", endpoint)
    vehicle = VehicleState(armed=True, mode="LOITER", landed_state="IN_AIR", alt=8.0, yaw=0.3)
    fc = FakeFlightController(FakeFCSettings(url=f"udpout:127.0.0.1:{port}", heartbeat_hz=5), vehicle)
    publisher = observer.declare_publisher(keys.detector_markers("clitest", "det9"))
    scene = MarkerScene(camera, north=1.0, east=0.5, size_m=0.5)
    try:
        _wait_ready(bridge)
        fc.setup()
        # the bridge's link asks for ATTITUDE and LOCAL_POSITION_NED: the held target needs them
        wait_until(lambda: fc.stream_rate("LOCAL_POSITION_NED") and fc.stream_rate("ATTITUDE"), 10, "streams asked")
        corners = scene.corners(((0.0, 0.0, 0.3), vehicle.position_ned))
        for seq in (1, 2, 3):  # a marker counts once seen in 3 steady frames (kgadapt.onboard.flight.confirmation)
            now = time.time()
            publisher.put(messages.encode("detections", {
                "instance": "det9", "config": "c", "host": "onboard", "seq": seq, "frame_time": now, "time": now,
                "ids": [[7]], "corners": [[corners]], "processing_ms": 3.0}))
            time.sleep(0.05)  # three camera frames apart
        got = fc.wait_for("LANDING_TARGET", 5, timeout=10)  # the confirmed detection, then the held target re-sent
        from kgadapt.onboard.flight.geometry import ned_to_body

        truth = ned_to_body((0.0, 0.0, 0.3), (1.0, 0.5, 8.0))
        for target in got[:5]:
            f = target.fields
            assert f["position_valid"] == 1 and f["frame"] == 12 and f["target_num"] == 7
            assert (f["x"], f["y"], f["z"]) == pytest.approx(truth, abs=0.02)
        assert got[1].fields["time_usec"] > got[0].fields["time_usec"]  # predicted for when it is re-sent
    finally:
        publisher.undeclare()
        fc.shutdown()
        code = _stop(bridge)
        observer.close()
    assert code == 0


def test_the_bridge_command_with_a_bad_camera_file_exits_1_naming_it(kgadapt_cmd, tmp_path):
    bad = tmp_path / "cam.json"
    bad.write_text(json.dumps({"fx": 600, "fy": 600, "cx": 320}))
    out = subprocess.run([*kgadapt_cmd, "flight", "bridge", "--robot", "clitest", "--camera-file", str(bad)],
                         cwd=REPO, capture_output=True, text=True, timeout=30)
    assert out.returncode == 1 and str(bad) in out.stderr and "lacks cy" in out.stderr
