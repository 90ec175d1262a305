"""Fixtures of the Zenoh fabric tests: loopback sessions, an in-process service, child processes."""

from __future__ import annotations

import itertools
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import pytest

from knowledge.client import KnowledgeClient
from knowledge.schema import ensure_indexes
from knowledge.service import KnowledgeService, ServiceSettings
from shared import keys
from shared.session import ZenohSettings, open_session
from tests.conftest import REPO, free_port

_robots = itertools.count()


def wait_for(predicate: Callable[[], object], timeout: float, what: str, interval: float = 0.01):
    """Poll ``predicate`` until it returns something truthy; fail naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    last_error: Exception | None = None
    while True:
        try:
            value = predicate()
            if value:
                return value
        except Exception as exc:  # keep polling; report the last error on failure
            last_error = exc
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what} (last error: {last_error})")
        time.sleep(interval)


def platform_row(client: KnowledgeClient, name: str) -> dict | None:
    for row in client.query("platforms", {}):
        if row["platform"] == name:
            return row
    return None


@pytest.fixture
def robot() -> str:
    """A robot name of its own, so tests never see each other's keys."""
    return f"r{os.getpid()}x{next(_robots)}"


@pytest.fixture(scope="module")
def zenoh_pair():
    """Two peer sessions on loopback: (server side listening, client side connected to it)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    client = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    # The first get may race the connection being set up; wait until the link is there.
    deadline = time.monotonic() + 5
    while not list(client.info.peers_zid()) and time.monotonic() < deadline:
        time.sleep(0.01)
    yield server, client
    client.close()
    server.close()


@pytest.fixture
def service(resp_store, zenoh_pair, robot):
    """An in-process knowledge service on the test's own graph and robot name."""
    server, _ = zenoh_pair
    ensure_indexes(resp_store)  # as `kgadapt knowledge serve` does; it also creates the graph
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot))
    svc.setup(server)
    yield svc
    svc.shutdown()


def wait_until_serving(session, robot: str, *, writes: bool = True, timeout: float = 5.0) -> None:
    """Wait until the service's queryables are known on ``session``'s side.

    A declaration takes a moment to reach another peer; a get sent before
    that finds no queryable and gets no reply at all.
    """
    probes = [keys.knowledge_query(robot, "platforms"), keys.knowledge_cypher(robot)]
    if writes:
        probes.append(keys.knowledge_write(robot, "probe"))  # an unknown verb: any reply will do
    for key in probes:
        wait_for(lambda: list(session.get(key, timeout=1)), timeout, f"a reply on {key}")


@pytest.fixture
def client(zenoh_pair, robot, service) -> KnowledgeClient:
    _, session = zenoh_pair
    wait_until_serving(session, robot, writes=service.settings.writes)
    return KnowledgeClient(session, robot, timeout=3.0)


class Child:
    """A ``kgadapt`` child process whose stdout lines are collected by a thread."""

    def __init__(self, argv: list[str], name: str, log_dir: Path) -> None:
        self.name = name
        self.argv = argv
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        self.stderr_path = log_dir / f"{name}.stderr"
        env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
        self._stderr = open(self.stderr_path, "w")
        self.process = subprocess.Popen(
            argv, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=self._stderr, text=True,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.output.append(line)
            self.lines.put(line)

    def wait_for_line(self, text: str, timeout: float = 15.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.name}: no line with {text!r} within {timeout} s; stderr:\n{self.stderr()}")
            try:
                line = self.lines.get(timeout=min(left, 0.2))
            except queue.Empty:
                if self.process.poll() is not None:
                    raise AssertionError(f"{self.name} exited with {self.process.returncode}; stderr:\n{self.stderr()}")
                continue
            if text in line:
                return line

    def stderr(self) -> str:
        try:
            return self.stderr_path.read_text()[-4000:]
        except OSError:
            return ""

    def stop(self, timeout: float = 10.0) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._stderr.close()
        return self.process.returncode

    def kill9(self) -> None:
        self.process.kill()
        self.process.wait()


@pytest.fixture
def children(tmp_path):
    """Start ``kgadapt`` children; every one still running is stopped at teardown, also on failure."""
    started: list[Child] = []

    def start(name: str, *args: str) -> Child:
        child = Child([sys.executable, "-m", "kgadapt", "--log-level", "INFO", *args], name, tmp_path)
        started.append(child)
        return child

    yield start
    for child in reversed(started):
        child.stop()
