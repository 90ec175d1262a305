"""A whole robot on one machine: knowledge service, remote agent, fake flight controller, onboard agent.

Used by ``kgadapt demo``, the adaptation tests and ``kgadapt bench adaptation``.
Every process is a real child (``python -m kgadapt ...``) started by
:class:`kgadapt.shared.children.ChildProcess` in its own process group;
``start()`` waits on each one's readiness line (kgadapt.shared.readiness)
with a bounded wait and raises with its log tail; ``stop()`` asks politely
(SIGINT), then SIGTERM, then SIGKILL, and always runs, even after a failed start.

With a :class:`HostNetwork` (the fault tests and ``kgadapt bench
reliability``), the hosts are Linux network namespaces on one bridge: the
knowledge service and the onboard agent run in the ``onboard`` namespace, the
remote agent in ``remote``, and Zenoh runs over their veth addresses, so a
host's link can be cut and restored (``ip link set ... down``).
"""

from __future__ import annotations

import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence, TypeVar

from kgadapt.shared.children import ChildProcess, StopPolicy
from kgadapt.shared.errors import DeploymentError, KgadaptError, TransportError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.resources import models

if TYPE_CHECKING:
    import zenoh

_T = TypeVar("_T")


def _free_port(kind: int) -> int:
    # Below Linux's ephemeral range (32768-60999): a port the kernel hands out for port 0 is also
    # what any process's next outgoing connection may take before ours binds it (seen with two test
    # workers: "Address already in use"). Random, so two callers rarely pick the same one.
    for _ in range(200):
        port = random.randrange(20000, 32000)
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise TransportError("no free loopback port in 20000-32000")


def free_tcp_port() -> int:
    return _free_port(socket.SOCK_STREAM)


def free_udp_port() -> int:
    return _free_port(socket.SOCK_DGRAM)


@dataclass(frozen=True, kw_only=True)
class ClusterSettings:
    """What to run. Budgets make two agents on one machine behave as two hosts."""

    workdir: Path
    robot: str = DEFAULT_ROBOT
    profile: str | None = None  # synthetic camera profile file; None: the shipped demo scenario
    scenario_speed: float = 1.0
    onboard_budget: str = "700M"
    remote_budget: str = "4G"
    fps: float = 30.0
    adapt: bool = True
    prefer: str = "onboard-first"
    dwell_s: float = 1.0
    in_place: bool = True  # False: the onboard agent's --no-in-place (every change a new process)
    standby: bool = False  # the onboard agent's --standby (a warm standby for the neighbouring band)
    calibrate: bool = True
    fake_fc: bool = True
    land_after_s: float | None = None  # fake FC starts a final descent after this many seconds
    descent_s: float = 5.0  # ... lasting this long (LANDING, then ON_GROUND)
    log_level: str = "INFO"
    start_timeout: float = 30.0
    extra_onboard_args: tuple[str, ...] = ()
    extra_remote_args: tuple[str, ...] = ()
    # Zenoh mode of both agents (and, through their deployers, of the detectors they start);
    # None: their default (peer). "client" sends all traffic through the service's router.
    agent_mode: str | None = None
    env: tuple[tuple[str, str], ...] = ()  # extra environment of every child (e.g. ZENOH_RUNTIME)
    # The camera as a process of its own ("camera": kgadapt perception camera) instead of a part of the
    # onboard agent, so the agent (its adaptation manager) can be stopped while frames keep coming.
    camera_process: bool = False
    models: Path | None = None  # the model folder to load (None: the shipped models)


@dataclass(frozen=True)
class _Recipe:
    """How a child was started, to start it again (``respawn``)."""

    argv: tuple[str, ...]
    ready: bool
    host: str | None  # the network namespace's host it runs in (None: this machine's network)


