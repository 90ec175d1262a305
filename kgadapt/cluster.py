"""A whole robot on one machine: knowledge service, remote agent, fake flight controller, onboard agent.

Used by ``kgadapt demo``, the adaptation tests and ``kgadapt bench adaptation``.
Every process is a real child (``python -m kgadapt ...``) in its own process
group; ``start()`` waits on each one's readiness line with a bounded wait and
raises with its log tail; ``stop()`` asks politely (SIGINT), then SIGTERM,
then SIGKILL, and always runs, even after a failed start.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from shared.errors import KgadaptError

REPO = Path(__file__).resolve().parent.parent
MODELS = REPO / "knowledge" / "models"


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True, kw_only=True)
class ClusterSettings:
    """What to run. Budgets make two agents on one machine behave as two hosts."""

    workdir: Path
    robot: str = "quad1"
    profile: str | None = None  # synthetic camera profile file; None: the shipped demo scenario
    scenario_speed: float = 1.0
    onboard_budget: str = "700M"
    remote_budget: str = "4G"
    fps: float = 30.0
    adapt: bool = True
    prefer: str = "onboard-first"
    dwell_s: float = 1.0
    calibrate: bool = True
    fake_fc: bool = True
    land_after_s: float | None = None  # fake FC starts a final descent after this many seconds
    log_level: str = "INFO"
    start_timeout: float = 30.0
    extra_onboard_args: tuple[str, ...] = ()


@dataclass
class Child:
    name: str
    process: subprocess.Popen[str]
    log_path: Path
    ready: threading.Event = field(default_factory=threading.Event)
    lines: list[str] = field(default_factory=list)

    def tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return "(no log)"


class LocalCluster:
    """Start and stop the robot's processes on loopback. ``__init__`` does no I/O."""

    def __init__(self, settings: ClusterSettings) -> None:
        self.settings = settings
        self.port = 0
        self.fc_port = 0
        self.children: dict[str, Child] = {}
        self.store_url = f"embedded:{settings.workdir / 'store'}"

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def kgadapt(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "kgadapt", "--log-level", self.settings.log_level, *args]

    def prepare_store(self) -> list[str]:
        """Load the models (and calibrate) into a fresh store; returns what was printed."""
        s = self.settings
        s.workdir.mkdir(parents=True, exist_ok=True)
        out = []
        steps = [self.kgadapt("knowledge", "load", str(MODELS), "--store", self.store_url)]
        if s.calibrate:
            steps.append(self.kgadapt("perception", "calibrate", "--store", self.store_url,
                                      "--out", str(s.workdir / "calibration.json"),
                                      "--plot", str(s.workdir / "calibration.png")))
        for argv in steps:
            result = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=REPO)
            if result.returncode != 0:
                raise KgadaptError(f"{' '.join(argv[3:6])} failed: {result.stderr.strip()[-500:]}")
            out.append(result.stdout)
        return out

    def start(self) -> None:
        """Start service, remote agent, fake FC and onboard agent, each waited for."""
        s = self.settings
        self.port = free_tcp_port()
        self.fc_port = free_udp_port()
        connect = ("--connect", self.endpoint)
        try:
            self._spawn("service", self.kgadapt("knowledge", "serve", "--robot", s.robot, "--store", self.store_url,
                                                "--listen", self.endpoint), ready="service ready")
            self._spawn("remote", self.kgadapt("remote", "--robot", s.robot, "--host", "remote",
                                               "--memory-budget", s.remote_budget, *connect), ready="agent ready")
            onboard = ["onboard", "--robot", s.robot, "--host", "onboard", "--memory-budget", s.onboard_budget,
                       "--camera-source", f"synthetic:{s.profile}" if s.profile else "synthetic",
                       "--fps", str(s.fps), "--scenario-speed", str(s.scenario_speed), *connect]
            if s.fake_fc:
                fc = ["flight", "fake-fc", "--url", f"udpout:127.0.0.1:{self.fc_port}", "--armed"]
                if s.land_after_s is not None:
                    fc += ["--land-after", str(s.land_after_s)]
                self._spawn("fake-fc", self.kgadapt(*fc), ready="KGADAPT_READY")
                onboard += ["--fc", f"udpin:127.0.0.1:{self.fc_port}"]
            if s.adapt:
                onboard += ["--adapt", "--prefer", s.prefer, "--dwell", str(s.dwell_s)]
            self._spawn("onboard", self.kgadapt(*onboard, *s.extra_onboard_args), ready="agent ready")
        except BaseException:
            self.stop()
            raise

    def _spawn(self, name: str, argv: Sequence[str], *, ready: str | None) -> Child:
        log_path = self.settings.workdir / f"{name}.log"
        log_file = open(log_path, "w")
        process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=log_file, stdin=subprocess.DEVNULL,
                                   text=True, cwd=REPO, start_new_session=True)
        child = Child(name, process, log_path)
        self.children[name] = child

        def pump() -> None:  # stdout to the log and the readiness line to an event
            for line in process.stdout:
                child.lines.append(line.rstrip())
                log_file.write(line)
                log_file.flush()
                if ready is None or ready in line or "KGADAPT_READY" in line:
                    child.ready.set()
            log_file.close()

        threading.Thread(target=pump, name=f"{name}-stdout", daemon=True).start()
        if ready is None:
            return child
        deadline = time.monotonic() + self.settings.start_timeout
        while not child.ready.wait(0.05):
            if process.poll() is not None or time.monotonic() > deadline:
                why = f"exited with {process.returncode}" if process.poll() is not None else "was not ready in time"
                raise KgadaptError(f"{name} {why}; last log lines:\n{child.tail()}")
        return child

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to one process's whole group (e.g. kill -9 of the remote agent and its detectors' parent)."""
        child = self.children[name]
        try:
            os.killpg(child.process.pid, sig)
        except ProcessLookupError:
            pass
        if sig == signal.SIGKILL:
            child.process.wait(10)

    def stop(self, timeout: float = 8.0) -> dict[str, int | None]:
        """Stop every child, newest first: SIGINT, then SIGTERM, then SIGKILL."""
        codes: dict[str, int | None] = {}
        for name in reversed(list(self.children)):
            child = self.children[name]
            p = child.process
            for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, timeout / 2), (signal.SIGKILL, 5.0)):
                if p.poll() is not None:
                    break
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    p.wait(wait)
                except subprocess.TimeoutExpired:
                    continue
            codes[name] = p.poll()
        self.children.clear()
        return codes

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
