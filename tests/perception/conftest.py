"""Fixtures of the perception tests: a Zenoh session on loopback, detector processes, collectors."""

from __future__ import annotations

import itertools
import os
import queue
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

import pytest

from kgadapt.shared import messages
from kgadapt.shared.readiness import Payload
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.support import Child, wait_for  # noqa: F401 (the tests import wait_for from here)

_robots = itertools.count()

# The cheap default, and a configuration made for the dark (both as the calibration ranks them).
DAY_JSON = '{"dictionary": "DICT_4X4_50", "preprocess": [], "parameters": {"cornerRefinementMethod": 1}}'


@pytest.fixture
def robot() -> str:
    """A robot name of its own, so tests never see each other's keys."""
    return f"p{os.getpid()}x{next(_robots)}"


@pytest.fixture(scope="module")
def endpoint_session():
    """A peer session listening on a free loopback port: ``(endpoint, session)``."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    yield endpoint, session
    session.close()


class Collector:
    """Decoded messages of one kind from a key expression, handed over by a queue."""

    def __init__(self, session: Any, key: str, kind: str) -> None:
        self.kind = kind
        self.items: queue.Queue[dict[str, Any]] = queue.Queue()
        self._sub = session.declare_subscriber(key, lambda s: self.items.put(s.payload.to_bytes()))

    def next(self, timeout: float = 10.0) -> dict[str, Any]:
        return messages.decode(self.items.get(timeout=timeout), self.kind)

    def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout: float = 10.0, what: str = "a message"):
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no {self.kind} message with {what} within {timeout} s")
            try:
                item = self.next(timeout=left)
            except queue.Empty:
                continue
            if predicate(item):
                return item

    def close(self) -> None:
        self._sub.undeclare()


class DetectorProcess(Child):
    """``python -m kgadapt.onboard.perception.detector`` as a child of ours (tests.support.Child)."""

    def __init__(self, args: list[str], log_dir: Path, name: str) -> None:
        super().__init__([sys.executable, "-m", "kgadapt.onboard.perception.detector", *args], name, log_dir)

    def wait_ready(self, timeout: float = 20.0) -> Payload:
        return super().wait_ready(timeout)

    def wait(self, timeout: float = 10.0) -> int:
        return self.process.wait(timeout)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:  # type: ignore[override]
        """``sig`` first, then on up the escalation (SIGTERM, SIGKILL)."""
        return super().stop(timeout, first=sig)


@pytest.fixture
def detectors(tmp_path):
    """Start detector processes; each one still running is stopped at teardown, also on failure."""
    started: list[DetectorProcess] = []

    def start(*args: str) -> DetectorProcess:
        child = DetectorProcess(list(args), tmp_path, f"detector{len(started)}")
        started.append(child)
        return child

    yield start
    for child in reversed(started):
        child.stop()
