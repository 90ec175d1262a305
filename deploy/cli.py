"""``kgadapt deploy start|stop|status|list|migrate|serve``: the deployers, for people.

Every command but ``serve`` is a Zenoh client of the deployers (by default
through the knowledge service's router on ``tcp/127.0.0.1:7447``); ``serve``
runs a deployer on its own, for a host that runs no other agent.
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

import msgspec

from kgadapt.shared import messages
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.states import LIVE_STATES

if TYPE_CHECKING:  # imported where used: the command line starts without zenoh
    import zenoh

    from kgadapt.deploy.client import DeployerClient


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "deploy",
        help="start, stop, list and migrate detector processes on the robot's hosts",
        description="Ask the hosts' deployers to start, stop, list or migrate detector processes. "
        "What runs comes from the knowledge store: you name a deployment and a detector configuration.",
    )
    sub = parser.add_subparsers(dest="deploy_command", metavar="ACTION")
    sub.required = True

    start = sub.add_parser("start", help="start a deployment with a configuration on a host",
                           description="Start DEPLOYMENT with detector configuration CONFIG on --host; "
                           "waits until the process announces it is ready (its readiness line) unless --no-wait.")
    start.add_argument("deployment", help="Deployment name in the knowledge store")
    start.add_argument("config", help="detector configuration (PerceptionGraph name)")
    start.add_argument("--host", required=True, help="host whose deployer starts it (a Platform name)")
    start.add_argument("--instance", help="instance id (default: <config>-<host>-<random>)")
    start.add_argument("--no-wait", action="store_true", help="reply once started, without waiting for readiness")
    start.add_argument("--ready-timeout", type=float, metavar="S", help="seconds to get ready (default: the deployer's)")
    _common(start)
    start.set_defaults(func=run_start)

    stop = sub.add_parser("stop", help="stop an instance (SIGINT, then SIGTERM, then SIGKILL)",
                          description="Stop INSTANCE; without --host the deployer running it is found first.")
    stop.add_argument("instance")
    stop.add_argument("--host", help="host running it (default: ask every deployer)")
    _common(stop)
    stop.set_defaults(func=run_stop)

    status = sub.add_parser("status", help="show one instance", description="Show INSTANCE's state, PID and last output.")
    status.add_argument("instance")
    status.add_argument("--host", help="host running it (default: ask every deployer)")
    _common(status)
    status.set_defaults(func=run_status)

    listing = sub.add_parser("list", help="list processes on one or every host",
                             description="List the processes the deployers know (live and recently ended).")
    listing.add_argument("--host", default="*", help="one host (default: every deployer that answers)")
    listing.add_argument("--live", action="store_true", help="only live processes")
    _common(listing)
    listing.set_defaults(func=run_list)

    migrate = sub.add_parser("migrate", help="move an instance to another host (or configuration) without losing output",
                             description="Start INSTANCE's deployment and configuration (or --deployment / --config) "
                             "on --to, wait for its first detections, then stop INSTANCE. If the target does not "
                             "get ready, INSTANCE keeps running and the command fails.")
    migrate.add_argument("instance")
    migrate.add_argument("--to", dest="target", required=True, metavar="HOST", help="target host")
    migrate.add_argument("--from", dest="source", metavar="HOST", help="source host (default: found by asking)")
    migrate.add_argument("--config", help="switch to this detector configuration too (default: the same)")
    migrate.add_argument("--deployment", help="switch to this deployment too (default: the same)")
    migrate.add_argument("--new-instance", help="the target instance's id (default: generated)")
    migrate.add_argument("--ready-timeout", type=float, default=15.0, metavar="S", help="target readiness timeout (default 15)")
    migrate.add_argument("--output-timeout", type=float, default=5.0, metavar="S",
                         help="time for the target's first detections after it is ready (default 5)")
    _common(migrate)
    migrate.set_defaults(func=run_migrate)

    serve = sub.add_parser("serve", help="run a deployer alone on this host",
                           description="Run only a deployer for --host (no host monitor): for hosts without "
                           "another agent, and for tests. Stops its processes on SIGINT or SIGTERM.")
    serve.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")
    serve.add_argument("--host", required=True, help="this host's name, as the models call its Platform")
    from kgadapt.deploy.options import add_arguments as add_deployer_arguments
    from kgadapt.shared.session import add_arguments as add_zenoh_arguments

    add_zenoh_arguments(serve)
    add_deployer_arguments(serve)
    serve.set_defaults(func=run_serve)


def _common(parser: argparse.ArgumentParser) -> None:
    from kgadapt.shared.session import add_arguments as add_zenoh_arguments

    parser.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S", help="request timeout (default 5)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    add_zenoh_arguments(parser)


class _Client:
    """A client-mode session and a DeployerClient for one command."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args

    def __enter__(self) -> tuple[zenoh.Session, DeployerClient]:
        from kgadapt.deploy.client import DeployerClient
        from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

        zenoh = settings_from_args(self.args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
        self.session = open_session(zenoh)
        return self.session, DeployerClient(self.session, self.args.robot, timeout=self.args.timeout)

    def __exit__(self, *exc: object) -> None:
        self.session.close()


def run_start(args: argparse.Namespace) -> int:
    with _Client(args) as (_, client):
        info = client.start(args.host, args.deployment, args.config, instance=args.instance,
                            wait_ready=not args.no_wait, ready_timeout=args.ready_timeout)
    _print_info(info, args)
    return 0


def run_stop(args: argparse.Namespace) -> int:
    with _Client(args) as (_, client):
        host = args.host or str(client.find(args.instance).host)
        info = client.stop(host, args.instance)
    _print_info(info, args)
    return 0


def run_status(args: argparse.Namespace) -> int:
    with _Client(args) as (_, client):
        info = client.status(args.host, args.instance) if args.host else client.find(args.instance)
    _print_info(info, args, output=True)
    return 0


def run_list(args: argparse.Namespace) -> int:
    with _Client(args) as (_, client):
        processes = client.processes(args.host)
    if not client.answered:  # silence is not "no processes": say whom we asked, and fail
        from kgadapt.shared.errors import RequestTimeout
        from kgadapt.shared.session import DEFAULT_ENDPOINT, settings_from_args

        via = ", ".join(settings_from_args(args).connect) or args.zenoh_config or DEFAULT_ENDPOINT
        where = "no deployer" if args.host == "*" else f"no deployer on host {args.host}"
        raise RequestTimeout(f"{where} of robot {args.robot} answered within {args.timeout:g} s via {via} "
                             f"(is `kgadapt onboard` or `kgadapt remote --robot {args.robot}` running there?)")
    if args.live:
        processes = [p for p in processes if p.state in LIVE_STATES]
    processes.sort(key=lambda p: (str(p.host), str(p.instance)))
    if args.json:
        print(json.dumps(msgspec.to_builtins(processes), indent=2))
        return 0
    from kgadapt.knowledge.store import rows_as_table

    columns = ("host", "instance", "state", "pid", "deployment", "config", "restarts", "returncode")
    print(rows_as_table([{c: getattr(p, c) for c in columns} for p in processes]))
    return 0


def run_migrate(args: argparse.Namespace) -> int:
    from kgadapt.deploy.client import DeployerClient
    from kgadapt.deploy.migration import migrate

    with _Client(args) as (session, _):
        client = DeployerClient(session, args.robot, timeout=args.timeout,
                                start_timeout=args.ready_timeout + args.timeout)
        report = migrate(session, args.robot, args.instance, args.target, source_host=args.source,
                         deployment=args.deployment, config=args.config, new_instance=args.new_instance,
                         ready_timeout=args.ready_timeout, output_timeout=args.output_timeout, client=client)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(f"migrated {report.instance} ({report.config}) from {report.source_host} to {report.target_host} "
              f"as {report.new_instance}: ready after {report.target_ready_ms:.0f} ms, first detections after "
              f"{report.first_output_ms:.0f} ms, source stopped after {report.source_stopped_ms:.0f} ms")
    return 0


def run_serve(args: argparse.Namespace) -> int:
    from kgadapt.deploy.deployer import Deployer, settings_from_args
    from kgadapt.shared.agent import Agent, AgentSettings, run_agent
    from kgadapt.shared.session import DEFAULT_ENDPOINT
    from kgadapt.shared.session import settings_from_args as zenoh_settings_from_args

    zenoh = zenoh_settings_from_args(args).with_defaults(mode="peer", connect=[DEFAULT_ENDPOINT])
    if zenoh.mode == "client" and not zenoh.connect and not zenoh.config_file:
        raise ConfigError("a deployer in client mode needs --connect")
    settings = settings_from_args(args, robot=args.robot, host=args.host)
    agent = Agent(AgentSettings(robot=args.robot, host=args.host, role="deployer", zenoh=zenoh), [Deployer(settings)])
    return run_agent(agent)


def _print_info(info: messages.ProcessDetail, args: argparse.Namespace, *, output: bool = False) -> None:
    if args.json:
        print(json.dumps(msgspec.to_builtins(info), indent=2))
        return
    line = (f"{info.instance} on {info.host}: {info.state}, pid {info.pid}, "
            f"{info.deployment} / {info.config}")
    if info.returncode is not None:
        line += f", exit status {info.returncode}"
    if info.detail:
        line += f" ({info.detail})"
    print(line)
    if output and info.output:
        print("last output:")
        for text in info.output:
            print(f"  {text}")
