"""The deployer: a host's detector processes, started and stopped on request over Zenoh.

One :class:`Deployer` runs in each agent (onboard and remote) as one of its
parts. It answers four queryables (``kgadapt.shared.keys.deployer_verb``)::

    kgadapt/<robot>/host/<host>/deployer/start    deploy_request {deployment, config, instance?,
                                                                  wait_ready?, ready_timeout?, idle?}
    kgadapt/<robot>/host/<host>/deployer/stop     deploy_request {instance}
    kgadapt/<robot>/host/<host>/deployer/status   deploy_request {instance}
    kgadapt/<robot>/host/<host>/deployer/list     deploy_request {idle?}

and replies ``deploy_reply {ok, detail}``: ``detail`` is the process snapshot
(``ProcessInfo`` as ``ProcessDetail``, with ``host``), for ``list`` ``{host, processes, launcher}``
(``launcher``: ``{pid, ready}`` of the host's launcher, absent without one; with ``idle``
also ``idle_members``, the pids of its idle pool members);
a refusal or failure is ``ok: false`` with ``detail {error, error_type}``. A
request that is not a valid ``deploy_request`` gets ``query.reply_err``.
Events (``started``, ``ready``, ``exited``, ``restarted``, ``stopped``,
``failed``) go out as ``deploy_event`` on ``.../host/<host>/deployer/events``.

What runs comes from the knowledge store only: the named query
``deployment`` gives executable, arguments and environment; the deployment
must DEPLOY the requested configuration and be EXECUTABLE_ON this host, and
its texts may use only the placeholders of docs/CONTRACTS.md. A request that
carries anything else (a ``command``, an ``executable``...) is refused: a
request names what to run, it never says how.

Requests are answered on a small thread pool, never in the Zenoh callback;
profiles are written through the knowledge service by :class:`ProfileRecorder`.

Warm pool (``pool`` > 0, with the launcher): ahead of any start the deployer
has the launcher keep idle detectors for every kind of start the graph says may
run on this host (:meth:`Deployer.warm_host`: the feature's deployments
executable here, ``feature_deployments``), so the first start of a kind, a
failover's included, takes an idle member instead of a fork. It does so once
the launcher is ready, again when a new launcher replaced a dead one (it has no
pool), and every ``warm_refresh_s`` (the graph may have changed; nothing tells a
deployer that it did, and the refresh is a handful of named queries).
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import dataclasses
import hashlib
import heapq
import itertools
import logging
import re
import secrets
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, TypeVar

import msgspec
import zenoh

from kgadapt.deploy.options import (
    DEFAULT_POOL,
    add_arguments,  # noqa: F401  (re-exported for agents)
)
from kgadapt.deploy.profile import ProfileRecorder, ProfileSettings
from kgadapt.deploy.supervisor import ProcessEvent, ProcessInfo, ProcessSpec, RestartPolicy, Supervisor, SupervisorSettings
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.agent import DEFAULT_ROBOT
from kgadapt.shared.children import StopPolicy
from kgadapt.shared.errors import ConfigError, DeploymentError, KgadaptError, MessageError, RemoteError, TransportError
from kgadapt.shared.readiness import POOL_DEPLOYMENTS_ENV, RESOLVED_CONFIG_ENV, START_IDLE_ENV
from kgadapt.shared.session import DEFAULT_ENDPOINT

log = logging.getLogger(__name__)

VERBS = ("start", "stop", "status", "list")
PLACEHOLDERS = ("python", "robot", "host", "instance", "config", "connect")
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

# Fields a request may carry besides kind and version; anything else is refused.
_ALLOWED = {
    "start": {"deployment", "config", "instance", "wait_ready", "ready_timeout", "idle"},
    "stop": {"instance"},
    "status": {"instance"},
    "list": {"idle"},
}


@dataclass(frozen=True, kw_only=True)
class DeployerSettings:
    """One host's deployer. ``connect`` fills ``{connect}``: the endpoint the agent itself uses."""

    robot: str = DEFAULT_ROBOT
    host: str
    connect: str = DEFAULT_ENDPOINT
    zenoh_config: str | None = None  # handed to children as $KGADAPT_ZENOH_CONFIG (TLS, ACL)
    # The children's own configuration instead (the shipped ones: the host's detector certificate,
    # so a detector cannot use the agent's rights); None: the agent's.
    child_zenoh_config: str | None = None
    zenoh_mode: str | None = None  # handed to children as $KGADAPT_ZENOH_MODE
    python: str = sys.executable
    ready_timeout: float = 15.0
    max_ready_timeout: float = 120.0  # a request may ask for less or more, up to this
    restart: RestartPolicy = field(default_factory=RestartPolicy)
    stop: StopPolicy = field(default_factory=StopPolicy)
    sample_interval: float = 1.0
    knowledge_timeout: float = 2.0
    workers: int = 4
    # Fork detectors from the host's launcher (deploy/launcher.py); a plain start when it is absent.
    launcher: bool = True
    # Idle detectors the launcher keeps per kind of start (deploy/launcher.py's pool), within the memory
    # budget; each counts as the least declared memory of its kind's configurations. 0: no pool. (The
    # agents' --pool default is deploy/options.py's; this library default stays 0 so a bare Deployer forks.)
    pool: int = 0
    # Seconds between two readings of what the graph says may run on this host (the pool's kinds of start).
    warm_refresh_s: float = 30.0
    # Seconds after a start taken from the pool (or forked) before the pool is filled again: a member's
    # fork, Zenoh session and prepared detectors cost a loaded core 100 ms and more, which the started
    # detector's first frames would otherwise wait behind.
    pool_refill_s: float = 0.5

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.host, "host name")


