"""systemd's notify protocol (sd_notify(3)), so units can be ``Type=notify`` with a watchdog.

A service started by systemd with ``Type=notify`` finds a datagram socket
in ``$NOTIFY_SOCKET`` and tells it ``READY=1`` once it really serves,
``WATCHDOG=1`` at least every ``$WATCHDOG_USEC`` / 2 while it is healthy, and
``STOPPING=1`` on the way out. Without ``$NOTIFY_SOCKET`` (not under systemd)
every call does nothing. A failed send is logged once and never raised: the
robot must not stop because its supervisor's socket went away.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from typing import Mapping

log = logging.getLogger(__name__)


class ServiceNotifier:
    """Tells systemd (or whoever set ``$NOTIFY_SOCKET``) how this process is doing."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        path = env.get("NOTIFY_SOCKET", "")
        # "@name" is an abstract socket: the name starts with a NUL byte.
        self.address: str | None = ("\0" + path[1:]) if path.startswith("@") else (path or None)
        self.watchdog_interval: float | None = None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval = int(usec) / 2e6  # half the limit, as sd_watchdog_enabled(3) advises
        self._last_watchdog = 0.0
        self._warned = False

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def ready(self, status: str = "") -> None:
        self._send("READY=1" + (f"\nSTATUS={_one_line(status)}" if status else ""))

    def stopping(self) -> None:
        self._send("STOPPING=1")

    def status(self, text: str) -> None:
        self._send(f"STATUS={_one_line(text)}")

    def watchdog(self) -> None:
        """Feed the watchdog, at most once per half interval (call it as often as you like)."""
        if self.watchdog_interval is None:
            return
        now = time.monotonic()
        if now - self._last_watchdog >= self.watchdog_interval / 2:
            self._last_watchdog = now
            self._send("WATCHDOG=1")

    def _send(self, message: str) -> None:
        if self.address is None:
            return
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.sendto(message.encode(), self.address)
        except OSError as exc:
            if not self._warned:
                self._warned = True
                log.warning("cannot notify the service manager at %r: %s", self.address, exc)


def _one_line(text: str) -> str:
    return " ".join(text.split())
