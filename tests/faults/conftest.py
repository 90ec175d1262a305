"""Fixtures of the fault tests: hosts as network namespaces, the robot across them, a second robot watching.

The robot runs as real processes in three namespaces joined by a bridge
(kgadapt/operator/cluster.py ``HostNetwork``): the knowledge service (the Zenoh router)
and the onboard agent in ``onboard``, the remote agent in ``remote``, and
the observer (bench/reliability_bench.py's probe, another robot on the
network) in ``robot2``. Names carry a per-run suffix; everything started is
stopped and every namespace removed in the finalizer, also after a failure.
Where namespaces cannot be made, the tests that need them are skipped with
the reason.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Callable, Iterator

import pytest

from kgadapt.bench.reliability_bench import RobotOnHosts, RobotSettings
from kgadapt.operator.cluster import HostNetwork

_reason: list[str | None] = []


def namespaces_unavailable() -> str | None:
    """Why network namespaces cannot be made here (asked once per session), or None."""
    if not _reason:
        _reason.append(HostNetwork.unavailable_reason())
    return _reason[0]


def our_namespaces(network: HostNetwork) -> list[str]:
    """The namespaces of ``network`` that exist right now."""
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    names = {line.split()[0] for line in listed.splitlines() if line.strip()}
    ours = [network.switch] + [network.namespace(h) for h in network.settings.hosts]
    return [n for n in ours if n in names]


@pytest.fixture
def needs_namespaces() -> None:
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")


@pytest.fixture
def start_robot(tmp_path: Path, needs_namespaces: None) -> Iterator[Callable[..., RobotOnHosts]]:
    """Start the robot across namespaces (settings as keywords of RobotSettings); stopped and removed after."""
    started: list[RobotOnHosts] = []

    def start(**settings: object) -> RobotOnHosts:
        robot = RobotOnHosts(RobotSettings(workdir=tmp_path / f"robot{len(started)}", **settings))
        started.append(robot)
        robot.start()
        return robot

    yield start
    leftovers = []
    for robot in started:
        robot.stop()
        leftovers += our_namespaces(robot.network)
    assert not leftovers, f"namespaces left behind: {leftovers}"


@pytest.fixture
def robot(start_robot: Callable[..., RobotOnHosts]) -> RobotOnHosts:
    """The robot with the detector on the remote host (remote-first), constant day light."""
    return start_robot()
