"""The systemd units for real hosts: valid for systemd, and their command lines parse."""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from kgadapt.cli import build_parser

UNITS = sorted((Path(__file__).resolve().parents[2] / "deploy" / "systemd").glob("*.service"))


def exec_start(unit: Path) -> list[str]:
    text = unit.read_text().replace("\\\n", " ")
    line = next(l for l in text.splitlines() if l.startswith("ExecStart="))
    return shlex.split(line[len("ExecStart="):])


def test_units_for_the_knowledge_service_and_both_agents_are_shipped():
    assert {u.name for u in UNITS} == {"kgadapt-knowledge.service", "kgadapt-onboard.service", "kgadapt-remote.service"}


@pytest.mark.skipif(not shutil.which("systemd-analyze"), reason="systemd-analyze is not installed")
@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_systemd_finds_nothing_wrong_in_the_unit_but_the_missing_install(unit):
    done = subprocess.run(["systemd-analyze", "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=60)
    complaints = [l for l in (done.stdout + done.stderr).splitlines()
                  if l.strip() and "/opt/kgadapt/venv/bin/kgadapt is not executable" not in l]
    assert complaints == []


@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_each_unit_restarts_its_service_and_runs_a_kgadapt_command_that_parses(unit):
    text = unit.read_text()
    assert "Restart=always" in text and "RestartSec=" in text
    argv = exec_start(unit)
    assert argv[0].endswith("/kgadapt")
    args = [a.replace("${KGADAPT_STORE}", "embedded:/var/lib/kgadapt/store") for a in argv[1:]]
    parsed = build_parser().parse_args(args)
    assert parsed.robot == "quad1" and parsed.zenoh_config.startswith("/etc/kgadapt/zenoh/")
