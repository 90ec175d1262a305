"""The robot as the README starts it, on real ArduCopter SITL, when a binary is given: KGADAPT_SITL=/path/to/arducopter.

Each flight (``tests/flight/sitl_flight.py``, in a network namespace of its
own) runs ``kgadapt knowledge load/serve`` and ``kgadapt flight bridge --url
udpin:...`` with only the robot and camera names (intrinsics and site from the
graph), SITL with precision landing over MAVLink (PLND_ENABLED=1, PLND_TYPE=1)
and, where asked, its downward rangefinder; a ground station takes off to 10 m
and switches to LAND while detections of a site marker 2.5 m north and 2 m
east, projected from SITL's true pose, go out over Zenoh. How to build the
binary: docs/flight.md, "Measured on ArduCopter SITL here". Each test prints its figures
as one JSON line (``pytest -s``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid

import pytest

from tests.conftest import REPO

SITL = os.environ.get("KGADAPT_SITL")

pytestmark = [
    pytest.mark.skipif(not SITL, reason="needs an ArduCopter SITL binary: set KGADAPT_SITL=/path/to/arducopter "
                                        "(docs/flight.md)"),
    pytest.mark.timeout(900),  # a flight takes 1.5 min, one with a reboot 3-4 (origin again after 40 s)
]

# The bridge as the README's robot runs it: the camera component's name, everything else from the graph.
DEFAULT_START = ("--camera", "camera")


@pytest.fixture
def netns():
    """A network namespace with only loopback up; removed after."""
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("needs root and iproute2 to give SITL a network namespace of its own")
    name = f"kgsitl{uuid.uuid4().hex[:8]}"
    subprocess.run(["ip", "netns", "add", name], check=True)
    try:
        subprocess.run(["ip", "netns", "exec", name, "ip", "link", "set", "lo", "up"], check=True)
        yield name
    finally:
        subprocess.run(["ip", "netns", "delete", name], check=False)


def _fly(netns: str, tmp_path, *args: str) -> dict:
    argv = ["ip", "netns", "exec", netns, sys.executable, "-m", "tests.flight.sitl_flight", "--sitl", str(SITL),
            "--workdir", str(tmp_path), *args, *(f"--bridge-arg={a}" for a in DEFAULT_START)]
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr[-6000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    print("SITL", json.dumps(result))
    return result


@pytest.mark.parametrize("rate", [15, 1], ids=["15-per-s", "1-per-s"])
@pytest.mark.parametrize("rangefinder", [False, True], ids=["no-rangefinder", "rangefinder"])
def test_the_default_start_lands_on_the_marker(netns, tmp_path, rangefinder, rate):
    result = _fly(netns, tmp_path, "--rate", str(rate), *(["--rangefinder"] if rangefinder else []))
    assert result["landed"], result
    assert result["acquired_s"] is not None, f"ArduPilot never acquired the target: {result}"
    assert result["error_m"] <= 0.3, result
    # Once ArduPilot has the target it keeps getting one: no gap over 1 s, also at 1 detection a second.
    assert result["max_gap_after_acquired_s"] <= 1.0, result


def test_after_a_reboot_on_the_ground_the_streams_are_back_and_it_still_lands(netns, tmp_path):
    result = _fly(netns, tmp_path, "--rate", "15", "--rangefinder", "--reboot-first")
    late = {name: s for name, s in result["reboot"]["streams"].items()
            # what ArduPilot sends at once: within 3 s of its first heartbeat; the rest within 1 s of its first
            if s["back_s"] is None or s["back_s"] > max(3.0, s["ardupilot_first_s"] + 1.0)}
    assert not late, result["reboot"]
    assert result["landed"] and result["error_m"] <= 0.3, result
