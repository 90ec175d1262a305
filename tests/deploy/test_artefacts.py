"""The systemd units for real hosts: valid for systemd, and their command lines parse."""

from __future__ import annotations

import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from kgadapt.cli import build_parser

UNITS = sorted((Path(__file__).resolve().parents[2] / "deploy" / "systemd").glob("*.service"))


def unit_environment(unit: Path) -> dict[str, str]:
    """The unit's own Environment= values (what applies without /etc/kgadapt/kgadapt.env)."""
    env: dict[str, str] = {}
    for line in unit.read_text().splitlines():
        if line.startswith("Environment="):
            for word in shlex.split(line[len("Environment="):]):
                key, _, value = word.partition("=")
                env[key] = value
    return env


def exec_start(unit: Path, env_file: dict[str, str] | None = None) -> list[str]:
    """ExecStart= as systemd runs it: ``${X}`` is one word, ``$X`` split at whitespace; the env file wins."""
    env = {**unit_environment(unit), **(env_file or {})}
    text = unit.read_text().replace("\\\n", " ")
    line = next(line for line in text.splitlines() if line.startswith("ExecStart="))
    argv: list[str] = []
    for word in shlex.split(line[len("ExecStart="):]):
        if word.startswith("$") and not word.startswith("${"):
            argv.extend(env.get(word[1:], "").split())
        else:
            argv.append(word.replace("${KGADAPT_STORE}", env.get("KGADAPT_STORE", "")))
    return argv


def test_the_onboard_unit_adapts_with_camera_and_flight_controller_and_the_env_file_can_change_them():
    unit = next(u for u in UNITS if u.name == "kgadapt-onboard.service")
    parsed = build_parser().parse_args(exec_start(unit)[1:])
    assert parsed.adapt and parsed.camera_source == "device:0" and parsed.fc == "/dev/ttyACM0:921600"
    changed = build_parser().parse_args(exec_start(unit, {
        "KGADAPT_ONBOARD_ARGS": "--adapt --camera-source device:1 --fc udpin:0.0.0.0:14550 --prefer remote-first"})[1:])
    assert (changed.camera_source, changed.fc, changed.prefer) == ("device:1", "udpin:0.0.0.0:14550", "remote-first")
    remote = next(u for u in UNITS if u.name == "kgadapt-remote.service")
    assert build_parser().parse_args(exec_start(remote, {"KGADAPT_REMOTE_ARGS": "--memory-budget 2G"})[1:]).memory_budget


def test_units_for_the_knowledge_service_and_both_agents_are_shipped():
    assert {u.name for u in UNITS} == {"kgadapt-knowledge.service", "kgadapt-onboard.service", "kgadapt-remote.service"}


@pytest.mark.skipif(not shutil.which("systemd-analyze"), reason="systemd-analyze is not installed")
@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_systemd_finds_nothing_wrong_in_the_unit_but_the_missing_install(unit):
    done = subprocess.run(["systemd-analyze", "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=60)
    complaints = [line for line in (done.stdout + done.stderr).splitlines()
                  if line.strip() and "/opt/kgadapt/venv/bin/kgadapt is not executable" not in line]
    assert complaints == []


@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_each_unit_restarts_its_service_and_runs_a_kgadapt_command_that_parses(unit):
    text = unit.read_text()
    assert "Restart=always" in text and "RestartSec=" in text
    argv = exec_start(unit)
    assert argv[0].endswith("/kgadapt")
    parsed = build_parser().parse_args(argv[1:])
    assert parsed.robot == "quad1" and parsed.zenoh_config.startswith("/etc/kgadapt/zenoh/")
