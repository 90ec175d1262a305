"""The command tables: every subcommand is there, a missing module is an error, parsing loads no heavy library."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from kgadapt import cli
from kgadapt.bench import cli as bench_cli

REPO = Path(__file__).resolve().parents[1]


def _choices(parser) -> set[str]:
    return set(parser._subparsers._group_actions[0].choices)  # argparse keeps its subparsers there


def test_every_command_of_the_table_is_registered():
    parser = cli.build_parser()
    assert _choices(parser) == {"ask", "bench", "certs", "demo", "deploy", "fleet", "flight", "knowledge", "onboard",
                                "perception", "remote", "squeeze", "status", "why"}
    sub = parser._subparsers._group_actions[0].choices
    assert "serve" in _choices(sub["knowledge"])  # the hook of kgadapt.knowledge.service_cli
    assert {"table1", "zenoh", "deployer", "perception", "adaptation", "reliability", "soak"} <= _choices(sub["bench"])


@pytest.mark.parametrize("table", [(cli, "PARTS"), (bench_cli, "BENCHES")], ids=["kgadapt", "bench"])
def test_a_module_of_the_table_that_is_missing_is_an_error_not_a_missing_subcommand(monkeypatch, table):
    module, name = table
    monkeypatch.setattr(module, name, (*getattr(module, name), "kgadapt.no_such_part"))
    with pytest.raises(ModuleNotFoundError, match="kgadapt.no_such_part"):
        cli.build_parser()


def test_building_the_parser_loads_neither_opencv_nor_a_store_driver_nor_mavlink():
    heavy = ("cv2", "falkordb", "redis", "neo4j", "pymavlink", "matplotlib")
    code = ("import sys; from kgadapt.cli import build_parser; build_parser(); "
            f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
