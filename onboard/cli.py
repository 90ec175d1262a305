"""``kgadapt onboard``: the quadcopter's agent.

Parts, in setup order: host monitor (always), deployer (always), camera with
illumination monitor (``--camera-source``), MAVLink bridge (``--fc URL``) and
the adaptation manager (``--adapt``). The liveliness token is declared after
every part is up, so others see the host only when it can serve.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

log = logging.getLogger(__name__)

# How long a part's first read from the graph waits for the knowledge service: it may be starting,
# or its store reloading after a restart (20 s seen on a loaded machine); within systemd's TimeoutStartSec.
STARTUP_WAIT_S = 30.0

def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "onboard",
        help="run the quadcopter's onboard agent",
        description="Run the onboard agent: host monitor, deployer, and optionally camera, MAVLink bridge "
        "and adaptation manager; stops cleanly on SIGINT or SIGTERM.",
    )
    from kgadapt.onboard.adaptation.planning_defaults import ONBOARD_HOST
    from kgadapt.shared.agent import add_agent_arguments

    add_agent_arguments(parser, default_host=ONBOARD_HOST)
    add_part_arguments(parser)
    parser.set_defaults(func=run)


def add_part_arguments(parser: argparse.ArgumentParser) -> None:
    from kgadapt.deploy import options as deploy_options
    from kgadapt.onboard.adaptation.planning_defaults import DEFAULT_PREFERENCE, PREFERENCES
    from kgadapt.shared import hostmonitor

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
    fc.add_argument("--fc-camera-file", metavar="JSON",
                    help="camera file (intrinsics, distortion, mounting) instead of the graph's intrinsics")
    fc.add_argument("--fc-profile", choices=("auto", "ardupilot", "px4"), default="auto",
                    help="LANDING_TARGET frame per autopilot (default: from its heartbeat)")
    fc.add_argument("--site", metavar="FILE",
                    help="site file (*.site: marker ids, sizes, dictionary) instead of the graph's site: only its "
                         "ids become LANDING_TARGET, and they go with the marker's position")
    fc.add_argument("--site-name", metavar="NAME",
                    help="the graph's site to use when it holds several (default: the only one)")
    ad = parser.add_argument_group("adaptation")
    ad.add_argument("--adapt", action="store_true", help="run the adaptation manager on this agent")
    ad.add_argument("--prefer", choices=PREFERENCES, default=DEFAULT_PREFERENCE,
                    help=f"where a detector goes when both hosts can hold it (default {DEFAULT_PREFERENCE}: "
                    "the link to the remote host can fail)")
    ad.add_argument("--dwell", type=float, default=1.0, metavar="S",
                    help="seconds a new illumination band must hold before the detector changes (default 1)")
    ad.add_argument("--hysteresis", type=float, default=4.0, metavar="LEVELS",
                    help="luminance levels beyond a band edge before a change counts (default 4)")
    ad.add_argument("--no-in-place", dest="in_place", action="store_false",
                    help="always start a new detector for a change, even where the graph allows an in-place "
                    "reconfiguration (for comparison)")
    ad.add_argument("--standby", action="store_true",
                    help="keep the neighbouring illumination band's configuration started but idle where the graph "
                    "says a host has room for it as well, so a band change or a lost host is a switch (default off)")


def log_site(site: Any) -> None:
    """Say which site's markers the flight bridge takes (and that without one targets may carry angles only)."""
    if site is None:
        log.warning("no landing site known (none in the knowledge graph, no --site FILE): every marker id may "
                    "become a landing target, and without marker sizes the targets carry angles only "
                    "(kgadapt knowledge load knowledge/models loads the shipped site)")
    else:
        log.info("landing site %s from %s: markers %s", site.site, site.source or "?",
                 ", ".join(f"{mid} ({size:g} m)" for mid, size in sorted(site.sizes_m.items())))


