"""The agents speak systemd's notify protocol: READY=1 when serving, WATCHDOG=1 while healthy, STOPPING=1.

A real AF_UNIX datagram socket stands where systemd's would be
(``$NOTIFY_SOCKET``, ``$WATCHDOG_USEC``), and the real agent and knowledge
service run as child processes.
"""

from __future__ import annotations

import socket
import sys
import time

import pytest

from kgadapt.shared.notifier import ServiceNotifier
from tests.conftest import free_port
from tests.support import Child


class NotifySocket:
    def __init__(self, path) -> None:
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)

    def next(self, timeout: float) -> str:
        self.sock.settimeout(timeout)
        return self.sock.recv(4096).decode()

    def wait_for(self, prefix: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no {prefix!r} notification within {timeout} s")
            try:
                message = self.next(left)
            except socket.timeout:
                continue
            if message.startswith(prefix):
                return message

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def notify(tmp_path):
    s = NotifySocket(tmp_path / "notify.sock")
    yield s
    s.close()


@pytest.mark.parametrize("command", [
    ["remote", "--host", "remote"],
    ["knowledge", "serve", "--store", "embedded:{tmp}/store"],
])
def test_ready_watchdog_and_stopping_reach_the_notify_socket(notify, tmp_path, command):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = [a.format(tmp=tmp_path) for a in command]
    args += ["--listen", endpoint] if command[0] == "knowledge" else ["--connect", endpoint]
    child = Child([sys.executable, "-m", "kgadapt", "--log-level", "INFO", *args], "agent", tmp_path,
                  env={"NOTIFY_SOCKET": notify.path, "WATCHDOG_USEC": "1000000"})
    try:
        ready = notify.wait_for("READY=1", timeout=60)
        assert "STATUS=" in ready and "ready" in ready
        first = notify.wait_for("WATCHDOG=1", timeout=5)
        assert first == "WATCHDOG=1"
        notify.wait_for("WATCHDOG=1", timeout=5)  # and again: fed for as long as it is healthy
        child.process.terminate()
        notify.wait_for("STOPPING=1", timeout=30)
    finally:
        assert child.stop() == 0


def test_the_notifier_is_silent_without_systemd_and_understands_abstract_sockets():
    quiet = ServiceNotifier({})
    assert not quiet.enabled
    quiet.ready("x")  # nothing to send to: no error
    abstract = ServiceNotifier({"NOTIFY_SOCKET": "@/org/freedesktop/systemd1/notify", "WATCHDOG_USEC": "4000000"})
    assert abstract.address == "\0/org/freedesktop/systemd1/notify" and abstract.watchdog_interval == 2.0
    # WATCHDOG_PID names another process: the watchdog is not ours to feed.
    assert ServiceNotifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}).watchdog_interval is None


def test_a_vanished_notify_socket_never_stops_the_process(tmp_path, caplog):
    notifier = ServiceNotifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    notifier.ready()
    notifier.stopping()
    assert sum("cannot notify" in r.message for r in caplog.records) == 1
