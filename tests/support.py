"""Helpers shared by the test folders: polling with a deadline, child processes of ours (the one launcher), and
hosts as network namespaces."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest

from kgadapt.shared.children import ChildProcess, StopPolicy
from kgadapt.shared.readiness import Payload

REPO = Path(__file__).resolve().parent.parent


@contextlib.contextmanager
def host_network(hosts: tuple[str, ...], subnet: str) -> Iterator[Any]:
    """``hosts`` as network namespaces on a bridge (kgadapt.operator.cluster.HostNetwork), removed afterwards;
    the test is skipped, naming why, where namespaces cannot be made."""
    from kgadapt.operator.cluster import HostNetwork, NetworkSettings

    reason = HostNetwork.unavailable_reason()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    network = HostNetwork(NetworkSettings(hosts=hosts, subnet=subnet))
    network.setup()
    try:
        yield network
    finally:
        network.shutdown()


def wait_for(predicate: Callable[[], object], timeout: float, what: str, interval: float = 0.02) -> Any:
    """Poll ``predicate`` until it returns something truthy; fail naming ``what`` after ``timeout`` s.

    An exception from the predicate counts as "not yet"; the last one is shown on failure.
    """
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while True:
        try:
            value = predicate()
            if value:
                return value
        except Exception as exc:
            last = exc
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what} (last error: {last})")
        time.sleep(interval)


class Child(ChildProcess):
    """A child process of ours (kgadapt.shared.children) whose stderr goes to a file in ``log_dir``."""

    def __init__(self, argv: list[str], name: str, log_dir: Path, *, from_checkout: bool = True,
                 env: dict[str, str] | None = None) -> None:
        """``from_checkout=False`` runs outside this checkout (cwd ``log_dir``, no PYTHONPATH): an installed kgadapt."""
        base = {k: v for k, v in os.environ.items() if from_checkout or k != "PYTHONPATH"}
        if from_checkout:
            base["PYTHONPATH"] = str(REPO)
        self.stderr_path = log_dir / f"{name}.stderr"
        super().__init__(argv, name=name, env={**base, "PYTHONUNBUFFERED": "1", **(env or {})},
                         cwd=REPO if from_checkout else log_dir, log=self.stderr_path, log_stdout=False)

    @classmethod
    def kgadapt(cls, name: str, args: list[str], log_dir: Path) -> "Child":
        """``python -m kgadapt --log-level INFO ARGS``."""
        return cls([sys.executable, "-m", "kgadapt", "--log-level", "INFO", *args], name, log_dir)

    def wait_ready(self, timeout: float = 30.0) -> Payload:
        return super().wait_ready(timeout)

    def stderr(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def stop(self, timeout: float = 15.0, *, first: int = signal.SIGINT) -> int:  # type: ignore[override]
        """SIGINT, SIGTERM, SIGKILL (from ``first`` on), ``timeout`` in all; returns the exit status."""
        return super().stop(StopPolicy(sigint_timeout=timeout / 2, sigterm_timeout=timeout / 2, sigkill_timeout=5.0),
                            first=first)

    def kill9(self) -> None:
        """SIGKILL to the child itself (not its group), as ``kill -9 PID``."""
        self.process.kill()
        self.process.wait()


def detections(ids: list[Any], corners: list[Any], **fields: Any) -> Any:
    """A ``detections`` message with ``ids`` and ``corners`` (the other required fields filled in)."""
    from kgadapt.shared import messages

    base: dict[str, Any] = {"instance": "d1", "config": "c", "host": "onboard", "seq": 1, "frame_time": 1.0,
                            "time": 1.0, "processing_ms": 1.0}
    return messages.Detections(ids=ids, corners=corners, **{**base, **fields})
