"""The ``kgadapt`` command: one entry point, subcommands registered by each part.

Each part owns a module with ``register(subparsers)`` that adds its
subcommand and sets ``func`` (called with the parsed args; returns an exit
status or None). The table below is static: every module in it is part of
kgadapt, so one that cannot be imported is a broken installation and the
command says so, instead of quietly lacking a subcommand. Modules are
imported only to register; heavy imports (cv2, the store drivers) belong
inside the functions, which run only for the chosen subcommand. Any
:class:`KgadaptError` ends the command with exit status 1 and one line on
stderr naming the problem.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Sequence

from kgadapt.shared.errors import KgadaptError

# The modules that register subcommands, in the order of `kgadapt --help`.
PARTS = (
    "kgadapt.knowledge.cli",          # kgadapt knowledge load|query|queries|cypher|export (+ serve, via a hook)
    "kgadapt.knowledge.service_cli",  # kgadapt ask
    "kgadapt.fleet_view",     # kgadapt fleet
    "kgadapt.onboard.cli",            # kgadapt onboard
    "kgadapt.onboard.perception_cli", # kgadapt perception calibrate|camera|detector ...
    "kgadapt.onboard.flight_cli",     # kgadapt flight ... (MAVLink bridge, fake flight controller)
    "kgadapt.remote.cli",             # kgadapt remote
    "kgadapt.deploy.cli",             # kgadapt deploy start|stop|list|migrate
    "kgadapt.onboard.adaptation_cli", # kgadapt why
    "kgadapt.bench.cli",              # kgadapt bench table1|zenoh|deployer|perception|adaptation|reliability
    "kgadapt.demo",           # kgadapt demo
    "kgadapt.certs",          # kgadapt certs (TLS certificate authority and certificates)
    "kgadapt.status",         # kgadapt status (one screen for the person running the robot)
)


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("kgadapt")
    except metadata.PackageNotFoundError:  # run from a checkout without installing
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kgadapt",
        description="Graph-based software knowledge for run-time adaptation of a quadcopter's marker detection.",
    )
    parser.add_argument("--log-level", default=None,
                        help="DEBUG, INFO, WARNING or ERROR (default: INFO for the long-running services and "
                             "agents, one line per decision, host change and process start/stop; WARNING for the rest)")
    parser.add_argument("--version", action="version", version=f"kgadapt {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in PARTS:
        importlib.import_module(name).register(sub)
    return parser


def _long_running(args: argparse.Namespace) -> bool:
    """The commands a person leaves running and watches: they say what they decide and do."""
    sub = getattr(args, "knowledge_command", None) or getattr(args, "deploy_command", None)
    return args.command in ("onboard", "remote") or (args.command in ("knowledge", "deploy") and sub == "serve")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.log_level is None:
        args.log_level = "INFO" if _long_running(args) else "WARNING"
    level = getattr(logging, str(args.log_level).upper(), None)
    if not isinstance(level, int):
        parser.error(f"--log-level {args.log_level!r}: use DEBUG, INFO, WARNING or ERROR")
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        status = args.func(args)
    except KgadaptError as exc:
        print(f"kgadapt: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (e.g. `| head`); not an error of ours.
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    return int(status or 0)
