"""``kgadapt remote`` (the remote host's agent) and ``kgadapt squeeze``.

The remote agent's parts: the host monitor and the deployer.

``kgadapt squeeze --host H SIZE`` asks host H's monitor to reserve SIZE of
memory (``0`` lifts it): the way to make a host run short on cue in tests and
in the demo.
"""

from __future__ import annotations

import argparse
from typing import Any

import msgspec


def register(subparsers: Any) -> None:
    from kgadapt.shared.agent import add_agent_arguments

    parser = subparsers.add_parser(
        "remote",
        help="run the remote host's agent",
        description="Run the remote host's agent: host monitor (memory, CPU) and liveliness token; "
        "stops cleanly on SIGINT or SIGTERM.",
    )
    add_agent_arguments(parser, default_host="remote")
    add_part_arguments(parser)
    parser.set_defaults(func=run)


def register_squeeze(subparsers: Any) -> None:
    from kgadapt.shared.agent import add_agent_arguments

    squeeze = subparsers.add_parser(
        "squeeze",
        help="reserve memory on a host (tests, demo)",
        description="Ask a host's monitor to subtract SIZE from its free memory (0 lifts the reservation); "
        "prints the status it then publishes.",
    )
    add_agent_arguments(squeeze, default_host="remote", give_up=False)  # it asks once, within --timeout
    squeeze.add_argument("size", metavar="SIZE", help="memory to reserve, e.g. 300M, 1G, or 0")
    squeeze.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the host (default 2)")
    squeeze.add_argument("--json", action="store_true", help="print the status as JSON")
    squeeze.set_defaults(func=run_squeeze)


def add_part_arguments(parser: argparse.ArgumentParser) -> None:
    from kgadapt.deploy import options as deploy_options
    from kgadapt.shared import hostmonitor

    hostmonitor.add_arguments(parser)
    deploy_options.add_arguments(parser)


def build_parts(args: argparse.Namespace) -> list[Any]:
    """The remote agent's parts, in setup order: host monitor, deployer."""
    from kgadapt.deploy.deployer import Deployer
    from kgadapt.deploy.deployer import settings_from_args as deployer_settings
    from kgadapt.shared.hostmonitor import HostMonitor, settings_from_args

    monitor = HostMonitor(settings_from_args(args, robot=args.robot, host=args.host))
    deployer = Deployer(deployer_settings(args, robot=args.robot, host=args.host), free_memory=monitor.free_mb,
                        budget=monitor.budget_mb)
    monitor.yielding = deployer.yielding_pids  # idle pool members (and their intermediate processes) yield to a start
    return [monitor, deployer]


def run(args: argparse.Namespace) -> int:
    from kgadapt.shared.agent import Agent, agent_settings_from_args, run_agent

    agent = Agent(agent_settings_from_args(args, role="remote"), build_parts(args))
    return run_agent(agent)


def run_squeeze(args: argparse.Namespace) -> int:
    from kgadapt.shared import hostmonitor
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    reserve = hostmonitor.parse_size_mb(args.size, allow_zero=True)
    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    session = open_session(zenoh)
    try:
        status = hostmonitor.squeeze(session, args.robot, args.host, reserve, timeout=args.timeout)
    finally:
        session.close()
    if args.json:
        print(msgspec.json.encode(status).decode())
    else:
        reserved = status.reserved_mb if status.reserved_mb is not None else reserve
        print(f"{status.host}: reserved {reserved:.0f} MiB, "
              f"free {status.memory_free_mb:.0f} of {status.memory_total_mb:.0f} MiB")
    return 0