class FlightPart:
    """The MAVLink bridge, with the camera intrinsics read from the graph at setup."""

    name = "flight"

    def __init__(self, *, robot: str, url: str, camera_model: str, camera: Any = None, site: Any = None,
                 site_name: str | None = None, profile: str = "auto", manager: Any = None,
                 host: str = "onboard") -> None:
        self.robot, self.url, self.camera_model = robot, url, camera_model
        self.host = host  # its flight state is written as this host's (knowledge/write/<host>/flight_state)
        self.camera, self.profile = camera, profile  # a checked camera file (kgadapt.onboard.flight.landing_targets)
        # A checked site file (kgadapt.onboard.flight.site.SiteMarkers), else the graph's site (site_name: which one)
        self.site, self.site_name = site, site_name
        self.manager = manager  # the adaptation manager beside it: only its chosen detector steers
        self.bridge: Any = None

    def in_final_descent(self) -> bool:
        """Whether the vehicle is in a landing's final descent as the bridge knows its state (False before
        setup): landed state LANDING, or in LAND/RTL with the landed state unknown or at most 10 m up."""
        from kgadapt.onboard.flight.flight_phase import in_final_descent

        bridge = self.bridge
        if bridge is None:
            return False
        state = bridge.state
        return in_final_descent({"landed_state": state.landed_state, "mode": state.mode, "alt_rel_m": state.alt_rel_m})

    def setup(self, session: Any) -> None:
        from kgadapt.knowledge.client import KnowledgeClient
        from kgadapt.onboard.flight.confirmation import ConfirmationSettings
        from kgadapt.onboard.flight.flight import (
            BridgeSettings,
            CameraIntrinsics,
            FlightBridge,
            FlightControlWriter,
            intrinsics_from_graph,
        )
        from kgadapt.onboard.flight.mavlink import LinkSettings
        from kgadapt.onboard.flight.site import site_from_graph

        client = KnowledgeClient(session, self.robot, own=True, host=self.host)
        c = self.camera
        intrinsics = (CameraIntrinsics(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy) if c is not None
                      else intrinsics_from_graph(client, self.camera_model, wait_s=STARTUP_WAIT_S))
        site = self.site if self.site is not None else site_from_graph(client, self.site_name, wait_s=STARTUP_WAIT_S)
        log_site(site)
        # One site for both: its ids are the only ones confirmed, its sizes give the targets' positions.
        settings = BridgeSettings(robot=self.robot, link=LinkSettings(url=self.url), intrinsics=intrinsics,
                                  camera=c, markers=site, profile=self.profile,
                                  confirmation=ConfirmationSettings(site=site))
        manager = self.manager
        chosen = None
        if manager is not None:
            def chosen() -> str | None:
                current = manager.current
                return current.instance if current is not None else None
        self.bridge = FlightBridge(settings, on_state=FlightControlWriter(client), chosen_detector=chosen)
        self.bridge.setup(session)

    def shutdown(self) -> None:
        if self.bridge is not None:
            self.bridge.shutdown()
            self.bridge = None


def build_parts(args: argparse.Namespace) -> list[Any]:
    """The onboard agent's parts, in setup order."""
    from kgadapt.deploy.deployer import Deployer
    from kgadapt.deploy.deployer import settings_from_args as deployer_settings
    from kgadapt.shared.hostmonitor import HostMonitor, settings_from_args

    monitor = HostMonitor(settings_from_args(args, robot=args.robot, host=args.host))
    deployer = Deployer(deployer_settings(args, robot=args.robot, host=args.host), free_memory=monitor.free_mb,
                        budget=monitor.budget_mb)
    monitor.yielding = deployer.yielding_pids  # idle pool members (and their intermediate processes) yield to a start
    parts: list[Any] = [monitor, deployer]
    if args.camera_source:
        from kgadapt.onboard.perception.camera import CameraPart, CameraSettings, make_source

        settings = CameraSettings(robot=args.robot, camera=args.camera, fps=args.fps, jpeg_quality=args.jpeg_quality)
        source = make_source(args.camera_source, width=settings.width, height=settings.height, fps=args.fps,
                             speed=args.scenario_speed)
        parts.append(CameraPart(settings, source))
    flight = None
    if args.fc:
        from kgadapt.onboard.flight.landing_targets import load_camera
        from kgadapt.onboard.flight.site import load_site

        flight = FlightPart(  # the files are checked here, before anything starts
            robot=args.robot, url=args.fc, camera_model=args.camera_model,
            camera=load_camera(args.fc_camera_file) if getattr(args, "fc_camera_file", None) else None,
            site=load_site(args.site) if getattr(args, "site", None) else None,
            site_name=getattr(args, "site_name", None), profile=getattr(args, "fc_profile", "auto"), host=args.host)
        parts.append(flight)
    if args.adapt:
        from kgadapt.onboard.adaptation.adaptation_manager import AdaptationManager, AdaptationSettings

        # In one process, the manager and the bridge trust each other directly: the bridge follows
        # the manager's chosen detector, the manager the bridge's flight phase (not Zenoh messages).
        manager = AdaptationManager(AdaptationSettings(
            robot=args.robot, camera=args.camera, preference=args.prefer, onboard_host=args.host,
            dwell_s=args.dwell, hysteresis=args.hysteresis, in_place=args.in_place,
            standby=args.standby),
            final_descent=flight.in_final_descent if flight is not None else None)
        if flight is not None:
            flight.manager = manager
        parts.append(manager)
    return parts


def run(args: argparse.Namespace) -> int:
    from kgadapt.shared.agent import Agent, agent_settings_from_args, run_agent

    agent = Agent(agent_settings_from_args(args, role="onboard"), build_parts(args))
    return run_agent(agent)