class Deployer:
    """The deployer part of an agent: ``setup(session)``, ``shutdown()``.

    The same operations are available in-process (``start``, ``stop``,
    ``status``, ``list``) for the agent's own use and for tests.
    ``knowledge`` is anything with ``query(name, params)`` and
    ``write(verb, params)``; by default a ``KnowledgeClient`` on the session.
    """

    name = "deployer"

    def __init__(self, settings: DeployerSettings, *, knowledge: Any = None,
                 free_memory: Callable[[], float] | None = None,
                 budget: Callable[[], float] | None = None) -> None:
        self.settings = settings
        self._knowledge = knowledge
        # MiB this host may still give (the host monitor's figure, within its budget); None: no check.
        self._free_memory = free_memory
        # MiB this host gives our processes in all (its --memory-budget, else the machine's memory): what
        # the graph declares for every process it runs must fit in it. None: no check.
        self._budget = budget
        # Admission: one start decided at a time, and the starts admitted but not yet in the supervisor's
        # list (instance -> (config, declared MiB)), so that raced starts cannot pass together.
        self._admission = threading.Lock()
        self._admitted: dict[str, tuple[str, float]] = {}
        # What each process started here declared when it was admitted (instance -> (config, MiB)): the
        # figure its admission counted, counted again for it at the next start instead of asking the graph.
        self._declared: dict[str, tuple[str, float]] = {}
        # Kinds of start the launcher keeps idle members for, by what a member can take (its pool key).
        self._warm: dict[str, _Kind] = {}
        self._stop_warming = threading.Event()
        # The pool's upkeep after a start (sized again, filled again later), on a thread of its own: the
        # start's reply does not wait for it.
        self._upkeep = _Later(f"deployer-pool-{settings.host}")
        self.supervisor = Supervisor(SupervisorSettings(launcher=settings.launcher, python=settings.python))
        self.recorder: ProfileRecorder | None = None
        self._session: Any = None
        self._publisher: Any = None
        self._publish_lock = threading.Lock()
        self._stack = contextlib.ExitStack()

    # -- life cycle ---------------------------------------------------------------

    def setup(self, session: Any) -> None:
        """Start the supervisor and profile recorder, declare queryables and the event publisher."""
        s = self.settings
        self._session = session
        if self._knowledge is None:
            from kgadapt.knowledge.client import KnowledgeClient

            self._knowledge = KnowledgeClient(session, s.robot, timeout=s.knowledge_timeout, own=True, host=s.host)
        # Shut down in reverse: queryables, supervisor (it stops every process and wakes requests waiting
        # for readiness), request workers, profile recorder, and last the publisher (the "stopped" events).
        with contextlib.ExitStack() as stack:
            try:
                publisher = session.declare_publisher(keys.deployer_events(s.robot, s.host))
            except zenoh.ZError as exc:
                raise TransportError(f"deployer of host {s.host}: cannot declare its event publisher: {exc}") from exc
            self._publisher = rpc.declared(stack, publisher)
            stack.callback(self._forget_publisher)
            self.recorder = ProfileRecorder(
                host=s.host, write=self._knowledge.write, settings=ProfileSettings(sample_interval=s.sample_interval)
            )
            self.recorder.setup()
            stack.callback(self._forget_recorder, self.recorder)
            server = stack.enter_context(rpc.Server(f"deployer {s.host}", workers=s.workers, max_pending=64,
                                                    prefix=f"deployer {s.host}: "))
            self.supervisor.add_listener(self.recorder.on_event)
            self.supervisor.add_listener(self._publish_event)
            self.supervisor.setup()
            stack.callback(self.supervisor.shutdown)
            self._upkeep.setup()
            stack.callback(self._upkeep.shutdown)  # before the supervisor stops: no pool asked for meanwhile
            if s.pool > 0 and self.supervisor.launcher is not None:
                self._stop_warming.clear()
                warmer = threading.Thread(target=self._keep_host_warm, name=f"deployer-warm-{s.host}", daemon=True)
                warmer.start()
                stack.callback(warmer.join, 10.0)
                stack.callback(self._stop_warming.set)
            stack.callback(server.undeclare)
            for verb in VERBS:
                key = keys.deployer_verb(s.robot, s.host, verb)
                server.serve(session, key, self._handler(verb, key), what=verb)
            self._stack = stack.pop_all()
        log.info("deployer of host %s (robot %s) ready", s.host, s.robot)

    def shutdown(self) -> None:
        """Refuse new requests, stop every process (SIGINT, SIGTERM, SIGKILL), flush profiles."""
        self._stack.close()
        self._upkeep.shutdown()
        self._session = None

    def _forget_publisher(self) -> None:
        with self._publish_lock:  # no event is put while the publisher is undeclared
            self._publisher = None

    def _forget_recorder(self, recorder: ProfileRecorder) -> None:
        recorder.shutdown()
        self.recorder = None

    # -- operations ---------------------------------------------------------------

    def resolve(self, deployment: str, config: str, instance: str | None = None,
                *, ready_timeout: float | None = None, idle: bool = False, carry: bool = True) -> ProcessSpec:
        """What to run for ``deployment`` with ``config`` on this host, from the knowledge store.

        Raises DeploymentError naming what is wrong: an unknown deployment, one
        that does not deploy ``config`` or is not executable on this host, a
        placeholder that is not allowed. ``carry``: the configuration as the graph
        gives it goes with the start (``$KGADAPT_RESOLVED_CONFIG``).
        """
        return self._resolve(deployment, config, instance, ready_timeout=ready_timeout, idle=idle, carry=carry)[0]

    def _resolve(self, deployment: str, config: str, instance: str | None = None, *, ready_timeout: float | None,
                 idle: bool, carry: bool) -> tuple[ProcessSpec, float | None]:
        """:meth:`resolve`, and the memory ``config`` declares when the carried configuration's row said it
        (None: not looked up, or not known)."""
        s = self.settings
        keys.check_name(deployment, "deployment name")
        keys.check_name(config, "configuration name")
        instance = keys.check_name(instance, "instance") if instance else new_instance_name(config, s.host)
        # The configuration's row is asked for beside the deployment's, not after it: on a loaded host each
        # question waits its turn at the service and the store, and a start waits for both.
        carried: list[tuple[str | None, float | None]] = []
        asking = threading.Thread(target=lambda: carried.append(self._resolved_config(config)),
                                  name="deployer-config", daemon=True) if carry else None
        if asking is not None:
            asking.start()
        try:
            rows = self._knowledge.query("deployment", {"name": deployment})
        except (RemoteError, TransportError) as exc:
            raise DeploymentError(f"cannot look up deployment {deployment} in the knowledge store: {exc}") from exc
        finally:
            if asking is not None:
                asking.join()  # bounded by the client's own timeout
        if not rows:
            raise DeploymentError(f"deployment {deployment!r} is not in the knowledge store")
        row = rows[0]
        platforms = list(row.get("platforms") or [])
        if s.host not in platforms:
            where = ", ".join(map(str, platforms)) or "no platform"
            raise DeploymentError(f"deployment {deployment} is not executable on host {s.host} (only on {where})")
        deploys = list(row.get("deploys") or [])
        if config not in deploys:
            what = ", ".join(map(str, deploys)) or "nothing"
            raise DeploymentError(f"deployment {deployment} does not deploy configuration {config} (it deploys {what})")
        executable = row.get("executable")
        if not isinstance(executable, str) or not executable.strip():
            raise DeploymentError(f"deployment {deployment} has no executable in the knowledge store")
        values = {
            "python": s.python, "robot": s.robot, "host": s.host,
            "instance": instance, "config": config, "connect": s.connect,
        }
        argv = [fill_placeholders(executable, values, f"deployment {deployment} executable")]
        for i, arg in enumerate(_as_list(row.get("arguments"), deployment, "arguments")):
            argv.append(fill_placeholders(str(arg), values, f"deployment {deployment} argument {i}"))
        env: list[tuple[str, str]] = []
        zenoh_config = s.child_zenoh_config or s.zenoh_config
        if zenoh_config:
            env.append(("KGADAPT_ZENOH_CONFIG", zenoh_config))
        if s.zenoh_mode:
            env.append(("KGADAPT_ZENOH_MODE", s.zenoh_mode))
        if idle:
            env.append((START_IDLE_ENV, "1"))
        resolved, demand = carried[0] if carried else (None, None)
        if resolved is not None:
            env.append((RESOLVED_CONFIG_ENV, resolved))
        for item in _as_list(row.get("environment"), deployment, "environment"):
            name, sep, value = str(item).partition("=")
            if not sep or not _ENV_NAME.match(name):
                raise DeploymentError(f"deployment {deployment}: environment entry {item!r} is not NAME=VALUE")
            env.append((name, fill_placeholders(value, values, f"deployment {deployment} environment {name}")))
        timeout = s.ready_timeout if ready_timeout is None else ready_timeout
        if not 0 < timeout <= s.max_ready_timeout:
            raise DeploymentError(f"ready_timeout {timeout:g} s: use more than 0 and at most {s.max_ready_timeout:g} s")
        return ProcessSpec(
            instance=instance, argv=tuple(argv), env=tuple(env), deployment=deployment, config=config,
            ready_timeout=timeout, restart=s.restart, stop=s.stop,
        ), demand

    def _resolved_config(self, config: str) -> tuple[str | None, float | None]:
        """``config`` as the graph gives it now (``detector_config``), for the started detector to take
        instead of asking again: a ``resolved_config`` message, base64. None when the graph has no
        such row (a program that is not a detector) or does not answer: the child then asks itself.
        With it, the memory the row declares (what admission counts; None when the graph did not answer)."""
        try:
            rows = self._knowledge.query("detector_config", {"config": config})
        except (RemoteError, TransportError) as exc:
            log.info("host %s: %s not resolved for its start (%s); the process asks itself", self.settings.host,
                     config, exc)
            return None, None
        demand = float((rows[0].get("memory_demand_mb") or 0.0) if rows else 0.0)  # as _declared_demands has it
        if not rows or not isinstance(rows[0].get("config_json"), str):
            return None, demand
        row = rows[0]
        try:
            body = messages.encode(messages.ResolvedConfig(
                config=config, config_json=row["config_json"], dictionary=row.get("dictionary"),
                deployment=row.get("deployment"), memory_demand_mb=row.get("memory_demand_mb"),
                resolved_at=time.time(), digest=hashlib.sha256(msgspec.json.encode(row, order="sorted")).hexdigest()[:32]))
        except (MessageError, TypeError) as exc:
            log.info("host %s: %s not carried to its start (%s); the process asks itself", self.settings.host,
                     config, exc)
            return None, demand
        return base64.b64encode(body).decode("ascii"), demand

    def start(self, deployment: str, config: str, *, instance: str | None = None,
              wait_ready: bool = True, ready_timeout: float | None = None, idle: bool = False) -> ProcessInfo:
        """Check with the knowledge store and the host's memory, then start; see :meth:`Supervisor.start`.

        ``idle``: the process is told to start idle (``$KGADAPT_START_IDLE``), as a warm standby does."""
        # One question for the configuration: carried with the start, and its declared memory for admission.
        spec, demand = self._resolve(deployment, config, instance, ready_timeout=ready_timeout, idle=idle, carry=True)
        self._admit(spec.instance, config, demand)
        try:
            log.info("host %s: starting %s (%s, %s): %s", self.settings.host, spec.instance, deployment, config,
                     " ".join(spec.argv))
            info = self.supervisor.start(spec, wait_ready=wait_ready)
        finally:
            with self._admission:  # from now on the supervisor's list holds it (or it failed)
                self._admitted.pop(spec.instance, None)
        if self.settings.pool > 0:
            # Right after the reply, every other kind is sized again within the budget with this process
            # in it (idle members yielded to it: fewer may be kept now); the next start like it takes an
            # idle member made pool_refill_s from now.
            self._upkeep.after(0.0, lambda: self._resize_after(spec))
            if info.via in ("launcher", "pool"):
                self._upkeep.after(self.settings.pool_refill_s, lambda: self._refill(deployment, config, spec))
        return info

    def _resize_after(self, spec: ProcessSpec) -> None:
        try:
            self._resize_pool(but=self.supervisor.pool_key(spec))
        except KgadaptError as exc:  # the start is done; the pool waits for the next reading
            log.info("host %s: pool not sized after starting %s: %s", self.settings.host, spec.instance, exc)

    def _refill(self, deployment: str, config: str, spec: ProcessSpec) -> None:
        """The pool kept for starts like ``spec`` filled again."""
        try:
            self._keep_warm(deployment, config, spec, replace=False)
        except KgadaptError as exc:  # the pool waits for the next reading
            log.info("host %s: pool not filled again after starting %s: %s", self.settings.host,
                     spec.instance, exc)

    def _resize_pool(self, *, but: str | None = None) -> None:
        """Size every kind kept warm (but ``but``) again within the budget."""
        for key, kind in list(self._warm.items()):
            if key == but:
                continue
            with self._admission:
                size = self._pool_size(key, kind.config)
            if size < self.supervisor.idle_for(kind.spec):
                self.supervisor.keep_pool(kind.spec, size)

    def warm(self, deployment: str, config: str) -> int:
        """Have the launcher keep idle members for starts of ``deployment`` with ``config`` (as many as
        ``pool`` and the memory budget allow); the number asked for."""
        spec = self.resolve(deployment, config, "pooled")
        return self._keep_warm(deployment, config, _preparing(spec, [deployment]))

    def warm_host(self) -> int:
        """Have the launcher keep idle members, as many as ``pool`` and the memory budget allow, for every
        kind of start the graph says may run on this host: the feature's deployments executable here
        (``feature_deployments``), grouped by what one member can take (deploy/launcher.py's ``pool_key``;
        the shipped detector deployments are one kind). A kind's members count as its least demanding
        configuration (an idle member is none of them yet) and prepare the reflex table of each of its
        deployments. Kinds the launcher does not fork are left out. The number of members asked for;
        DeploymentError when the graph does not answer."""
        s = self.settings
        if s.pool <= 0:
            return 0
        try:
            rows = self._knowledge.query("feature_deployments", {"platform": s.host})
        except (RemoteError, TransportError) as exc:
            raise DeploymentError(f"host {s.host}: cannot ask the graph what may run here: {exc}") from exc
        kinds: dict[str, list[tuple[str, str, ProcessSpec]]] = {}
        for deployment, config in sorted({(str(r.get("deployment")), str(r.get("config"))) for r in rows}):
            if self._stop_warming.is_set():  # shutting down: no more questions to the graph
                return 0
            try:
                spec = self.resolve(deployment, config, "pooled", carry=False)
            except DeploymentError as exc:  # a deployment the graph describes badly: not one to keep warm
                log.info("host %s: no pool for %s (%s): %s", s.host, deployment, config, exc)
                continue
            key = self.supervisor.pool_key(spec)
            if key is not None:
                kinds.setdefault(key, []).append((deployment, config, spec))
        asked = 0
        for options in kinds.values():
            demands = self._declared_demands({config for _, config, _ in options})
            deployment, config, spec = min(options, key=lambda o: (demands[o[1]], o[1], o[0]))
            asked += self._keep_warm(deployment, config, _preparing(spec, [d for d, _, _ in options]))
        return asked

    def _keep_host_warm(self) -> None:
        """Thread: :meth:`warm_host` once the launcher is ready, again when a new launcher replaced a dead
        one (it has no pool) and every ``warm_refresh_s``; after a failed reading, again 2 s later."""
        launcher = self.supervisor.launcher
        assert launcher is not None
        seen, due = -1, 0.0
        while not self._stop_warming.wait(0.25):  # a flag read: cheap, and a new launcher is seen soon
            if not launcher.ready:
                continue
            now = time.monotonic()
            if launcher.starts == seen and now < due:
                continue
            seen = launcher.starts
            try:
                asked = self.warm_host()
            except KgadaptError as exc:
                log.info("host %s: pool not warmed yet: %s", self.settings.host, exc)
                due = now + 2.0
                continue
            due = now + self.settings.warm_refresh_s
            log.debug("host %s: %d idle detector(s) kept", self.settings.host, asked)

    def _keep_warm(self, deployment: str, config: str, spec: ProcessSpec, *, replace: bool = True) -> int:
        """Keep idle members for ``spec``'s kind of start, counted as ``config``, as many as ``pool`` and the
        budget allow (the launcher ends the ones beyond); ``replace``: this spec is the kind's from now on
        (else a kind already kept keeps its own, which prepares for more)."""
        key = self.supervisor.pool_key(spec)
        if key is None:  # the launcher does not fork it (or is not ready): nothing to keep
            return 0
        with self._admission:
            kind = self._warm.get(key)
            if kind is None or replace:
                kind = self._warm[key] = _Kind(deployment=deployment, config=config, spec=spec)
            size = self._pool_size(key, kind.config)
        self.supervisor.keep_pool(kind.spec, size)
        return size

    def _pooled(self) -> list[tuple[str, str, int]]:
        """(pool key, config counted, idle members) of every kind of start kept warm."""
        return [(key, kind.config, self.supervisor.idle_for(kind.spec)) for key, kind in self._warm.items()]

    def _pool_size(self, key: str, config: str) -> int:
        """Idle members for the kind of start ``key``, each counted as ``config``: ``pool``, fewer when the
        budget has no room for them beside what the graph declares for the processes of this host (caller
        holds _admission)."""
        size = self.settings.pool
        if self._budget is None or size <= 0:
            return size
        running = {info.instance: info.config for info in self.supervisor.processes(include_finished=False)}
        held = [*running.values(), *(c for c, _ in self._admitted.values())]
        others = [(c, n) for k, c, n in self._pooled() if k != key]
        # A live process's configuration as it was admitted with (not one it was changed to in place since).
        declared = {c: mb for name, (c, mb) in self._declared.items() if running.get(name) == c}
        demands = self._declared_demands({config, *held, *(c for c, _ in others)}, declared)
        used = sum(demands[c] for c in held) + sum(demands[c] * n for c, n in others)
        room = float(self._budget()) - used
        each = demands[config]
        return max(0, min(size, int(room // each))) if each > 0 else size

    def _admit(self, instance: str, config: str, demand: float | None = None) -> None:
        """Admit a start of ``config`` as ``instance`` or raise DeploymentError naming the figures.

        Two checks, under one lock with the starts already admitted:

        - by declaration: the memory the graph declares for every live process of this host, the
          starts admitted meanwhile and this one must fit the host's budget. A detector that has
          just started has not yet taken its memory, so only this check holds against raced starts;
        - by measure: the host monitor's free memory, less what the starts under way have declared
          and not yet taken, must cover this one's demand.

        Idle pool members yield to a start: they are not counted against it (the pool is sized
        again after the start, within the budget: :meth:`_keep_warm`); the agents' host monitor
        leaves them out of its measure too (``HostMonitor.yielding``: :meth:`yielding_pids`).

        ``demand``: what the graph declares for ``config``, read with its row just before (None: asked here).
        A live process started here counts what it declared when it was admitted; the graph is asked only
        for the others.
        """
        if self._free_memory is None and self._budget is None:
            return
        host = self.settings.host
        with self._admission:
            if instance in self._admitted:
                raise DeploymentError(f"instance {instance} is already being started on host {host}")
            held: dict[str, tuple[str, bool]] = {  # instance -> (config, still starting)
                info.instance: (info.config, False) for info in self.supervisor.processes(include_finished=False)}
            for name, (other, _) in self._admitted.items():
                held[name] = (other, True)
            for gone in set(self._declared) - set(held):
                del self._declared[gone]
            known = {c: mb for name, (c, mb) in self._declared.items() if held.get(name, ("",))[0] == c}
            if demand is not None:
                known[config] = demand
            demands = self._declared_demands({config, *(c for c, _ in held.values())}, known)
            demand = demands[config]
            if self._budget is not None:
                budget = float(self._budget())
                declared = sum(demands[c] for c, _ in held.values())
                if declared + demand > budget:
                    each = ", ".join(f"{name} {c} {demands[c]:.0f} MiB" for name, (c, _) in sorted(held.items()))
                    raise DeploymentError(
                        f"start of {config} refused: it declares {demand:.0f} MiB and host {host}'s "
                        f"{len(held)} process(es) already declare {declared:.0f} MiB ({each or 'none'}): "
                        f"{declared + demand:.0f} MiB would exceed its memory budget of {budget:.0f} MiB"
                    )
            if self._free_memory is not None:
                free = float(self._free_memory())
                starting = sum(demands[c] for c, still in held.values() if still)
                if demand > free - starting:
                    under_way = f" less {starting:.0f} MiB declared by starts under way" if starting else ""
                    raise DeploymentError(
                        f"start of {config} refused: it needs {demand:.0f} MiB and host {host} has "
                        f"{max(0.0, free - starting):.0f} MiB free within its memory budget "
                        f"(measured {free:.0f} MiB{under_way})"
                    )
            self._admitted[instance] = (config, demand)
            self._declared[instance] = (config, demand)

    def _declared_demands(self, configs: set[str], known: Mapping[str, float] | None = None) -> dict[str, float]:
        """Each configuration's declared memory demand (MiB; 0 for one the graph does not know); those in
        ``known`` as given there."""
        demands: dict[str, float] = {c: float(known[c]) for c in configs if known and c in known}
        for config in sorted(configs - set(demands)):
            try:
                rows = self._knowledge.query("detector_config", {"config": config})
            except (RemoteError, TransportError) as exc:
                raise DeploymentError(f"cannot look up the memory demand of {config}: {exc}") from exc
            demands[config] = float((rows[0].get("memory_demand_mb") or 0.0) if rows else 0.0)
        return demands

    def idle_pids(self) -> list[int]:
        """The pids of the launcher's idle pool members."""
        launcher = self.supervisor.launcher
        return launcher.idle_pids() if launcher is not None else []

    def yielding_pids(self) -> list[int]:
        """The pids of the processes that yield their memory to a start: the idle pool members and the
        launcher's intermediate process above each (it ends when its member is taken)."""
        launcher = self.supervisor.launcher
        return launcher.yielding_pids() if launcher is not None else []

    def stop(self, instance: str) -> ProcessInfo:
        """Stop one instance (SIGINT, SIGTERM, SIGKILL)."""
        return self.supervisor.stop(keys.check_name(instance, "instance"))

    def status(self, instance: str) -> ProcessInfo:
        return self.supervisor.status(keys.check_name(instance, "instance"))

    def processes(self) -> list[ProcessInfo]:
        return self.supervisor.processes()

    # -- Zenoh --------------------------------------------------------------------

    def _handler(self, verb: str, key: str) -> rpc.Handler:
        def answer(request: rpc.Request) -> rpc.Reply:
            # A MessageError here is answered with reply_err ("deployer <host>: ..."); every refusal
            # past the message itself is a deploy_reply with ok false.
            if request.payload is None:
                raise MessageError(f"{verb} request has no payload; send a deploy_request message")
            body, unknown = messages.decode_with_unknown(request.payload, messages.DeployRequest)
            if verb in ("start", "stop") and request.key != key:
                # host/*/deployer/start would reach every host: a change names exactly one.
                raise MessageError(f"a {verb} request must name exactly one host; {request.key} does not")
            try:
                reply = messages.DeployReply(ok=True, detail=self._handle(verb, body, unknown))
            except KgadaptError as exc:
                log.info("host %s: %s refused: %s", self.settings.host, verb, exc)
                reply = messages.DeployReply(ok=False, detail=messages.DeployDetail(
                    error=str(exc), error_type=type(exc).__name__, host=self.settings.host))
            return rpc.Reply(key=key, payload=messages.encode(reply))

        return answer

    def _handle(self, verb: str, request: messages.DeployRequest, unknown: tuple[str, ...] = ()) -> messages.DeployDetail:
        given = {name for name in request.__struct_fields__ if name != "v" and getattr(request, name) is not None}
        extra = sorted((given | set(unknown)) - _ALLOWED[verb])
        if extra:
            raise DeploymentError(
                f"{verb} request field(s) {', '.join(map(repr, extra))} not accepted: a request names a "
                "deployment and a configuration; what runs comes from the knowledge store"
            )
        host = self.settings.host
        if verb == "list":
            launcher = self.supervisor.launcher
            return messages.DeployDetail(
                host=host, processes=[_detail(i, host, messages.ProcessDetail) for i in self.processes()],
                launcher=messages.Launcher(pid=launcher.pid, ready=launcher.ready,
                                           idle_members=(launcher.idle_pids() or None) if request.idle else None)
                if launcher is not None else None)
        if verb in ("stop", "status"):
            instance = request.instance
            if not instance:
                raise DeploymentError(f"{verb} request needs an instance")
            info = self.stop(instance) if verb == "stop" else self.status(instance)
            return _detail(info, host, messages.DeployDetail)
        if not request.deployment:
            raise DeploymentError("start request needs a deployment")
        if not request.config:
            raise DeploymentError("start request needs a config")
        info = self.start(
            request.deployment, request.config, instance=request.instance or None,
            wait_ready=True if request.wait_ready is None else request.wait_ready,  # absent and nil alike
            ready_timeout=request.ready_timeout, idle=bool(request.idle),
        )
        return _detail(info, host, messages.DeployDetail)

    def _publish_event(self, event: ProcessEvent) -> None:
        body = messages.DeployEvent(
            event=event.event, host=self.settings.host, instance=event.instance, time=event.time,
            pid=event.pid, returncode=event.returncode, detail=(event.detail or "")[-4000:] or None,
            run_id=event.run_id, deployment=event.deployment, config=event.config,
        )
        with self._publish_lock:
            if self._publisher is None:
                return
            try:
                self._publisher.put(messages.encode(body))
            except Exception as exc:  # noqa: BLE001 - never let a transport hiccup stop supervision
                log.warning("cannot publish deployer event %s: %s", event.event, exc)


class _Later:
    """Jobs run one after another on a thread of their own, each at its time (``setup`` starts the thread,
    else the first job does). ``shutdown`` drops those not yet due and ends the thread."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._changed = threading.Condition()
        self._jobs: list[tuple[float, int, Callable[[], None]]] = []  # a heap by due time
        self._order = itertools.count()
        self._thread: threading.Thread | None = None
        self._closed = False

    def setup(self) -> None:
        with self._changed:
            self._start()

    def after(self, delay: float, job: Callable[[], None]) -> None:
        """Run ``job`` ``delay`` seconds from now (not at all once shut down)."""
        with self._changed:
            if self._closed:
                return
            heapq.heappush(self._jobs, (time.monotonic() + delay, next(self._order), job))
            self._start()
            self._changed.notify()

    def _start(self) -> None:
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while True:
            with self._changed:
                while not self._closed and (not self._jobs or self._jobs[0][0] > time.monotonic()):
                    self._changed.wait(self._jobs[0][0] - time.monotonic() if self._jobs else None)
                if self._closed:
                    return
                job = heapq.heappop(self._jobs)[2]
            try:
                job()
            except Exception:  # noqa: BLE001 - a bug in one job must not end the others
                log.exception("%s: a job failed", self._name)

    def shutdown(self) -> None:
        with self._changed:
            self._closed = True
            self._jobs.clear()
            thread, self._thread = self._thread, None
            self._changed.notify_all()
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10.0)


@dataclass(frozen=True, kw_only=True)
class _Kind:
    """A kind of start kept warm: the spec its members are forked with, and the configuration they count as."""

    deployment: str
    config: str
    spec: ProcessSpec


def _preparing(spec: ProcessSpec, deployments: list[str]) -> ProcessSpec:
    """``spec`` for a pool member that prepares the starts of ``deployments`` (their reflex tables)."""
    env = tuple((k, v) for k, v in spec.env if k != POOL_DEPLOYMENTS_ENV)
    return dataclasses.replace(spec, env=(*env, (POOL_DEPLOYMENTS_ENV, ",".join(sorted(set(deployments))))))


def new_instance_name(config: str, host: str) -> str:
    """A fresh instance id: ``<config>-<host>-<6 hex>``, a safe key chunk of at most 64 characters."""
    return f"{config[:40]}-{host[:16]}-{secrets.token_hex(3)}"


def fill_placeholders(text: str, values: Mapping[str, str], where: str) -> str:
    """Replace ``{name}`` by ``values[name]``; any other ``{...}`` raises DeploymentError."""

    def substitute(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in values:
            raise DeploymentError(
                f"{where}: placeholder {{{name}}} is not allowed; use {', '.join('{' + p + '}' for p in PLACEHOLDERS)}"
            )
        return values[name]

    return _PLACEHOLDER.sub(substitute, text)


def _as_list(value: Any, deployment: str, what: str) -> list[Any]:
    if value is None:
        return []
    if not isinstance(value, (list, tuple)):
        raise DeploymentError(f"deployment {deployment}: {what} in the knowledge store is not a list")
    return list(value)


D = TypeVar("D", bound=messages.ProcessDetail)


# What a reply carries of a child's own words: the start of each of its last lines and the end of why it ended.
# A child's single long line must not push a reply past the message bound (256 KiB) and so fail it for every
# asker (the adaptation manager adopts and stops twins by a host's list). In a list, 60 instances (50 ended ones
# kept) of 5 lines, their detail and argv stay near 170 KiB; one instance's reply (status, start, stop) keeps
# more of each line (a probe's report of its own arguments, say).
OUTPUT_LINE_CHARS = 240  # in a host's list
DETAIL_CHARS = 1000  # in a host's list
ONE_LINE_CHARS = 8000  # in one instance's reply
ONE_DETAIL_CHARS = 8000


def _clipped(text: str, room: int, *, keep_end: bool = False) -> str:
    if len(text) <= room:
        return text
    return "…" + text[-(room - 1):] if keep_end else text[:room - 1] + "…"


def _detail(info: ProcessInfo, host: str, cls: type[D]) -> D:
    """``info`` as the wire's process detail, with its ``host``; the child's output and detail clipped (more
    room in one instance's reply than in each entry of a list)."""
    single = cls is messages.DeployDetail
    line_room, detail_room = (ONE_LINE_CHARS, ONE_DETAIL_CHARS) if single else (OUTPUT_LINE_CHARS, DETAIL_CHARS)
    detail = None if info.detail is None else _clipped(info.detail, detail_room, keep_end=True)
    return cls(instance=info.instance, host=host, deployment=info.deployment, config=info.config, state=info.state,
               pid=info.pid, run_id=info.run_id, restarts=info.restarts, started_at=info.started_at,
               ready_at=info.ready_at, ended_at=info.ended_at, returncode=info.returncode, argv=list(info.argv),
               detail=detail, output=[_clipped(line, line_room) for line in info.output], via=info.via)


# -- agent wiring -------------------------------------------------------------------


def settings_from_args(args: argparse.Namespace, *, robot: str, host: str) -> DeployerSettings:
    """Deployer settings of an agent command; ``{connect}`` is the agent's own first endpoint."""
    from kgadapt.shared.session import settings_from_args as zenoh_settings_from_args

    zenoh = zenoh_settings_from_args(args)
    connect = zenoh.connect[0] if zenoh.connect else _first_connect_in_file(zenoh.config_file) or DEFAULT_ENDPOINT
    stop = getattr(args, "stop_timeout", 3.0)
    return DeployerSettings(
        robot=robot, host=host, connect=connect, zenoh_config=zenoh.config_file, zenoh_mode=zenoh.mode,
        child_zenoh_config=getattr(args, "detector_zenoh_config", None),
        ready_timeout=getattr(args, "ready_timeout", 15.0),
        restart=RestartPolicy(max_restarts=getattr(args, "max_restarts", 3)),
        stop=StopPolicy(sigint_timeout=stop, sigterm_timeout=stop),
        sample_interval=getattr(args, "profile_interval", 1.0),
        launcher=not getattr(args, "no_launcher", False),
        pool=max(0, int(getattr(args, "pool", DEFAULT_POOL))),
    )


def _first_connect_in_file(path: str | None) -> str | None:
    if not path:
        return None
    import json

    try:
        endpoints = json.loads(zenoh.Config.from_file(path).get_json("connect/endpoints"))
    except Exception as exc:  # zenoh's and JSON's errors: translated here
        raise ConfigError(f"Zenoh config {path}: cannot read connect/endpoints: {exc}") from exc
    if isinstance(endpoints, dict):  # per-mode form {router: [...], peer: [...]}
        endpoints = endpoints.get("peer") or next(iter(endpoints.values()), [])
    return endpoints[0] if endpoints else None
