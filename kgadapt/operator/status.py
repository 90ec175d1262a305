"""``kgadapt status``: one screen for the person running the robot.

What it shows, and where each figure comes from (nothing is computed twice):

- the knowledge service (answers named queries over Zenoh) and the hosts
  (their agents' liveliness tokens; ``online_since`` from the graph);
- each host's free memory (its monitor's ``host_status``, else the graph);
- the detector processes (every deployer's ``list``);
- light level and band (``illumination`` messages, banded with the graph's
  ``detector_configs``), the detection rate over the listening window against
  the configuration's calibrated rate in that band;
- the flight phase (the bridge's ``flight_state``, the same message
  ``kgadapt flight status`` prints, judged by kgadapt.onboard.flight.flight_phase);
- the last decisions with their reasons (``decisions``);
- hosts the knowledge service refused because no model names them (its
  ``own/stats``: counted, never added to the graph);
- problems: anything above that is missing or wrong.

Live in a terminal (redrawn every ``--interval``), ``--once`` or ``--json``
for scripts. Exit status with ``--once``/``--json``: 0 when no problem was
found, 1 otherwise (the problems are printed).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any, Callable

import msgspec

from kgadapt.shared import messages
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.states import KEPT_STATES, ProcessState
from kgadapt.shared.timefmt import ago, duration, stamp


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "status", help="one screen: services, hosts, detector, light, detection rate, flight, decisions, problems",
        description="What the robot is doing, from its knowledge service, its agents and its messages over Zenoh. "
                    "Redraws every --interval seconds in a terminal; --once or --json prints it once and exits "
                    "(status 1 when a problem is listed).")
    parser.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")
    parser.add_argument("--once", action="store_true", help="print once and exit")
    parser.add_argument("--json", action="store_true", help="print once as JSON and exit")
    parser.add_argument("--interval", type=float, default=2.0, metavar="S", help="redraw period when live (default 2)")
    parser.add_argument("--window", type=float, default=1.5, metavar="S",
                        help="seconds to listen for host status, light, detections and flight state (default 1.5)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="S", help="request timeout (default 2)")
    parser.add_argument("--decisions", type=int, default=5, metavar="N", help="last N decisions (default 5)")
    from kgadapt.shared.session import add_arguments

    add_arguments(parser)
    parser.set_defaults(func=run)


class _Listener:
    """Subscribers that only collect (never block in a Zenoh callback); read after the window."""

    def __init__(self, session: Any, robot: str) -> None:
        from kgadapt.shared import keys

        self.lock = threading.Lock()
        self.host_status: dict[str, messages.HostStatus] = {}
        self.light: messages.Illumination | None = None
        self.detections: dict[str, dict[str, Any]] = {}  # instance -> counts
        self.flight: messages.FlightState | None = None
        self.subscribers = [
            session.declare_subscriber(keys.host_status(robot), self._on(messages.HostStatus)),
            session.declare_subscriber(keys.camera_illumination(robot), self._on(messages.Illumination)),
            session.declare_subscriber(keys.detector_markers(robot), self._on(messages.Detections)),
            session.declare_subscriber(keys.flight_state(robot), self._on(messages.FlightState)),
        ]

    def _on(self, kind: type[messages.Message]) -> Callable[[Any], None]:
        from kgadapt.shared.errors import MessageError

        def callback(sample: Any) -> None:
            try:
                body = messages.decode_as(sample.payload.to_bytes(), kind)
            except MessageError:
                return  # a malformed message is the sender's problem; status shows what is well-formed
            with self.lock:
                if isinstance(body, messages.HostStatus):
                    self.host_status[body.host] = body
                elif isinstance(body, messages.Illumination):
                    self.light = body
                elif isinstance(body, messages.FlightState):
                    self.flight = body
                elif isinstance(body, messages.Detections):
                    seen = self.detections.setdefault(body.instance, {"frames": 0, "with_markers": 0,
                                                                      "config": body.config, "host": body.host})
                    seen["frames"] += 1
                    seen["with_markers"] += 1 if body.ids else 0
        return callback

    def close(self) -> None:
        from kgadapt.shared import rpc

        for sub in self.subscribers:
            rpc.undeclare_quietly(sub)


def gather(session: Any, robot: str, *, endpoint: str = "?", listen_s: float = 1.5, timeout: float = 2.0,
           decisions: int = 5) -> dict[str, Any]:
    """Everything ``status`` shows, as data (epoch times; ``problems`` a list of sentences)."""
    from kgadapt.deploy.client import DeployerClient
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.shared import keys
    from kgadapt.shared.errors import KgadaptError

    started = time.monotonic()
    listener = _Listener(session, robot)
    problems: list[str] = []
    out: dict[str, Any] = {"robot": robot, "endpoint": endpoint, "time": time.time()}
    try:
        client = KnowledgeClient(session, robot, timeout=timeout, own=True)  # a person running this robot: fresh answers
        graph: dict[str, Any] = {}
        try:
            t0 = time.monotonic()
            graph["platforms"] = client.query("platforms", {})
            out["service"] = {"reachable": True, "answered_ms": round((time.monotonic() - t0) * 1000.0, 1)}
            graph["configs"] = client.query("detector_configs", {})
            graph["decisions"] = client.query("decisions", {"limit": decisions})
            graph["current"] = client.query("current_placement", {})
            graph["flight_control"] = client.query("flight_control", {})
        except KgadaptError as exc:
            out["service"] = {"reachable": False, "error": str(exc)}
            problems.append(f"knowledge service of robot {robot} not reachable via {endpoint}: {exc}")

        alive: dict[str, float] = {}
        try:
            for reply in session.liveliness().get(keys.host_alive(robot), timeout=timeout):
                if reply.ok is not None:
                    alive[keys.last_chunk(str(reply.ok.key_expr), 2)] = time.time()
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError and the like: a problem reported, the rest still gathered
            problems.append(f"cannot ask which hosts are alive: {exc}")

        deployers = DeployerClient(session, robot, timeout=timeout)
        processes: list[messages.ProcessDetail] = []
        try:
            processes = deployers.processes("*")
        except KgadaptError as exc:
            problems.append(f"deployers of robot {robot}: {exc}")

        left = listen_s - (time.monotonic() - started)
        if left > 0:
            time.sleep(left)  # the subscribers collect meanwhile: host status at 2 Hz, frames at camera rate
    finally:
        listener.close()
    with listener.lock:
        host_status = dict(listener.host_status)
        light, flight = listener.light, listener.flight
        detections = {k: dict(v) for k, v in listener.detections.items()}

    # Hosts the knowledge service refused because no model names them (it never adds them to the graph).
    stats: dict[str, Any] = {}
    if out.get("service", {}).get("reachable"):
        try:
            stats = client.service_stats()
        except KgadaptError:
            pass  # a service without own/stats: nothing to count
    refused: dict[str, Any] = {"count": int(stats.get("unknown_host_refused") or 0),
                               "hosts": list(stats.get("unknown_hosts") or [])}
    out["refused_hosts"] = refused
    if refused["count"]:
        problems.append(f"the knowledge service refused {refused['count']} message(s) naming hosts no model names: "
                        f"{', '.join(refused['hosts']) or '?'} (not in the graph; a wrong --host, or a forger)")

    # Hosts: the graph's platforms, plus any live host the graph does not know.
    platforms = {row["platform"]: row for row in graph.get("platforms", [])}
    hosts = []
    for name in sorted(set(platforms) | set(alive) | set(host_status)):
        row, st = platforms.get(name, {}), host_status.get(name)
        up = name in alive
        hosts.append({"host": name, "up": up, "online_since": row.get("online_since") if up else None,
                      "last_seen": row.get("last_seen"),
                      "memory_free_mb": st.memory_free_mb if st else row.get("memory_free_mb"),
                      "memory_total_mb": st.memory_total_mb if st else row.get("memory_total_mb"),
                      "cpu_load": st.cpu_load if st else None, "in_graph": name in platforms})
        if not up and name in platforms:
            problems.append(f"host {name} is offline (last seen {ago(row.get('last_seen'))})"
                            if row.get("last_seen") else f"host {name} has never come online")
        elif up and name not in platforms and graph:
            problems.append(f"host {name} is up but no Platform of that name is in the graph")
    out["hosts"] = hosts

    out["processes"] = [{"host": p.host, "instance": p.instance, "config": p.config, "deployment": p.deployment,
                         "state": p.state, "pid": p.pid, "started_at": p.started_at, "ready_at": p.ready_at,
                         "ended_at": p.ended_at, "restarts": p.restarts, "returncode": p.returncode,
                         "detail": p.detail} for p in processes]
    for p in processes:
        state = p.state
        if state == ProcessState.FAILED or (state == ProcessState.EXITED and p.returncode not in (0, None)):
            problems.append(f"instance {p.instance} on {p.host} {p.state} "
                            f"(exit status {p.returncode}): {p.detail or 'see kgadapt deploy status'}")
    live = [p for p in processes if p.state in KEPT_STATES]

    configs = graph.get("configs", [])
    if graph and not platforms and not configs:
        problems.append("the knowledge store is empty: nothing is loaded (kgadapt knowledge load knowledge/models)")
    for row in configs:
        if row.get("band") and row.get("detection_rate") is None:
            problems.append(f"configuration {row['config']} is not calibrated for band {row['band']} "
                            "(kgadapt perception calibrate)")

    # Light and band.
    band = None
    if light is not None:
        level = light.smoothed
        if configs:
            from kgadapt.onboard.perception.illumination import band_for_level
            from kgadapt.shared.errors import ConfigError

            try:
                band = band_for_level(level, configs)
            except ConfigError:
                band = None
        out["light"] = {"camera": light.camera, "level": round(float(level), 1), "band": band,
                        "time": light.time}
    else:
        out["light"] = None

    # Detection rate against the calibrated expectation.
    detectors = []
    for instance, seen in sorted(detections.items()):
        rate = seen["with_markers"] / seen["frames"] if seen["frames"] else None
        expected = next((r.get("detection_rate") for r in configs
                         if r.get("config") == seen["config"] and r.get("band") == band), None)
        detectors.append({"instance": instance, "config": seen["config"], "host": seen["host"],
                          "frames": seen["frames"], "rate": rate, "expected_rate": expected, "band": band})
        if rate is not None and expected is not None and seen["frames"] >= 10 and rate < 0.5 * expected:
            problems.append(f"detector {instance} ({seen['config']}) finds markers in {rate:.0%} of frames; "
                            f"calibrated {expected:.0%} in band {band}")
    out["detection"] = detectors
    heard = {d["instance"] for d in detectors}
    for p in live:
        if p.state == ProcessState.READY and p.instance not in heard and light is not None \
                and p.config in {r.get("config") for r in configs}:
            problems.append(f"detector {p.instance} is ready but sent no detections in {listen_s:g} s "
                            "(on a host with only a loopback interface Zenoh peers cannot reach each other: "
                            "run the agents with --mode client)")
    if light is not None and not live and processes is not None:
        problems.append("the camera publishes frames but no detector process is running")

    # Flight: the bridge's message, else what it last wrote into the graph.
    out["flight"] = _flight(flight, graph.get("flight_control") or [])
    if out["flight"] and out["flight"].get("link") is False:
        problems.append("flight controller link lost")
    if out["flight"] and out["flight"].get("angles_only"):
        from kgadapt.onboard.flight.site import ANGLES_ONLY

        problems.append(ANGLES_ONLY)

    out["current"] = (graph.get("current") or [None])[0]
    out["decisions"] = [{k: d.get(k) for k in ("time", "trigger", "config", "host", "outcome", "duration_ms")}
                        for d in graph.get("decisions", [])]
    out["problems"] = problems
    return out


def _flight(message: messages.FlightState | None, graph_rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    from kgadapt.onboard.flight.flight_phase import in_final_descent

    if message is not None:
        # Its known fields, as the graph's row names them (a nil one is unknown, as an absent one).
        state = {k: v for k, v in msgspec.structs.asdict(message).items() if v is not None}
        source = "flight_state"
    elif graph_rows and graph_rows[0].get("link") is not None:
        state, source = dict(graph_rows[0]), "graph"
        state["time"] = state.pop("last_seen", None)
    else:  # no message, and the models' FlightControl that no bridge has written yet (its link null)
        return None
    landed = state.get("landed_state")
    if not state.get("link", True):
        phase = "link lost"
    elif in_final_descent(state):
        phase = "final descent (planned changes deferred)"
    elif landed == "ON_GROUND" or state.get("armed") is False:
        phase = "on the ground"
    elif landed in ("TAKEOFF", "IN_AIR", "LANDING"):
        phase = {"TAKEOFF": "taking off", "IN_AIR": "in the air", "LANDING": "landing"}[landed]
    else:
        phase = "unknown (no landed state)"
    keep = ("link", "armed", "mode", "landed_state", "alt_rel_m", "rangefinder_m", "battery_pct", "time",
            "angles_only", "rejected", "refused")
    return {**{k: state.get(k) for k in keep}, "phase": phase, "source": source}


def render(data: dict[str, Any], *, now: float | None = None) -> str:
    """The screen, as text."""
    now = time.time() if now is None else now
    lines = [f"robot {data['robot']}  via {data['endpoint']}  at {stamp(data['time'], now).split(' (')[0]}"]
    svc = data.get("service") or {}
    lines.append("knowledge service  " + (f"up (answered in {svc['answered_ms']:.1f} ms)" if svc.get("reachable")
                                          else "NOT REACHABLE"))
    lines.append("hosts")
    if not data["hosts"]:
        lines.append("  (none known)")
    for h in data["hosts"]:
        free = h.get("memory_free_mb")
        mem = "-" if free is None else f"{free:.0f} MiB free" + (
            f" of {h['memory_total_mb']:.0f}" if h.get("memory_total_mb") else "")
        since = f"up since {stamp(h['online_since'], now)}" if h["up"] and h.get("online_since") else (
            "up" if h["up"] else f"DOWN, last seen {ago(h.get('last_seen'), now)}" if h.get("last_seen") else "DOWN")
        lines.append(f"  {h['host']:<10} {since:<44} {mem}")
    lines.append("detector processes")
    shown = [p for p in data["processes"] if p.get("state") != ProcessState.STOPPED]
    if not shown:
        lines.append("  (none)")
    for p in shown:
        lines.append(f"  {p.get('config')}@{p.get('host')}  {p.get('state')}  pid {p.get('pid')}  "
                     f"since {stamp(p.get('ready_at') or p.get('started_at'), now)}  ({p.get('instance')})")
    light = data.get("light")
    lines.append("light              " + ("no illumination heard" if light is None else
                                          f"level {light['level']:.1f}, band {light.get('band') or '?'} "
                                          f"(camera {light['camera']})"))
    for d in data["detection"]:
        rate = "-" if d["rate"] is None else f"{d['rate']:.0%}"
        expected = ("not calibrated for this band" if d["expected_rate"] is None
                    else f"calibrated {d['expected_rate']:.0%}")
        lines.append(f"detection rate     {rate} of {d['frames']} frames by {d['config']}@{d['host']} ({expected})")
    if not data["detection"]:
        lines.append("detection rate     no detections heard")
    f = data.get("flight")
    if f is None:
        lines.append("flight             no flight state heard")
    else:
        alt = "" if f.get("alt_rel_m") is None else f", {f['alt_rel_m']:.1f} m above home"
        lines.append(f"flight             {f['phase']}: mode {f.get('mode')}, armed {f.get('armed')}, "
                     f"landed {f.get('landed_state')}{alt}")
        if f.get("rejected") or f.get("refused"):
            refused = f.get("refused") or []
            lines.append(f"flight commands    {f.get('rejected') or 0} rejected by the autopilot"
                         + (f"; refused: {', '.join(map(str, refused))}" if refused else " (all accepted on retry)"))
    lines.append("last decisions")
    if not data["decisions"]:
        lines.append("  (none)")
    for d in data["decisions"]:
        lines.append(f"  {ago(d.get('time'), now):>12}  {d.get('trigger')} -> {d.get('config')}@{d.get('host')}: "
                     f"{d.get('outcome')}")
    if data["problems"]:
        lines.append("PROBLEMS")
        lines.extend(f"  - {p}" for p in data["problems"])
    else:
        lines.append("no problems seen")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
    endpoint = ", ".join(zenoh.connect) or (zenoh.config_file or "?")
    session = open_session(zenoh)
    try:
        def once() -> dict[str, Any]:
            return gather(session, args.robot, endpoint=endpoint, listen_s=args.window, timeout=args.timeout,
                          decisions=args.decisions)

        if args.json:
            data = once()
            print(json.dumps(data, default=str, indent=2))
            return 1 if data["problems"] else 0
        if args.once or not sys.stdout.isatty():
            data = once()
            print(render(data), flush=True)
            return 1 if data["problems"] else 0
        try:
            while True:
                screen = render(once())
                sys.stdout.write("\x1b[H\x1b[2J" + screen + f"\n\n(every {duration(args.interval)}; Ctrl-C to quit)\n")
                sys.stdout.flush()
                time.sleep(args.interval)
        except KeyboardInterrupt:
            return 0
    finally:
        session.close()