class LocalCluster:
    """Start and stop the robot's processes on loopback. ``__init__`` does no I/O.

    With ``network`` (set up by the caller) each process runs in its host's
    namespace and the service listens on the onboard host's address.
    """

    def __init__(self, settings: ClusterSettings, *, network: "HostNetwork | None" = None) -> None:
        self.settings = settings
        self.network = network
        self.port = 0
        self.fc_port = 0
        self.children: dict[str, ChildProcess] = {}
        self._recipes: dict[str, _Recipe] = {}
        self.store_url = f"embedded:{settings.workdir / 'store'}"

    @property
    def endpoint(self) -> str:
        host = self.network.address("onboard") if self.network else "127.0.0.1"
        return f"tcp/{host}:{self.port}"

    def kgadapt(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "kgadapt", "--log-level", self.settings.log_level, *args]

    def prepare_store(self) -> list[str]:
        """Load the models (and calibrate) into a fresh store; returns what was printed."""
        s = self.settings
        s.workdir.mkdir(parents=True, exist_ok=True)
        out = []
        steps = [self.kgadapt("knowledge", "load", str(s.models or models()), "--store", self.store_url)]
        if s.calibrate:
            steps.append(self.kgadapt("perception", "calibrate", "--store", self.store_url,
                                      "--out", str(s.workdir / "calibration.json"),
                                      "--plot", str(s.workdir / "calibration.png")))
        for argv in steps:
            try:
                # Within a test's own time limit (120 s), so that a step that hangs says what it printed.
                result = subprocess.run(argv, capture_output=True, text=True, timeout=90)
            except subprocess.TimeoutExpired as exc:
                printed = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else exc.stderr or ""
                raise KgadaptError(f"{' '.join(argv[3:6])} did not end within 90 s; it printed: "
                                   f"{printed.strip()[-1500:] or 'nothing'}") from exc
            if result.returncode != 0:
                raise KgadaptError(f"{' '.join(argv[3:6])} failed: {result.stderr.strip()[-500:]}")
            out.append(result.stdout)
        return out

    def start(self) -> None:
        """Start service, remote agent, fake FC and onboard agent, each waited for."""
        s = self.settings
        self.port = free_tcp_port()
        self.fc_port = free_udp_port()
        connect: tuple[str, ...] = ("--connect", self.endpoint)
        if s.agent_mode:
            connect += ("--mode", s.agent_mode)
        try:
            self._spawn("service", self.kgadapt("knowledge", "serve", "--robot", s.robot, "--store", self.store_url,
                                                "--listen", self.endpoint), host="onboard")
            self._spawn("remote", self.kgadapt("remote", "--robot", s.robot, "--host", "remote",
                                               "--memory-budget", s.remote_budget, *connect, *s.extra_remote_args),
                        host="remote")
            source = f"synthetic:{s.profile}" if s.profile else "synthetic"
            onboard = ["onboard", "--robot", s.robot, "--host", "onboard", "--memory-budget", s.onboard_budget,
                       *connect]
            if s.camera_process:
                self._spawn("camera", self.kgadapt("perception", "camera", "--robot", s.robot, "--source", source,
                                                   "--fps", str(s.fps), "--speed", str(s.scenario_speed), *connect),
                            ready=False, host="onboard")
            else:
                onboard += ["--camera-source", source, "--fps", str(s.fps), "--scenario-speed", str(s.scenario_speed)]
            if s.fake_fc:
                fc = ["flight", "fake-fc", "--url", f"udpout:127.0.0.1:{self.fc_port}", "--armed"]
                if s.land_after_s is not None:
                    fc += ["--land-after", str(s.land_after_s), "--descent", str(s.descent_s)]
                self._spawn("fake-fc", self.kgadapt(*fc), host="onboard")
                onboard += ["--fc", f"udpin:127.0.0.1:{self.fc_port}"]
            if s.adapt:
                onboard += ["--adapt", "--prefer", s.prefer, "--dwell", str(s.dwell_s)]
                if not s.in_place:
                    onboard.append("--no-in-place")
                if s.standby:
                    onboard.append("--standby")
            self._spawn("onboard", self.kgadapt(*onboard, *s.extra_onboard_args), host="onboard")
        except BaseException:
            self.stop()
            raise

    def _spawn(self, name: str, argv: Sequence[str], *, ready: bool = True, host: str | None = None,
               append: bool = False) -> ChildProcess:
        where = host if self.network is not None else None
        command = self.network.run_in(where, argv) if self.network is not None and where else list(argv)
        env = {**os.environ, **dict(self.settings.env)} if self.settings.env else None
        child = ChildProcess(command, name=name, env=env, log=self.settings.workdir / f"{name}.log", append=append)
        self.children[name] = child
        self._recipes[name] = _Recipe(tuple(argv), ready, where)
        if ready:
            child.wait_ready(self.settings.start_timeout)
        return child

    def spawn(self, name: str, argv: Sequence[str], *, ready: bool = True) -> ChildProcess:
        """Start one more process of this cluster (logged, stopped by ``stop()``); with ``ready``, wait for its readiness line."""
        return self._spawn(name, argv, ready=ready)

    def respawn(self, name: str) -> ChildProcess:
        """Start a stopped or killed process again with the same command line (and wait for it).

        It runs where it ran before (its host's namespace), appends to its log, and
        counts as the newest child (``stop()`` stops it first).
        """
        old = self.children[name]
        if old.alive():
            raise KgadaptError(f"{name} is still running (pid {old.pid}); stop it first")
        del self.children[name]
        recipe = self._recipes[name]
        return self._spawn(name, recipe.argv, ready=recipe.ready, host=recipe.host, append=True)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to one process's whole group (e.g. kill -9 of the remote agent and its detectors' parent)."""
        child = self.children[name]
        child.send_signal(sig)
        if sig == signal.SIGKILL:
            child.process.wait(10)

    def stop(self, timeout: float = 8.0) -> dict[str, int | None]:
        """Stop every child, newest first: SIGINT, then SIGTERM, then SIGKILL."""
        policy = StopPolicy(sigint_timeout=timeout, sigterm_timeout=timeout / 2, sigkill_timeout=5.0)
        codes: dict[str, int | None] = {}
        for name in reversed(list(self.children)):
            try:
                codes[name] = self.children[name].stop(policy)
            except DeploymentError:  # survived SIGKILL: reported as still running, the others are stopped anyway
                codes[name] = None
        self.children.clear()
        return codes

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- hosts as network namespaces ------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class NetworkSettings:
    """Which hosts to make and how to address them.

    ``tag`` makes every name unique to this run (namespaces ``kgadapt-<host>-<tag>``,
    the bridge's ``kgadapt-sw-<tag>``), so that a run never touches namespaces it did
    not create. The subnet exists only inside those namespaces.
    """

    hosts: tuple[str, ...] = ("onboard", "remote", "robot2")
    subnet: str = "10.213.7"  # a /24 of our own: host i gets <subnet>.<i + 1>
    tag: str = field(default_factory=lambda: secrets.token_hex(3))
    command_timeout: float = 10.0

    def __post_init__(self) -> None:
        if not 1 <= len(self.hosts) <= 250 or len(set(self.hosts)) != len(self.hosts):
            raise KgadaptError(f"network hosts {self.hosts!r}: give 1 to 250 distinct names")
        for host in self.hosts:
            if not host.isalnum() or len(host) > 12:
                raise KgadaptError(f"network host {host!r}: use at most 12 letters and digits (interface names)")


class HostNetwork:
    """Hosts as Linux network namespaces, each linked by a veth pair to a bridge in a namespace of its own.

    Nothing is added to the namespace this process runs in: traffic flows only
    between the namespaces made here. ``cut(host)`` takes the host's port on the
    bridge down (its cable is pulled); ``heal(host)`` brings it back.
    ``shutdown()`` kills whatever still runs inside the namespaces (only our
    processes can be there) and deletes them; it is safe after a failed setup.
    Needs root (CAP_SYS_ADMIN, CAP_NET_ADMIN) and iproute2's ``ip``.
    """

    def __init__(self, settings: NetworkSettings | None = None) -> None:
        self.settings = settings or NetworkSettings()
        self._created: list[str] = []

    @property
    def switch(self) -> str:
        return f"kgadapt-sw-{self.settings.tag}"

    def namespace(self, host: str) -> str:
        self._index(host)
        return f"kgadapt-{host}-{self.settings.tag}"

    def address(self, host: str) -> str:
        return f"{self.settings.subnet}.{self._index(host) + 1}"

    def port(self, host: str) -> str:
        """The bridge port (interface in the switch namespace) of ``host``'s link."""
        self._index(host)
        return f"to-{host}"

    def run_in(self, host: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside ``host``'s namespace (``ip netns exec`` execs it: the PID stays the program's)."""
        return ["ip", "netns", "exec", self.namespace(host), *argv]

    @staticmethod
    def unavailable_reason() -> str | None:
        """Why network namespaces cannot be made here, or None when they can."""
        if os.geteuid() != 0:
            return "network namespaces need root (CAP_SYS_ADMIN and CAP_NET_ADMIN)"
        if shutil.which("ip") is None:
            return "iproute2's ip command is not installed"
        probe = f"kgadapt-probe-{secrets.token_hex(3)}"
        made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True, timeout=10)
        if made.returncode != 0:
            return f"ip netns add failed: {made.stderr.strip() or made.returncode}"
        subprocess.run(["ip", "netns", "del", probe], capture_output=True, timeout=10)
        return None

    def setup(self) -> None:
        """Make the namespaces, the bridge and one link per host; raise TransportError naming a failed step."""
        s = self.settings
        try:
            self._ip("netns", "add", self.switch)
            self._created.append(self.switch)
            sw = ("-n", self.switch)
            self._ip(*sw, "link", "add", "br0", "type", "bridge")
            self._ip(*sw, "link", "set", "br0", "up")
            for host in s.hosts:
                ns = self.namespace(host)
                self._ip("netns", "add", ns)
                self._created.append(ns)
                port = self.port(host)
                # Both ends are made from the switch's side: the host's end moves straight into its namespace.
                self._ip(*sw, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", ns)
                self._ip(*sw, "link", "set", port, "master", "br0")
                self._ip(*sw, "link", "set", port, "up")
                self._ip("-n", ns, "link", "set", "lo", "up")
                self._ip("-n", ns, "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
                self._ip("-n", ns, "link", "set", "eth0", "up")
        except BaseException:
            self.shutdown()
            raise

    def cut(self, host: str) -> float:
        """Pull ``host``'s cable; returns the time (epoch seconds) it was done."""
        self._ip("-n", self.switch, "link", "set", self.port(host), "down")
        return time.time()

    def heal(self, host: str) -> float:
        """Plug ``host``'s cable back in; returns the time it was done."""
        self._ip("-n", self.switch, "link", "set", self.port(host), "up")
        return time.time()

    def inode(self, host: str) -> int:
        """The namespace's inode: compare with ``os.stat(f"/proc/{pid}/ns/net").st_ino`` to find its processes."""
        return os.stat(f"/run/netns/{self.namespace(host)}").st_ino

    def pids(self, host: str) -> list[int]:
        """Processes running in ``host``'s namespace."""
        out = subprocess.run(["ip", "netns", "pids", self.namespace(host)], capture_output=True, text=True,
                             timeout=self.settings.command_timeout)
        return [int(p) for p in out.stdout.split()]

    def shutdown(self, timeout: float = 5.0) -> None:
        """Kill what still runs in our namespaces and delete them (ours only, newest first)."""
        while self._created:
            ns = self._created.pop()
            deadline = time.monotonic() + timeout
            while True:
                out = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=10)
                pids = [int(p) for p in out.stdout.split()]
                if not pids or time.monotonic() > deadline:
                    break
                for pid in pids:
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                time.sleep(0.05)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)

    def _index(self, host: str) -> int:
        try:
            return self.settings.hosts.index(host)
        except ValueError:
            raise KgadaptError(f"host {host!r} is not in this network ({', '.join(self.settings.hosts)})") from None

    def _ip(self, *args: str) -> None:
        try:
            done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=self.settings.command_timeout)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise TransportError(f"ip {' '.join(args)}: {exc}") from exc
        if done.returncode != 0:
            raise TransportError(f"ip {' '.join(args)} failed: {done.stderr.strip() or done.returncode}")

    def __enter__(self) -> "HostNetwork":
        self.setup()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


