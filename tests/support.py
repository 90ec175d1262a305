"""Helpers shared by the test folders: polling with a deadline, and child processes with their output."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

REPO = Path(__file__).resolve().parent.parent


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


class Child:
    """A child process whose stdout lines a thread collects; stderr goes to a file in ``log_dir``."""

    def __init__(self, argv: list[str], name: str, log_dir: Path, *, from_checkout: bool = True,
                 env: dict[str, str] | None = None) -> None:
        """``from_checkout=False`` runs outside this checkout (cwd ``log_dir``, no PYTHONPATH): an installed kgadapt."""
        self.name = name
        self.argv = argv
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        self.stderr_path = log_dir / f"{name}.stderr"
        base = {k: v for k, v in os.environ.items() if from_checkout or k != "PYTHONPATH"}
        if from_checkout:
            base["PYTHONPATH"] = str(REPO)
        env = {**base, "PYTHONUNBUFFERED": "1", **(env or {})}
        self._stderr = open(self.stderr_path, "w")
        self.process = subprocess.Popen(argv, cwd=REPO if from_checkout else log_dir, env=env,
                                        stdout=subprocess.PIPE, stderr=self._stderr, text=True)
        threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True).start()

    @classmethod
    def kgadapt(cls, name: str, args: list[str], log_dir: Path) -> "Child":
        """``python -m kgadapt --log-level INFO ARGS``."""
        return cls([sys.executable, "-m", "kgadapt", "--log-level", "INFO", *args], name, log_dir)

    def _read(self) -> None:
        for line in self.process.stdout:
            self.output.append(line)
            self.lines.put(line)

    def wait_for_line(self, text: str, timeout: float = 30.0) -> str:
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
            return self.stderr_path.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, timeout: float = 15.0) -> int:
        """SIGTERM, then SIGKILL after ``timeout``; returns the exit status."""
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
