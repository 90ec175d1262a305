"""Talking to the deployers over Zenoh: start, stop, status, list, and their events.

:class:`DeployerClient` is what the command line, the migration and the
adaptation manager use to ask a host's deployer (deploy/deployer.py) to act.
Replies are checked; a refusal raises :class:`DeploymentError` (or
:class:`ReadinessTimeout`) with the deployer's own words, a malformed request
:class:`RemoteError`, and silence :class:`RequestTimeout`.
"""

from __future__ import annotations

import logging
from typing import Any

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import (
    ConfigError,
    DeploymentError,
    MessageError,
    NoResponder,
    ReadinessTimeout,
    RemoteError,
    RequestTimeout,
)
from kgadapt.shared.states import KEPT_STATES

log = logging.getLogger(__name__)

# The refusals a deployer names (docs/deploy.md): raised here as the same class; any other as DeploymentError.
_ERRORS: dict[str, type[Exception]] = {"ReadinessTimeout": ReadinessTimeout, "ConfigError": ConfigError}


class DeployerClient:
    """Requests to the deployers of one robot.

    ``timeout`` bounds every request but ``start`` with ``wait_ready``, which
    may take as long as the process needs to get ready (``start_timeout``).
    """

    def __init__(self, session: Any, robot: str, *, timeout: float = 5.0, start_timeout: float = 60.0,
                 resend_for: float | None = None) -> None:
        """``resend_for``: how long a request that reached no deployer is sent again (None: ``timeout``;
        0: not at all, for a caller to whom no deployer means a lost host, which liveliness reports)."""
        self.session = session
        self.robot = keys.check_name(robot, "robot name")
        self.timeout = timeout
        self.start_timeout = start_timeout
        self.resend_for = timeout if resend_for is None else resend_for
        self.answered: list[str] = []  # hosts whose deployers answered the last list()

    def start(self, host: str, deployment: str, config: str, *, instance: str | None = None,
              wait_ready: bool = True, ready_timeout: float | None = None,
              idle: bool = False) -> messages.DeployDetail:
        """Ask ``host`` to start ``deployment`` with ``config`` (``idle``: as a warm standby); returns the
        process snapshot."""
        body = messages.DeployRequest(deployment=deployment, config=config, wait_ready=wait_ready,
                                      instance=instance or None, idle=True if idle else None,
                                      ready_timeout=None if ready_timeout is None else float(ready_timeout))
        wait = self.start_timeout if wait_ready else self.timeout
        if ready_timeout is not None and wait_ready:
            wait = max(wait, ready_timeout + self.timeout)
        return self._one(host, "start", body, wait)

    def stop(self, host: str, instance: str) -> messages.DeployDetail:
        """Ask ``host`` to stop ``instance``; returns the final snapshot (with ``returncode``)."""
        # escalation may take a while
        return self._one(host, "stop", messages.DeployRequest(instance=instance), self.timeout + 15.0)

    def status(self, host: str, instance: str) -> messages.DeployDetail:
        return self._one(host, "status", messages.DeployRequest(instance=instance), self.timeout)

    def processes(self, host: str = "*") -> list[messages.ProcessDetail]:
        """Processes on ``host`` (``*``: every deployer that answers), each with its ``host``."""
        processes: list[messages.ProcessDetail] = []
        details = self._ask(host, "list", messages.DeployRequest(), self.timeout)
        self.answered = sorted(str(d.host) for d in details)
        for detail in details:
            processes.extend(detail.processes or [])
        return processes

    def wait_for(self, hosts: list[str], timeout: float = 10.0) -> None:
        """Wait until the deployer of each of ``hosts`` answers (a new session learns of them asynchronously).

        RequestTimeout naming the first host whose deployer did not answer within ``timeout``.
        """
        for host in hosts:
            keys.check_name(host, "host name")
            if not self._ask(host, "list", messages.DeployRequest(), timeout, resend_for=timeout):
                raise RequestTimeout(f"no deployer on host {host} answered within {timeout:g} s "
                                     f"(is the {host} agent running and reachable?)")

    def launcher(self, host: str) -> messages.Launcher | None:
        """``pid``, ``ready`` and ``idle_members`` of ``host``'s launcher, None when its deployer runs none."""
        details = self._ask(host, "list", messages.DeployRequest(idle=True), self.timeout)
        if not details:
            raise DeploymentError(f"no deployer of host {host} answered")
        return details[0].launcher

    def launchers(self, host: str = "*") -> dict[str, messages.Launcher]:
        """Each answering deployer's launcher (``pid``, ``ready``, ``idle_members``), by host; a host whose
        deployer runs none is left out."""
        details = self._ask(host, "list", messages.DeployRequest(idle=True), self.timeout)
        return {str(d.host): d.launcher for d in details if d.launcher is not None}

    def find(self, instance: str) -> messages.ProcessDetail:
        """The snapshot of ``instance`` on whichever host runs it (a live one first)."""
        found = [p for p in self.processes("*") if p.instance == instance]
        if not found:
            raise DeploymentError(f"no deployer knows instance {instance!r}")
        found.sort(key=lambda p: p.state not in KEPT_STATES)
        return found[0]

    # -- internals ----------------------------------------------------------------

    def _one(self, host: str, verb: str, body: messages.DeployRequest, timeout: float) -> messages.DeployDetail:
        keys.check_name(host, "host name")
        # Nobody answering at once means no matching queryable is known (yet): a session
        # opened a moment ago may not have the deployers' declarations. Nobody got the
        # request, so it is sent again, for up to ``self.resend_for``.
        details = self._ask(host, verb, body, timeout, resend_for=self.resend_for)
        if not details:
            raise RequestTimeout(
                f"no deployer on host {host} answered {verb} (is the {host} agent running and reachable?)"
            )
        return details[0]

    def _ask(self, host: str, verb: str, body: messages.DeployRequest, timeout: float, *,
             resend_for: float = 0.0) -> list[messages.DeployDetail]:
        """The ``detail`` of every deployer's reply (none: no deployer serves the key)."""
        key = keys.deployer_verb(self.robot, host, verb)
        payload = messages.encode(body)
        try:
            replies = rpc.gather(self.session, key, payload, lambda data: messages.decode_as(data, messages.DeployReply),
                                 timeout=timeout, resend_for=resend_for)
        except NoResponder:
            return []
        except RequestTimeout as exc:
            raise RequestTimeout(f"deployer on host {host} did not answer {verb} within {timeout:g} s") from exc
        except RemoteError as exc:
            raise RemoteError(f"deployer {verb} on host {host}: {exc}") from exc
        except MessageError as exc:
            raise RemoteError(f"deployer {verb} on {key}: bad reply: {exc}") from exc
        details: list[messages.DeployDetail] = []
        for message in replies:
            detail = message.detail or messages.DeployDetail()
            if not message.ok:
                # The refusal's class by its name in kgadapt.shared.errors (the wire carries it as error_type).
                error = _ERRORS.get(str(detail.error_type), DeploymentError)
                raise error(f"{detail.host or host}: {detail.error or 'refused'}")
            details.append(detail)
        return details
