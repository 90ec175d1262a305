"""Two robots side by side on one Zenoh network: every command honours --robot and none mixes them.

quad1 is the README's robot (adapting, with a camera); quad2 has its own store
and knowledge service and one agent whose host has the same name as one of
quad1's (``remote``), with another memory budget, so an answer that mixed them
would show. A robot nobody runs (quad3) gets errors naming it and the endpoint.
"""

from __future__ import annotations

import json

import pytest

from tests.support import wait_for

ENDPOINT = "tcp/127.0.0.1:7447"


def _json(terminal, line: str):
    result = terminal.run(line, timeout=60)
    assert result.returncode == 0, f"{line}: exit {result.returncode}\n{result.stdout}\n{result.stderr}"
    return json.loads(result.stdout)


@pytest.mark.timeout(300)  # several robots' processes on a shared 2-core machine
def test_every_command_answers_for_the_robot_it_is_given_and_never_mixes_two(terminal):
    k = f"{terminal.workdir}/.venv/bin/kgadapt"
    for robot in ("quad1", "quad2"):
        assert terminal.run(f"{k} knowledge load knowledge/models --store embedded:{robot}").returncode == 0
    # A short calibration (2 frames at 2 levels per band): what is tested is which robot's graph holds it.
    calibrated = terminal.run(f"{k} perception calibrate --store embedded:quad1 --frames 2 --levels 2 "
                              "--out var/c.json --plot var/c.png")
    assert calibrated.returncode == 0, calibrated.stderr
    terminal.start(f"{k} knowledge serve --robot quad1 --store embedded:quad1")
    terminal.start(f"{k} knowledge serve --robot quad2 --store embedded:quad2 --mode peer "
                   f"--connect {ENDPOINT} --listen tcp/127.0.0.1:7448")
    terminal.start(f"{k} remote --robot quad1 --host remote --memory-budget 4G")
    terminal.start(f"{k} remote --robot quad2 --host remote --memory-budget 2G")
    terminal.start(f"{k} onboard --robot quad1 --host onboard --memory-budget 700M --camera-source synthetic --adapt")

    def quad1_decided():
        return _json(terminal, f"{k} ask --robot quad1 decisions --json")

    wait_for(quad1_decided, 30, "quad1's first adaptation decision", interval=0.5)

    # why: each robot's own graph, and it says whose it asked.
    why1 = terminal.run(f"{k} why --robot quad1")
    assert why1.returncode == 0 and "on onboard" in why1.stdout and "robot quad1" in why1.stdout, why1.stdout
    why2 = terminal.run(f"{k} why --robot quad2")
    assert why2.returncode == 0, why2.stderr
    assert "No detector is running" in why2.stdout and "robot quad2" in why2.stdout, why2.stdout
    assert "marker_detection" not in why2.stdout
    both = terminal.run(f"{k} why --robot quad2 --store embedded:quad1")
    assert both.returncode == 1 and "not both" in both.stderr

    # ask: decisions and platforms of each robot's own store.
    assert _json(terminal, f"{k} ask --robot quad2 decisions --json") == []
    platforms2 = {r["platform"]: r for r in _json(terminal, f"{k} ask --robot quad2 platforms --json")}
    assert platforms2["remote"]["online"] is True and platforms2["onboard"]["online"] is not True

    misspelt = terminal.run(f"{k} ask --robot quad2 placement -p config=marker_detection_darkk")
    assert misspelt.returncode == 1
    assert "no detector configuration 'marker_detection_darkk' in the knowledge service of robot quad2" in misspelt.stderr

    # deploy list: quad2's deployer answers with nothing running; quad1's onboard runs the detector.
    assert _json(terminal, f"{k} deploy list --robot quad2 --json") == []
    listed1 = _json(terminal, f"{k} deploy list --robot quad1 --json")
    assert {p["host"] for p in listed1} == {"onboard"} and all(p["instance"].startswith("marker_detection") for p in listed1)

    # status: hosts, memory budgets, processes and decisions of the robot asked about only.
    result2 = terminal.run(f"{k} status --robot quad2 --json --window 1", timeout=60)
    status2 = json.loads(result2.stdout)
    # Exit status 1: quad2's onboard host never came online and nothing is calibrated; it says so.
    assert result2.returncode == 1 and "host onboard has never come online" in status2["problems"]
    assert {h["host"] for h in status2["hosts"] if h["up"]} == {"remote"}
    assert next(h for h in status2["hosts"] if h["host"] == "remote")["memory_total_mb"] == 2048
    assert status2["processes"] == [] and status2["decisions"] == [] and status2["detection"] == []
    assert status2["light"] is None  # quad1's camera is not quad2's
    status1 = terminal.run(f"{k} status --robot quad1 --json --window 1", timeout=60)
    data1 = json.loads(status1.stdout)
    assert {h["host"] for h in data1["hosts"] if h["up"]} == {"onboard", "remote"}
    assert next(h for h in data1["hosts"] if h["host"] == "remote")["memory_total_mb"] == 4096
    assert data1["decisions"] and data1["light"] is not None

    # squeeze reaches quad2's remote host only.
    squeezed = terminal.run(f"{k} squeeze --robot quad2 --host remote 100M")
    assert squeezed.returncode == 0 and "reserved 100 MiB" in squeezed.stdout, squeezed.stderr
    assert "reserved 0 MiB" in terminal.run(f"{k} squeeze --robot quad1 --host remote 0").stdout

    # A robot nobody runs: errors that name it and the endpoint tried, exit status 1.
    for line, words in ((f"{k} deploy list --robot quad3 --timeout 1", ("robot quad3", ENDPOINT)),
                        (f"{k} ask --robot quad3 placement --timeout 1", ("robot 'quad3'",)),
                        (f"{k} why --robot quad3", ("robot 'quad3'",))):
        result = terminal.run(line)
        assert result.returncode == 1 and result.stdout == "", f"{line}: {result.returncode} {result.stdout}"
        assert all(w in result.stderr for w in words), f"{line}: {result.stderr}"
    status3 = terminal.run(f"{k} status --robot quad3 --once --window 0.5 --timeout 1")
    assert status3.returncode == 1 and "knowledge service of robot quad3 not reachable" in status3.stdout
