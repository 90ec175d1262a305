"""The command registry: every subcommand is there, a missing module is an error, parsing loads no heavy library.

The registry is the package's ``kgadapt.commands`` entry points (pyproject.toml, read by kgadapt/cli.py).
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from kgadapt import cli
from kgadapt.bench import cli as bench_cli

REPO = Path(__file__).resolve().parents[1]
COMMANDS = {"ask", "bench", "certs", "demo", "deploy", "fleet", "flight", "knowledge", "onboard", "perception",
            "remote", "squeeze", "status", "why"}
# Subcommands that another part adds to a command: knowledge serve needs Zenoh; the flight ones drive stand-ins.
JOINED = {"knowledge serve", "flight fake-fc", "flight land-check"}


def _parses(*argv: str) -> None:
    """``kgadapt ARGV --help`` is a command the parser knows (its help ends the parse with status 0)."""
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args([*argv, "--help"])
    assert done.value.code == 0, argv


def test_the_installed_registry_is_the_one_pyproject_declares():
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"][cli.GROUP]
    assert {e.name: e.value for e in cli.commands()} == declared  # an editable install older than pyproject fails here
    assert {e.name for e in cli.commands()} == COMMANDS | JOINED


@pytest.mark.parametrize("command", sorted(COMMANDS | JOINED))
def test_every_command_of_the_registry_is_registered(command, capsys):
    _parses(*command.split())
    assert f"usage: kgadapt {command}" in capsys.readouterr().out


def test_the_benchmarks_of_the_bench_table_are_subcommands(capsys):
    for name in ("table1", "zenoh", "deployer", "perception", "adaptation", "reliability", "soak", "report"):
        _parses("bench", name)
    assert len(bench_cli.BENCHES) >= 12


def _with_entry(monkeypatch, name: str, value: str) -> None:
    extra = metadata.EntryPoint(name=name, value=value, group=cli.GROUP)
    real = cli.commands()
    monkeypatch.setattr(cli, "commands", lambda: sorted([*real, extra], key=lambda e: (len(e.name.split()), e.name)))


def test_a_command_whose_module_is_not_installed_is_listed_and_an_error_naming_it(monkeypatch, capsys):
    _with_entry(monkeypatch, "nowhere", "kgadapt.no_such_part:register")
    assert cli.main(["nowhere", "--any", "thing"]) == 1
    assert "command 'nowhere' needs kgadapt.no_such_part, which is not installed" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "nowhere" in capsys.readouterr().out


def test_a_bench_module_of_the_table_that_is_missing_is_an_error_not_a_missing_benchmark(monkeypatch):
    monkeypatch.setattr(bench_cli, "BENCHES", (*bench_cli.BENCHES, "kgadapt.no_such_part"))
    with pytest.raises(ModuleNotFoundError, match="kgadapt.no_such_part"):
        cli.build_parser()


def test_a_module_that_imports_something_missing_is_a_broken_installation(monkeypatch):
    # Only the registered module itself may be absent; an import error inside it propagates.
    _with_entry(monkeypatch, "broken", "kgadapt.shared.errors:NoSuchFunction")
    with pytest.raises(AttributeError):
        cli.build_parser()


def register_another_name(subparsers) -> None:
    subparsers.add_parser("another")


def test_an_entry_that_adds_no_such_command_or_joins_no_command_is_refused(monkeypatch):
    from kgadapt.shared.errors import ConfigError

    _with_entry(monkeypatch, "wrongname", "tests.test_commands:register_another_name")
    with pytest.raises(ConfigError, match="registered as command 'wrongname' but adds no such command"):
        cli.build_parser()
    monkeypatch.undo()
    _with_entry(monkeypatch, "deploy extra", "kgadapt.remote.cli:register_squeeze")
    with pytest.raises(ConfigError, match="no command 'deploy' takes subcommands from other parts"):
        cli.build_parser()


def test_an_installation_without_the_registry_says_so_in_one_line(monkeypatch, capsys):
    monkeypatch.setattr(metadata, "entry_points", lambda **_: [])
    assert cli.main(["status"]) == 1
    assert capsys.readouterr().err.strip() == (
        "kgadapt: error: no kgadapt commands are registered (entry points 'kgadapt.commands'): "
        "install kgadapt (pip install -e . in a checkout) to run it")


def test_building_the_parser_loads_neither_opencv_nor_a_store_driver_nor_mavlink():
    heavy = ("cv2", "falkordb", "redis", "neo4j", "pymavlink", "matplotlib")
    code = ("import sys; from kgadapt.cli import build_parser; build_parser(); "
            f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"



@pytest.mark.parametrize("argv", [["flight", "bridge"], ["onboard"], ["remote"], ["status"], ["deploy", "list"],
                                  ["knowledge", "serve"]])
def test_a_command_that_talks_to_a_robot_defaults_to_quad1(argv):
    # README: "Commands that talk to a robot take --robot NAME (default quad1)"; flight bridge required it.
    from kgadapt.shared.keys import DEFAULT_ROBOT

    assert cli.build_parser().parse_args(argv).robot == DEFAULT_ROBOT


def test_squeeze_asks_once_and_offers_no_give_up_option(capsys):
    # --give-up-after is an agent's (keep trying to reach the router); squeeze took it and ignored it.
    with pytest.raises(SystemExit) as done:
        cli.build_parser().parse_args(["squeeze", "--give-up-after", "600", "0"])
    assert done.value.code == 2 and "--give-up-after" in capsys.readouterr().err
    assert cli.build_parser().parse_args(["remote", "--give-up-after", "600"]).give_up_after == 600.0