def models_without_in_place(folder: Path) -> Path:
    """A copy of the shipped models in ``folder`` whose detector deployments may not change in place (no
    ``reconfigurable_as``): every change of configuration is a new process, as the graph says."""
    shutil.copytree(models(), folder, dirs_exist_ok=True)
    for path in (folder / "deployments").iterdir():
        lines = path.read_text().splitlines(keepends=True)
        path.write_text("".join(line for line in lines if not line.lower().replace(" ", "").startswith(
            ("reconfigurable_as:", "reconfigurableas="))))
    return folder


def write_profile(path: Path, points: list[list[float]], *, loop: bool = False) -> str:
    """Write a synthetic-camera illumination profile (see onboard/perception/scenarios/README.md); returns its path."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"points": points, "noise": 2.0, "gradient": 0.2, "loop": loop}))
    return str(path)


class WatchedRobot:
    """A :class:`LocalCluster` with a :class:`kgadapt.operator.timeline.Recorder` watching it over Zenoh.

    ``with WatchedRobot(settings) as robot:`` loads (and calibrates) the store,
    starts the processes, and attaches the recorder; leaving stops everything.
    """

    def __init__(self, settings: ClusterSettings) -> None:
        from kgadapt.operator.timeline import Recorder

        self.cluster = LocalCluster(settings)
        self.recorder = Recorder(robot=settings.robot)
        self.session: zenoh.Session | None = None
        self.prepared: list[str] = []  # what loading (and calibrating) printed
        self.timings: dict[str, float] = {}  # seconds: prepare, start
        self.exit_codes: dict[str, int | None] = {}  # of every process, after leaving

    def __enter__(self) -> "WatchedRobot":
        from kgadapt.shared.session import ZenohSettings, open_session

        t = time.perf_counter()
        self.prepared = self.cluster.prepare_store()
        self.timings["prepare"] = time.perf_counter() - t
        try:
            t = time.perf_counter()
            self.cluster.start()
            self.timings["start"] = time.perf_counter() - t
            self.recorder.t0 = time.time()
            self.session = open_session(ZenohSettings(mode="peer", connect=(self.cluster.endpoint,)))
            self.recorder.setup(self.session)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.recorder.shutdown()
            if self.session is not None:
                self.session.close()
                self.session = None
        finally:
            self.exit_codes = self.cluster.stop()

    def wait(self, predicate: Callable[[], _T], timeout: float, interval: float = 0.02) -> _T | None:
        """The predicate's first truthy value within ``timeout`` seconds, else None."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            value = predicate()
            if value:
                return value
            time.sleep(interval)
        return None
