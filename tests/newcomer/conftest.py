"""A machine of one's own for commands typed as a newcomer types them.

Each test gets a fresh network namespace (its own loopback: the default
ports 7447 and 14550 are free there, whatever else runs on the machine) and a
fresh home directory (the default store ``~/.local/share/kgadapt/store`` is
new and empty). :class:`Terminal` runs command lines with ``bash -c`` in that
namespace, in a working directory that holds the checkout's ``knowledge``
and ``.venv``; lines ending in ``&`` keep running until the test ends, when
they get Ctrl-C (SIGINT), as a person would stop them.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import pytest

from tests.support import REPO

_reason: list[str | None] = []


def _unavailable() -> str | None:
    if not _reason:
        from kgadapt.operator.cluster import HostNetwork

        _reason.append(HostNetwork.unavailable_reason())
    return _reason[0]


@dataclass
class Background:
    line: str
    process: subprocess.Popen
    log: Path
    stopped_in_s: float | None = None

    def text(self) -> str:
        return self.log.read_text(errors="replace")


@dataclass
class Terminal:
    namespace: str
    workdir: Path
    env: dict[str, str]
    background: list[Background] = field(default_factory=list)

    def _argv(self, line: str) -> list[str]:
        return ["ip", "netns", "exec", self.namespace, "bash", "-c", line]

    def run(self, line: str, *, timeout: float = 120.0) -> subprocess.CompletedProcess:
        """Run ``line`` to its end; the result has stdout, stderr and returncode."""
        return subprocess.run(self._argv(line), cwd=self.workdir, env=self.env, capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)

    def start(self, line: str, *, prelude: str = "", ready: str = "ready:", timeout: float = 60.0) -> Background:
        """Start ``line`` in the background (after the shell commands ``prelude``); wait for a line with
        ``ready`` (case-insensitive) in its output."""
        log = self.workdir / f"bg{len(self.background)}.log"
        out = open(log, "w")
        # exec: the shell becomes the command, so Ctrl-C (SIGINT) reaches it as it would in a terminal.
        process = subprocess.Popen(self._argv(f"{prelude} exec {line}"), cwd=self.workdir, env=self.env, stdout=out,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        job = Background(line, process, log)
        self.background.append(job)

        deadline = time.monotonic() + timeout
        while ready.lower() not in job.text().lower():
            if process.poll() is not None:
                raise AssertionError(f"{line!r} exited with {process.returncode}:\n{job.text()[-2000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{line!r} printed no {ready!r} within {timeout} s:\n{job.text()[-2000:]}")
            time.sleep(0.05)
        return job

    def interrupt_all(self, timeout: float = 20.0) -> None:
        """Ctrl-C to each background job, newest first; record how long each took to exit."""
        for job in reversed(self.background):
            if job.process.poll() is not None:
                continue
            t0 = time.monotonic()
            os.killpg(job.process.pid, signal.SIGINT)
            try:
                job.process.wait(timeout)
                job.stopped_in_s = time.monotonic() - t0
            except subprocess.TimeoutExpired:
                os.killpg(job.process.pid, signal.SIGKILL)
                job.process.wait(5)


@pytest.fixture
def terminal(tmp_path: Path) -> Iterator[Terminal]:
    why = _unavailable()
    if why:
        pytest.skip(why)
    namespace = f"kgadapt-nc-{secrets.token_hex(3)}"
    subprocess.run(["ip", "netns", "add", namespace], check=True, timeout=10)
    term = None
    try:
        # Loopback, and one ordinary interface as any real machine has: Zenoh peers advertise only
        # non-loopback addresses, and on a loopback-only host peer-to-peer data (frames to a detector)
        # does not flow at all (measured: no detections; `kgadapt status` lists that as a problem).
        for cmd in (["link", "set", "lo", "up"], ["link", "add", "nc0", "type", "veth", "peer", "name", "nc1"],
                    ["addr", "add", "10.231.0.1/24", "dev", "nc0"], ["link", "set", "nc0", "up"],
                    ["link", "set", "nc1", "up"]):
            subprocess.run(["ip", "-n", namespace, *cmd], check=True, timeout=10)
        work = tmp_path / "clone"
        work.mkdir()
        (work / "knowledge").symlink_to(REPO / "knowledge")
        venv = Path(sys.prefix)
        (work / ".venv").symlink_to(venv if (venv / "bin" / "activate").exists() else REPO / ".venv")
        home = tmp_path / "home"
        home.mkdir()
        env = {k: v for k, v in os.environ.items() if not k.startswith(("KGADAPT_", "PYTHONPATH", "VIRTUAL_ENV"))}
        env.update(HOME=str(home), PYTHONUNBUFFERED="1",
                   PATH=os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if ".venv" not in p))
        term = Terminal(namespace, work, env)
        yield term
    finally:
        if term is not None:
            term.interrupt_all()
        subprocess.run(["ip", "netns", "del", namespace], timeout=10)
        shutil.rmtree(tmp_path / "home" / ".local", ignore_errors=True)
