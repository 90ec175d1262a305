"""The base install is what a drone runs: agents start, nothing heavy comes along.

Installs this checkout into a fresh virtualenv with plain ``pip install``
(no extra), as a user would, and checks what is there and what a command
that needs an extra says.
"""

from __future__ import annotations

import subprocess

import pytest

from kgadapt.bench.footprint import NOT_IN_BASE, copy_source, install
from tests.conftest import free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]  # builds and installs: minutes on a loaded machine


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("base-install")
    return install(copy_source(tmp / "src"), tmp / "venv", "base")


def run(base, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([str(base.kgadapt), *args], capture_output=True, text=True, timeout=timeout)


def test_the_agents_start_on_the_base_install(base):
    for command in ("onboard", "remote"):
        done = run(base, command, "--help")
        assert done.returncode == 0, done.stderr
        assert f"usage: kgadapt {command}" in done.stdout


def test_the_base_install_holds_no_store_server_plots_or_machine_learning(base):
    packages = base.packages()
    assert {"eclipse-zenoh", "opencv-python-headless", "pymavlink", "msgpack", "psutil", "numpy"} <= set(packages)
    assert [p for p in NOT_IN_BASE if p in packages] == []


@pytest.mark.parametrize(("args", "extra"), [
    (("knowledge", "serve", "--store", "memgraph://127.0.0.1:{port}"), "memgraph"),
    (("knowledge", "queries", "--store", "embedded:{tmp}/store"), None),  # needs no store
    (("knowledge", "query", "platforms", "--store", "embedded:{tmp}/store"), "store"),
    (("knowledge", "query", "platforms", "--store", "bolt+s://127.0.0.1:{port}"), "memgraph"),
    (("bench", "table1"), "bench"),
    (("certs", "{tmp}/pki"), "certs"),
])
def test_a_command_that_needs_a_missing_extra_names_it_in_one_line(base, tmp_path, args, extra):
    args = tuple(a.format(port=free_port(), tmp=tmp_path) for a in args)
    done = run(base, *args)
    if extra is None:
        assert done.returncode == 0, done.stderr
        return
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"pip install 'kgadapt[{extra}]'" in lines[0], done.stderr
