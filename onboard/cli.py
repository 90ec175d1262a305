"""``kgadapt onboard``: the quadcopter's agent.

Parts today: the host monitor. Later parts (camera and illumination monitor,
MAVLink bridge, deployer, adaptation manager) are added in :func:`build_parts`
with their flags in :func:`add_part_arguments`.
"""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "onboard",
        help="run the quadcopter's onboard agent",
        description="Run the onboard agent: host monitor (memory, CPU) and liveliness token; "
        "stops cleanly on SIGINT or SIGTERM.",
    )
    from shared.agent import add_agent_arguments

    add_agent_arguments(parser, default_host="onboard")
    add_part_arguments(parser)
    parser.set_defaults(func=run)


def add_part_arguments(parser: argparse.ArgumentParser) -> None:
    from shared import hostmonitor

    hostmonitor.add_arguments(parser)


def build_parts(args: argparse.Namespace) -> list[Any]:
    """The onboard agent's parts, in setup order."""
    from shared.hostmonitor import HostMonitor, settings_from_args

    return [HostMonitor(settings_from_args(args, robot=args.robot, host=args.host))]


def run(args: argparse.Namespace) -> int:
    from shared.agent import Agent, agent_settings_from_args, run_agent

    agent = Agent(agent_settings_from_args(args, role="onboard"), build_parts(args))
    return run_agent(agent)
