"""``kgadapt onboard``: the quadcopter's agent.

Parts, in setup order: host monitor (always), deployer (always), camera with
illumination monitor (``--camera-source``), MAVLink bridge (``--fc URL``) and
the adaptation manager (``--adapt``). The liveliness token is declared after
every part is up, so others see the host only when it can serve.
"""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "onboard",
        help="run the quadcopter's onboard agent",
        description="Run the onboard agent: host monitor, deployer, and optionally camera, MAVLink bridge "
        "and adaptation manager; stops cleanly on SIGINT or SIGTERM.",
    )
    from shared.agent import add_agent_arguments

    add_agent_arguments(parser, default_host="onboard")
    add_part_arguments(parser)
    parser.set_defaults(func=run)


def add_part_arguments(parser: argparse.ArgumentParser) -> None:
    from deploy import options as deploy_options
    from shared import hostmonitor

    hostmonitor.add_arguments(parser)
    deploy_options.add_arguments(parser)
    cam = parser.add_argument_group("camera")
    cam.add_argument("--camera-source", metavar="SPEC",
                     help="synthetic[:PROFILE], device:N or file:PATH (default: no camera on this agent)")
    cam.add_argument("--camera", default="cam0", help="camera name in the key expressions (default cam0)")
    cam.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    cam.add_argument("--jpeg-quality", type=int, default=80, help="JPEG quality 1..100 (default 80)")
    cam.add_argument("--scenario-speed", type=float, default=1.0,
                     help="synthetic scenario seconds per wall-clock second (default 1)")
    fc = parser.add_argument_group("flight controller")
    fc.add_argument("--fc", metavar="URL", help="MAVLink URL of the flight controller, e.g. udpin:0.0.0.0:14550")
    fc.add_argument("--camera-model", default="camera",
                    help="camera component in the graph whose intrinsics aim LANDING_TARGET (default camera)")
    fc.add_argument("--site", metavar="FILE",
                    help="site file naming the marker ids there (*.site); other ids never become LANDING_TARGET")
    ad = parser.add_argument_group("adaptation")
    ad.add_argument("--adapt", action="store_true", help="run the adaptation manager on this agent")
    ad.add_argument("--prefer", choices=("onboard-first", "remote-first"), default="onboard-first",
                    help="where a detector goes when both hosts can hold it (default onboard-first: "
                    "the link to the remote host can fail)")
    ad.add_argument("--dwell", type=float, default=1.0, metavar="S",
                    help="seconds a new illumination band must hold before the detector changes (default 1)")
    ad.add_argument("--hysteresis", type=float, default=4.0, metavar="LEVELS",
                    help="luminance levels beyond a band edge before a change counts (default 4)")


class FlightPart:
    """The MAVLink bridge, with the camera intrinsics read from the graph at setup."""

    name = "flight"

    def __init__(self, *, robot: str, url: str, camera_model: str, site: str | None = None) -> None:
        self.robot, self.url, self.camera_model, self.site = robot, url, camera_model, site
        self.bridge: Any = None

    def setup(self, session: Any) -> None:
        from knowledge.client import KnowledgeClient
        from onboard.flight import BridgeSettings, FlightBridge, FlightControlWriter, intrinsics_from_graph
        from onboard.confirmation import ConfirmationSettings, load_site
        from onboard.mavlink import LinkSettings

        client = KnowledgeClient(session, self.robot)
        confirmation = ConfirmationSettings(site=load_site(self.site) if self.site else None)
        settings = BridgeSettings(robot=self.robot, link=LinkSettings(url=self.url),
                                  intrinsics=intrinsics_from_graph(client, self.camera_model), confirmation=confirmation)
        self.bridge = FlightBridge(settings, on_state=FlightControlWriter(client))
        self.bridge.setup(session)

    def shutdown(self) -> None:
        if self.bridge is not None:
            self.bridge.shutdown()
            self.bridge = None


def build_parts(args: argparse.Namespace) -> list[Any]:
    """The onboard agent's parts, in setup order."""
    from deploy.deployer import Deployer, settings_from_args as deployer_settings
    from shared.hostmonitor import HostMonitor, settings_from_args

    parts: list[Any] = [
        HostMonitor(settings_from_args(args, robot=args.robot, host=args.host)),
        Deployer(deployer_settings(args, robot=args.robot, host=args.host)),
    ]
    if args.camera_source:
        from onboard.camera import CameraPart, CameraSettings, make_source

        settings = CameraSettings(robot=args.robot, camera=args.camera, fps=args.fps, jpeg_quality=args.jpeg_quality)
        source = make_source(args.camera_source, width=settings.width, height=settings.height, fps=args.fps,
                             speed=args.scenario_speed)
        parts.append(CameraPart(settings, source))
    if args.fc:
        parts.append(FlightPart(robot=args.robot, url=args.fc, camera_model=args.camera_model,
                                site=getattr(args, "site", None)))
    if args.adapt:
        from onboard.adaptation_manager import AdaptationManager, AdaptationSettings

        parts.append(AdaptationManager(AdaptationSettings(
            robot=args.robot, camera=args.camera, preference=args.prefer, onboard_host=args.host,
            dwell_s=args.dwell, hysteresis=args.hysteresis)))
    return parts


def run(args: argparse.Namespace) -> int:
    from shared.agent import Agent, agent_settings_from_args, run_agent

    agent = Agent(agent_settings_from_args(args, role="onboard"), build_parts(args))
    return run_agent(agent)
