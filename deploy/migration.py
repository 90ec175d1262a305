"""Planned migration of a detector between hosts without losing output.

``migrate(session, robot, instance, target_host)``:

1. find the instance (its host, deployment and configuration) through the deployers;
2. subscribe to the markers of a new instance id, then ask the target's
   deployer to start the same deployment and configuration under that id and
   wait until it is ready (or another ``deployment`` / ``config`` when given:
   the same make-before-break switch serves a change of configuration, on the
   same host or another);
3. wait for its first ``detections`` message;
4. only then ask the source's deployer to stop the old instance.

If the target does not get ready, or produces nothing in time, the new
instance is stopped (best effort), the source keeps running, and a
:class:`DeploymentError` (``ReadinessTimeout`` for readiness) says so.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.deployer import new_instance_name
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import (
    DeploymentError,
    KgadaptError,
    MessageError,
    NoResponder,
    ReadinessTimeout,
    RemoteError,
    RequestTimeout,
    SourceNotStopped,
)
from kgadapt.shared.states import SERVING_STATES

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class MigrationReport:
    """What a migration did, with its phases in milliseconds from its start."""

    instance: str
    new_instance: str
    deployment: str
    config: str
    source_host: str
    target_host: str
    target_ready_ms: float
    first_output_ms: float
    source_stopped_ms: float | None  # None: the source could not be stopped (SourceNotStopped)
    source_returncode: int | None
    new_pid: int | None
    new_run_id: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class FirstOutput:
    """Notes the arrival of the first valid detections message (callback only sets an event);
    with ``config``, the first one made with that configuration."""

    def __init__(self, *, config: str | None = None) -> None:
        self.config = config
        self.event = threading.Event()
        self.at: float | None = None  # perf_counter() of the first output, for durations
        self.wall: float | None = None  # time.time() of it, to compare with other hosts' times

    def __call__(self, sample: Any) -> None:
        if self.event.is_set():
            return
        try:
            body = messages.decode_as(sample.payload.to_bytes(), messages.Detections)
        except MessageError as exc:
            log.info("migration: dropped a malformed detections message: %s", exc)
            return
        if self.config is not None and body.config != self.config:
            return
        self.at = time.perf_counter()
        self.wall = time.time()
        self.event.set()


def migrate(
    session: Any,
    robot: str,
    instance: str,
    target_host: str,
    *,
    source_host: str | None = None,
    deployment: str | None = None,
    config: str | None = None,
    new_instance: str | None = None,
    ready_timeout: float = 15.0,
    output_timeout: float = 5.0,
    client: DeployerClient | None = None,
) -> MigrationReport:
    """Move ``instance`` to ``target_host``: start there, wait for output, stop the source.

    ``deployment`` and ``config`` default to the source's; give them to switch
    configuration at the same time (or only that, with ``target_host`` the
    source's host).
    """
    client = client or DeployerClient(session, robot)
    keys.check_name(target_host, "host name")
    source = client.status(source_host, instance) if source_host else client.find(instance)
    source_host = str(source.host or source_host)
    if source.state not in SERVING_STATES:
        raise DeploymentError(f"instance {instance} on {source_host} is {source.state}, not running; nothing to migrate")
    deployment = deployment or str(source.deployment)
    config = config or str(source.config)
    if source_host == target_host and (deployment, config) == (source.deployment, source.config):
        raise DeploymentError(f"instance {instance} already runs on {target_host} with {deployment} / {config}")
    new_instance = keys.check_name(new_instance, "instance") if new_instance else new_instance_name(config, target_host)

    t0 = time.perf_counter()
    first = FirstOutput()
    subscriber = session.declare_subscriber(keys.detector_markers(robot, new_instance), first)
    try:
        try:
            started = client.start(target_host, deployment, config, instance=new_instance,
                                   wait_ready=True, ready_timeout=ready_timeout)
        except KgadaptError as exc:
            _abandon(client, target_host, new_instance)
            kind = ReadinessTimeout if isinstance(exc, ReadinessTimeout) else DeploymentError
            raise kind(
                f"migration of {instance} to {target_host} failed: {exc}; {instance} keeps running on {source_host}"
            ) from exc
        ready_ms = (time.perf_counter() - t0) * 1000.0
        if not first.event.wait(output_timeout):
            _abandon(client, target_host, new_instance)
            raise DeploymentError(
                f"migration of {instance} to {target_host} failed: {new_instance} was ready but produced no "
                f"detections within {output_timeout:g} s; stopped it; {instance} keeps running on {source_host}"
            )
        output_ms = ((first.at or time.perf_counter()) - t0) * 1000.0
    finally:
        rpc.undeclare_quietly(subscriber)
    try:
        stopped = client.stop(source_host, instance)
    except KgadaptError as exc:
        # The new instance runs and detects: the caller must know it (the soak saw it left
        # running unknown to the adaptation manager, a second detector for minutes).
        report = MigrationReport(
            instance=instance, new_instance=new_instance, deployment=deployment, config=config,
            source_host=source_host, target_host=target_host, target_ready_ms=round(ready_ms, 3),
            first_output_ms=round(output_ms, 3), source_stopped_ms=None, source_returncode=None,
            new_pid=started.pid, new_run_id=started.run_id,
        )
        raise SourceNotStopped(
            f"migration of {instance}: {new_instance} runs on {target_host}, but stopping {instance} on "
            f"{source_host} failed: {exc}", report=report,
        ) from exc
    stopped_ms = (time.perf_counter() - t0) * 1000.0
    log.info("migrated %s (%s) from %s to %s as %s in %.0f ms", instance, config, source_host, target_host,
             new_instance, stopped_ms)
    return MigrationReport(
        instance=instance, new_instance=new_instance, deployment=deployment, config=config,
        source_host=source_host, target_host=target_host, target_ready_ms=round(ready_ms, 3),
        first_output_ms=round(output_ms, 3), source_stopped_ms=round(stopped_ms, 3),
        source_returncode=stopped.returncode, new_pid=started.pid,
        new_run_id=started.run_id,
    )


def _abandon(client: DeployerClient, host: str, instance: str) -> None:
    """Stop a half-started target instance; it may not exist, which is fine."""
    try:
        client.stop(host, instance)
    except KgadaptError as exc:
        log.debug("migration cleanup of %s on %s: %s", instance, host, exc)


@dataclass(frozen=True, kw_only=True)
class ReconfigurationReport:
    """What an in-place reconfiguration did (the detector's own reply, and the round trip)."""

    instance: str
    host: str
    config: str
    previous: str
    deployment: str
    first_seq: int | None  # the first frame processed with the new configuration
    check_ms: float  # the detector asking the graph (configuration, in_place_change)
    build_ms: float  # building the new configuration's detector
    reply_ms: float  # request sent -> reply (includes waiting for the first frame with it)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def reconfigure(session: Any, robot: str, host: str, instance: str, config: str, *,
                timeout: float = 5.0) -> ReconfigurationReport:
    """Ask the running detector ``instance`` on ``host`` to take ``config`` in place.

    The detector checks with the graph that its deployment may take the new
    configuration's in place; refused or unanswered, the running configuration
    stays and :class:`DeploymentError` says why (the caller may then migrate).
    A request that reached nobody is sent again until ``timeout``: a detector's
    deployer says it is ready before every session has its queryable's
    declaration (a change asked right after a start found none under load);
    RequestTimeout then, naming it not reconfigurable.
    """
    key = keys.detector_configure(robot, host, instance)
    payload = messages.encode(messages.ConfigureRequest(config=config))
    sent = time.perf_counter()
    try:
        body = rpc.call(session, key, payload, lambda data: messages.decode_as(data, messages.ConfigureReply),
                        timeout=timeout, resend_for=timeout)
    except NoResponder as exc:
        raise RequestTimeout(f"detector {instance} on host {host} has no configure queryable (not reconfigurable)") from exc
    except RequestTimeout as exc:  # the detector took it, or not: its deployer's record says which
        raise DeploymentError(f"reconfigure {instance} on {host}: no reply within {timeout:g} s") from exc
    except RemoteError as exc:
        raise DeploymentError(f"reconfigure {instance} on {host}: {exc}") from exc
    except MessageError as exc:
        raise DeploymentError(f"reconfigure {instance} on {host}: bad reply: {exc}") from exc
    reply_ms = (time.perf_counter() - sent) * 1e3
    return ReconfigurationReport(instance=instance, host=host, config=body.config,
                                 previous=body.previous, deployment=body.deployment,
                                 first_seq=body.first_seq, check_ms=float(body.check_ms),
                                 build_ms=float(body.build_ms), reply_ms=reply_ms)
