"""The adaptation manager: the paper's Fig. 6 loop as a part of the onboard agent.

Monitor (Zenoh subscribers: illumination, host status, host liveliness, flight
state, the running detector's detections) -> analyse (:mod:`kgadapt.onboard.adaptation`)
-> plan (named queries through the knowledge service) -> execute (the hosts'
deployers) -> knowledge (every decision written into the graph).

Callbacks only queue observations; one worker thread analyses and acts, so a
migration never runs inside a Zenoh callback and decisions happen one at a time.
Host liveliness changes have their own queue, served first: a host lost during a
long action is acted on next, not after the observations queued meanwhile.

Execution: a planned change on the same host whose deployments the graph
says may be changed in place (the planner asks ``in_place_change``) reconfigures
the running detector between two frames (:func:`kgadapt.deploy.migration.reconfigure`);
otherwise, or when that is refused, it is make-before-break: start the new
detector, wait for its first detections, and only then stop the old one
(:func:`kgadapt.deploy.migration.migrate`). The decision records which and why. When the host running the detector is
lost, a new detector starts at once on a host that can hold it. During final
descent (flight state ``LANDING``, or landed state unknown in LAND/RTL:
:func:`kgadapt.onboard.flight_phase.in_final_descent`) planned changes are deferred; losing the
running host is still acted on.

Warm standby (``standby=True``, ``kgadapt onboard --standby``; off by default):
when the ``placement`` query says a host has room for the configuration of the
band the light most likely goes to next as well (the band it left at the last
change, else the neighbour whose edge it is nearest:
:meth:`kgadapt.onboard.adaptation.BandTracker.neighbour`), the
manager starts that configuration there through the deployer (supervised and
profiled like any detector, its memory in the graph) and makes it idle
(:func:`kgadapt.onboard.detector.set_active`). A change whose target configuration is the
standby's is then a switch: activate the standby, make it the running detector,
idle the old one (it becomes the standby). Losing the host that runs the
detector activates a standby on another host (reconfigured in place to the
band's configuration if needed) rather than starting a process. The standby is
the first thing stopped when memory gets short: a ``memory_short`` trigger
stops it and nothing else; a new one starts only after the next band change.

Reconciliation: what the manager believes runs is checked against what the
deployers report, on their events for our instance and every
``reconcile_s``. A detector stopped, migrated or killed by anyone else, or
one that ended ``failed``, is a ``detector_gone`` trigger: the planner's
choice starts afresh (a new instance, so a failed one is no dead end), and
any other detector of ours still running is stopped as a twin.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.deployer import new_instance_name
from kgadapt.deploy.migration import FirstOutput, migrate, reconfigure
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.onboard.adaptation import (
    FEATURE,
    Analyzer,
    BandTracker,
    Placement,
    Plan,
    Planner,
    PlanningError,
    Trigger,
    bands_from_rows,
)
from kgadapt.onboard.detector import set_active
from kgadapt.onboard.flight_phase import in_final_descent
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import DeploymentError, KgadaptError, MessageError, SourceNotStopped
from kgadapt.shared.hostmonitor import StatusTrust, TrustSettings, check_status
from kgadapt.shared.states import ENDED_EVENTS, KEPT_STATES, Change, TriggerKind

log = logging.getLogger(__name__)

UNMEASURED_MB = 5.0  # a detector's profile below this has only its exec-time sample
MEASURE_WITHIN_S = 10.0  # how long after a change an unmeasured detector is given the benefit of the doubt


@dataclass(frozen=True, kw_only=True)
class AdaptationSettings:
    """How the manager decides. ``preference``: see :mod:`kgadapt.onboard.adaptation`."""

    robot: str
    camera: str = "cam0"
    feature: str = FEATURE
    preference: str = "onboard-first"
    onboard_host: str = "onboard"
    hysteresis: float = 4.0
    dwell_s: float = 1.0
    ready_timeout: float = 20.0
    output_timeout: float = 5.0
    knowledge_timeout: float = 15.0  # bounded wait for the knowledge service at setup
    rss_refresh_s: float = 2.0
    startup_grace_s: float = 5.0  # how long the first placement waits for our own host to show online
    graph_catch_up_s: float = 2.0  # how long a host_back waits for the graph to show the host online
    settle_s: float = 1.0  # after a change, host statuses this young do not count for memory_short
    retry_s: float = 1.0  # the running host lost and no replacement started: try again this often
    reconcile_s: float = 0.5  # ask the running detector's deployer how it is at least this often
    in_place: bool = True  # reconfigure in place where the graph allows it (False: always migrate)
    status_window_s: float = 1.5  # a host's free memory counts when its statuses of this window (>= 2) agree
    standby: bool = False  # keep the neighbouring band's configuration started but idle where a host has room
    standby_check_s: float = 1.0  # how often the standby is checked against the graph


@dataclass(kw_only=True)
class Outcome:
    """What one decision did, for the graph, the event stream and the demo's summary."""

    trigger: Trigger
    plan: Plan | None = None
    outcome: str = ""
    latency_ms: float | None = None  # trigger observed -> new detector's first detection
    frames_lost: int | None = None
    detail: dict[str, Any] = field(default_factory=dict)


class AdaptationManager:
    """The MAPE-K loop. ``__init__`` does no I/O; ``setup(session)`` starts it."""

    name = "adaptation"

    def __init__(self, settings: AdaptationSettings, *, landed_state: Any = None) -> None:
        self.settings = settings
        # With a flight bridge in the same process: its landed state, read directly. Then
        # flight_state messages on Zenoh, which anyone holding a host certificate could
        # forge, are not listened to.
        self._landed_state = landed_state
        self.current: Placement | None = None
        self.history: list[Outcome] = []
        self.landing = False
        self._deferred: set[str] = set()  # kinds of change deferred in this descent: each recorded once
        self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=4096)
        # Liveliness changes, in their order, handled before the queue's backlog: after a long action
        # (a migration) hundreds of observations may wait there, and a lost host must not wait behind them.
        self._alive: collections.deque[tuple[str, bool]] = collections.deque()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._session: Any = None
        self._handles: list[Any] = []
        self._events_pub: Any = None
        self._knowledge: KnowledgeClient | None = None
        self._deployers: DeployerClient | None = None
        self._analyzer: Analyzer | None = None
        self._planner: Planner | None = None
        self._configs: dict[str, dict[str, Any]] = {}
        self._held_checked = 0.0
        self._decisions = 0
        self._setup_at = 0.0
        self._settled_after = 0.0
        self._changed_at = 0.0
        self._retry: Trigger | None = None  # a lost detector not yet replaced (e.g. the knowledge service was down)
        self._retry_at = 0.0
        self._lock = threading.Lock()
        self._probe: DeployerClient | None = None  # short timeout: a lost host is liveliness' business
        self._next_check = 0.0
        # (host, instance) of migration sources that could not be stopped (host cut off): twins to stop.
        self._leftovers: list[tuple[str, str]] = []
        self._next_leftover_check = 0.0
        self._trust = StatusTrust(TrustSettings(window_s=settings.status_window_s))
        self._refusal_logged: dict[str, float] = {}
        self.standby: Placement | None = None  # the warm standby (idle), when settings.standby
        self._standby_run_id: str | None = None
        self._standby_paused = False  # stopped for memory: none again until the band changes
        self._next_standby_check = 0.0

    # -- lifecycle -------------------------------------------------------

    def setup(self, session: Any) -> None:
        s = self.settings
        self._session = session
        self._knowledge = KnowledgeClient(session, s.robot, own=True, host=s.onboard_host)  # writes as its host's
        self._deployers = DeployerClient(session, s.robot)
        self._probe = DeployerClient(session, s.robot, timeout=min(0.5, s.reconcile_s))
        rows = self._wait_for_knowledge()
        self._configs = {str(r["config"]): r for r in rows}
        bands = bands_from_rows(rows)
        if not bands:
            raise KgadaptError(f"the knowledge graph has no detector configuration with a band for {s.feature}")
        self._analyzer = Analyzer(tracker=BandTracker(bands=bands, hysteresis=s.hysteresis, dwell_s=s.dwell_s))
        self._planner = Planner(ask=self._knowledge.query, feature=s.feature, preference=s.preference,
                                onboard_host=s.onboard_host, in_place=s.in_place)
        self._events_pub = session.declare_publisher(keys.adaptation_events(s.robot))
        self._handles = [
            session.declare_subscriber(keys.camera_illumination(s.robot, s.camera), self._on("illumination")),
            session.declare_subscriber(keys.host_status(s.robot), self._on("host_status")),
            session.liveliness().declare_subscriber(keys.host_alive(s.robot), self._on_alive, history=True),
            session.declare_subscriber(keys.flight_state(s.robot), self._on("flight_state")),
            session.declare_subscriber(keys.detector_markers(s.robot), self._on("detections")),
            session.declare_subscriber(keys.deployer_events(s.robot), self._on("deploy_event")),
        ]
        self._stop.clear()
        self._setup_at = time.monotonic()
        self._worker = threading.Thread(target=self._run, name="adaptation", daemon=True)
        self._worker.start()
        log.info("adaptation manager up: bands %s, preference %s", [b.name for b in bands], s.preference)

    def shutdown(self) -> None:
        self._stop.set()
        if self._worker is not None:
            self._worker.join(timeout=30)
            self._worker = None
        for handle in self._handles:
            try:
                handle.undeclare()
            except Exception as exc:  # session may be closing
                log.debug("undeclare: %s", exc)
        self._handles = []
        current, self.current = self.current, None
        standby, self.standby = self.standby, None
        if standby is not None and standby.instance and self._deployers is not None:
            try:
                self._deployers.stop(standby.host, standby.instance)
            except KgadaptError as exc:
                log.warning("could not stop the standby %s on %s: %s", standby.instance, standby.host, exc)
        if current is not None and current.instance and self._deployers is not None:
            # We started it; a clean shutdown stops it wherever it runs.
            try:
                self._deployers.stop(current.host, current.instance)
            except KgadaptError as exc:
                log.warning("could not stop %s on %s: %s", current.instance, current.host, exc)
        if self._events_pub is not None:
            try:
                self._events_pub.undeclare()
            except Exception as exc:
                log.debug("undeclare: %s", exc)
            self._events_pub = None

    def _wait_for_knowledge(self) -> list[dict[str, Any]]:
        deadline = time.monotonic() + self.settings.knowledge_timeout
        while True:
            try:
                return self._knowledge.query("detector_configs", {"feature": self.settings.feature})
            except KgadaptError as exc:
                if time.monotonic() >= deadline:
                    raise KgadaptError(f"adaptation: the knowledge service did not answer: {exc}") from exc
                time.sleep(0.2)

    # -- monitor: callbacks only queue -----------------------------------

    def _on(self, kind: str):
        def callback(sample: Any) -> None:
            self._put((kind, (str(sample.key_expr), sample.payload.to_bytes(), time.time())))
        return callback

    def _on_alive(self, sample: Any) -> None:
        alive = str(sample.kind).endswith("PUT")
        self._alive.append((keys.last_chunk(str(sample.key_expr), 2), alive))
        self._put(("wake", None))

    def _put(self, item: tuple[str, Any]) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            log.warning("adaptation: observation queue full; dropping %s", item[0])

    # -- analyse, plan, execute ------------------------------------------

    def _run(self) -> None:
        self._adopt_running()
        while not self._stop.is_set():
            if self._alive:
                kind, data = "alive", self._alive.popleft()
            else:
                try:
                    kind, data = self._queue.get(timeout=0.2)
                except queue.Empty:
                    kind, data = "tick", None
            try:
                trigger = self._observe(kind, data)
                if self.current is None:
                    # Nothing runs: whatever was observed, the question is where to start.
                    trigger = self._startup_trigger()
                if trigger is None:
                    trigger = self._due_retry()
                if trigger is None:
                    trigger = self._check_running()
                if trigger is None and self._leftovers:
                    self._stop_leftovers()
                if trigger is not None:
                    self._act(trigger)
                elif self.settings.standby:
                    self._keep_standby()
            except Exception:  # the loop must survive any single bad observation or failed action
                log.exception("adaptation: handling %s failed", kind)

    def _observe(self, kind: str, data: Any) -> Trigger | None:
        now = time.time()
        a = self._analyzer
        if kind == "alive":
            host, alive = data
            self._trust.alive(host, alive)
            if host == self.settings.onboard_host and not alive:
                # Our own token goes first when our agent shuts down; we go with it.
                return None
            return a.on_liveliness(host, alive, now, self.current)
        if kind in ("tick", "wake"):
            return None
        key, payload, received = data
        try:
            if kind == "illumination":
                m = messages.decode(payload, "illumination")
                return a.on_illumination(float(m["smoothed"]), now)
            if kind == "host_status":
                # Refused: what the knowledge service refuses, a host without a liveliness token,
                # a stale status, free memory its running detector's profile shows as used.
                host = keys.last_chunk(key, 2)
                held = self.current.held_mb if self.current is not None and self.current.host == host else 0.0
                m = check_status(host, messages.decode(payload, "host_status"))  # malformed: dropped below
                try:
                    m = self._trust.admit(host, m, received=received, used_mb=held)
                except MessageError as exc:
                    self._log_refusal(host, exc)
                    return None
                view = a.hosts.get(host)
                if view is None or not view.online:
                    return None
                # No move on the strength of one status: a shortage counts when every status of the
                # window shows it, and a host looks as roomy as the least of them (None: not yet confirmed).
                roomiest = self._trust.roomiest(host, received)
                if roomiest is None:
                    return None
                m = {**m, "memory_free_mb": roomiest}
                if self.current is not None and self.current.host == host:
                    self._refresh_held(now)
                # A status received before the last change settled was measured while old and
                # new detector both ran (it may have queued while we migrated): it updates the
                # view but cannot say the new detector does not fit.
                settled = received >= self._settled_after
                free = float(m["memory_free_mb"])
                running = self.current if settled else None
                if running is not None and running.host == host and free + running.held_mb < running.demand_mb:
                    # Before calling it unfit, make sure "held" is a real measurement: the
                    # profile's first sample is taken at exec (a few MiB).
                    self._refresh_held(now, force=True)
                    running = self.current
                    if running.held_mb < UNMEASURED_MB and now - self._changed_at < MEASURE_WITHIN_S:
                        running = None
                trigger = a.on_host_status(host, free_mb=free, cpu_load=float(m["cpu_load"]), now=now, running=running)
                view.memory_free_mb = self._trust.confirmed_free(host, received)
                sb = self.standby
                if (trigger is None and settled and sb is not None and sb.host == host
                        and (self.current is None or self.current.host != host) and free + sb.held_mb < sb.demand_mb):
                    self._refresh_standby_held()
                    sb = self.standby
                    if sb is not None and free + sb.held_mb < sb.demand_mb and sb.held_mb >= UNMEASURED_MB:
                        trigger = Trigger(TriggerKind.MEMORY_SHORT, now, {"host": host, "free_mb": round(free, 1),
                                                                            "held_mb": round(sb.held_mb, 1),
                                                                            "demand_mb": sb.demand_mb,
                                                                            "standby": sb.instance})
                return trigger
            if kind == "flight_state":
                m = messages.decode(payload, "flight_state")  # malformed ones are dropped and logged either way
                if self._landed_state is not None:
                    return None  # the bridge beside us is the one source
                self._set_landing(in_final_descent(m))  # landed state unknown in LAND/RTL counts as descent
                return None
            if kind == "deploy_event":
                m = messages.decode(payload, "deploy_event")
                if (self.standby is not None and m["instance"] == self.standby.instance
                        and m["event"] in ENDED_EVENTS):
                    log.info("adaptation: the standby %s %s", m["instance"], m["event"])
                    self.standby = None
                if (self.current is not None and m["instance"] == self.current.instance
                        and m["event"] in ENDED_EVENTS):
                    self._next_check = 0.0  # ask its deployer now, not at the next round
                return None
            if kind == "detections":
                m = messages.decode(payload, "detections")
                # Key and body must both name the instance we started: any detector may put on
                # detector/*/markers, under any name in the body.
                if (self.current is None or m["instance"] != self.current.instance
                        or keys.last_chunk(key, 2) != self.current.instance):
                    return None
                band = a.tracker.current.name if a.tracker.current else None
                # Only markers whose cells read clean count as evidence (phantoms do not hold up a rate).
                found = sum(c is not False for c in (m.get("clean") or [True] * len(m["ids"]))[:len(m["ids"])])
                return a.on_detection(found, now, self._expected_rate(self.current.config, band), self.current.config)
        except MessageError as exc:
            log.info("adaptation: dropped a %s message on %s: %s", kind, key, exc)
        return None

    def _set_landing(self, landing: bool) -> None:
        if not landing:
            self._deferred.clear()  # the next descent records its deferrals again
        self.landing = landing

    def _check_running(self) -> Trigger | None:
        """A ``detector_gone`` trigger when the deployer says our detector no longer runs."""
        current = self.current
        if current is None or not current.instance or time.monotonic() < self._next_check:
            return None
        host = self._analyzer.hosts.get(current.host)
        if host is not None and not host.online:
            return None  # host_lost covers it
        try:
            state = str(self._probe.status(current.host, current.instance).get("state"))
        except DeploymentError as exc:  # the deployer does not know it (any more)
            state = f"unknown to its deployer ({exc})"
        except KgadaptError as exc:  # no answer: the host's liveliness decides
            log.debug("adaptation: no status for %s: %s", current.instance, exc)
            return None
        finally:
            # Counted from the answer (or the timeout): unanswered probes back to back would leave
            # the loop no time for the observations waiting in the queue.
            self._next_check = time.monotonic() + self.settings.reconcile_s
        if state in KEPT_STATES:
            return None
        log.warning("adaptation: detector %s on %s is %s; replacing it", current.instance, current.host, state)
        return Trigger(TriggerKind.DETECTOR_GONE, time.time(), {"instance": current.instance, "host": current.host,
                                                                     "state": state[:120]})

    def _stop_leftovers(self) -> None:
        """Stop the sources of migrations that could not be stopped, once their deployers answer."""
        if time.monotonic() < self._next_leftover_check:
            return
        self._next_leftover_check = time.monotonic() + self.settings.reconcile_s
        for host, instance in list(self._leftovers):
            state = self._analyzer.hosts.get(host)
            if state is not None and not state.online:
                continue  # host_back's reconcile or the next round
            try:
                self._deployers.stop(host, instance)
                log.info("adaptation: stopped %s on %s, left running by a migration", instance, host)
            except DeploymentError as exc:  # not running or unknown there any more: nothing to stop
                log.info("adaptation: %s on %s is gone: %s", instance, host, exc)
            except KgadaptError as exc:  # no answer: try again next round
                log.debug("adaptation: %s on %s not stopped yet: %s", instance, host, exc)
                continue
            self._leftovers.remove((host, instance))

    def _stop_twins(self) -> list[str]:
        """Stop every live detector of ours but the current one, on any host."""
        try:
            processes = self._deployers.list("*")
        except KgadaptError:
            return []
        stopped = []
        for p in processes:
            if (p.get("state") in KEPT_STATES and p.get("config") in self._configs
                    and self.current is not None and p.get("instance") != self.current.instance
                    and (self.standby is None or p.get("instance") != self.standby.instance)):
                try:
                    self._deployers.stop(str(p["host"]), str(p["instance"]))
                    stopped.append(str(p["instance"]))
                except KgadaptError as exc:
                    log.warning("adaptation: could not stop twin %s: %s", p.get("instance"), exc)
        return stopped

    def _startup_trigger(self) -> Trigger | None:
        a = self._analyzer
        if a.tracker.current is None or not any(h.online for h in a.hosts.values()):
            return None
        if not self._own_host_known():
            return None
        now = time.time()
        # Within the grace period, every online host's figures confirmed (else the first plan
        # would see only the host confirmed first); after it, any host's.
        confirmed = [self._trust.confirmed_free(h.name, now) is not None for h in a.hosts.values() if h.online]
        within_grace = time.monotonic() - self._setup_at <= self.settings.startup_grace_s
        if not (all(confirmed) if within_grace else any(confirmed)):
            return None  # a plan now could only fail or go elsewhere
        return Trigger(TriggerKind.STARTUP, time.time(), {"band": a.tracker.current.name})

    def _log_refusal(self, host: str, exc: Exception) -> None:
        now = time.monotonic()
        if now - self._refusal_logged.get(host, -1e9) >= 5.0:  # a flood of forgeries logs once per host per 5 s
            self._refusal_logged[host] = now
            log.warning("adaptation: refused %s (%d refused so far)", exc, self._trust.refused)

    def _graph_shows_online(self, host: str, timeout: float) -> bool:
        """Wait (bounded) until the graph shows ``host`` online with a free-memory figure.

        We and the knowledge service see a liveliness token at the same moment;
        planning before the service has written it would leave the host out.
        """
        deadline = time.monotonic() + timeout
        while True:
            try:
                rows = self._knowledge.query("platforms", {})
            except KgadaptError:
                rows = []
            if any(r.get("platform") == host and r.get("online") and r.get("memory_free_mb") is not None
                   for r in rows):
                return True
            if time.monotonic() >= deadline or self._stop.is_set():
                return False
            time.sleep(0.05)

    def _own_host_known(self) -> bool:
        """True once the graph shows our own host online with its figures, or after a grace period.

        Our agent declares its liveliness token only after all its parts are up,
        so the first plan could otherwise see only the remote host online.
        """
        if time.monotonic() - self._setup_at > self.settings.startup_grace_s:
            return True
        own = self._analyzer.hosts.get(self.settings.onboard_host)
        if own is None or not own.online:
            return False
        try:
            rows = self._knowledge.query("platforms", {})
        except KgadaptError:
            return False
        # Online and with a free-memory figure: a status put right after open() can be lost.
        return any(r.get("platform") == self.settings.onboard_host and r.get("online")
                   and r.get("memory_free_mb") is not None for r in rows)

    def _expected_rate(self, config: str, band: str | None) -> float | None:
        planned = getattr(self, "_expected", None)  # (config, band, rate) from the plan's ranking
        if planned is not None and planned[:2] == (config, band):
            return planned[2]
        row = self._configs.get(config)
        if row is None or band is None or row.get("band") != band:
            return None
        rate = row.get("detection_rate")
        return float(rate) if rate is not None else None

    def _refresh_held(self, now: float, *, force: bool = False) -> None:
        if self.current is None or (not force and now - self._held_checked < self.settings.rss_refresh_s):
            return
        self._held_checked = now
        run_id = getattr(self, "_run_id", None)
        if not run_id:
            return
        try:
            # The maximum, not the last sample: the first sample is taken right after exec
            # (a few MiB) and would make the detector look as if it held nothing.
            rows = self._knowledge.cypher(
                "MATCH (r:ProcessProfile {name: $run_id}) RETURN r.rss_mb_max AS rss", {"run_id": run_id})
        except KgadaptError as exc:
            log.debug("adaptation: no profile figures yet: %s", exc)
            return
        if rows and rows[0].get("rss") is not None:
            c = self.current
            self.current = Placement(config=c.config, deployment=c.deployment, host=c.host, instance=c.instance,
                                     demand_mb=c.demand_mb, held_mb=float(rows[0]["rss"]))

    def _act(self, trigger: Trigger) -> None:
        a = self._analyzer
        band = a.tracker.current
        if band is None:
            return
        if trigger.kind == TriggerKind.HOST_BACK:
            self._graph_shows_online(str(trigger.detail.get("host")), self.settings.graph_catch_up_s)
            # A host back from a partition may still run the detector we replaced: no twins.
            twins = self.reconcile(str(trigger.detail.get("host")))
            if twins:
                self._record(Outcome(trigger=trigger, outcome=f"stopped twin(s) {', '.join(twins)}"))
        if (trigger.kind == TriggerKind.HOST_BACK and self._retry is None and not trigger.detail.get("confirming")
                and self._trust.confirmed_free(str(trigger.detail.get("host")), time.time()) is None):
            # The host is back but none of its statuses is confirmed yet: plan once they can be, not
            # now without it (the soak saw a needless migration to the other host that way).
            self._retry = Trigger(trigger.kind, trigger.time, {**trigger.detail, "confirming": True})
            self._retry_at = time.monotonic() + self.settings.status_window_s
            if not (self.current is not None and self.current.host in
                    tuple(h.name for h in a.hosts.values() if not h.online)):
                return
        if self._landed_state is not None:
            self._set_landing(self._landed_state() == "LANDING")
        if trigger.kind == TriggerKind.BAND_CHANGED:
            self._standby_paused = False
        if trigger.kind == TriggerKind.MEMORY_SHORT and self.standby is not None:
            # The standby is the first thing to go: stop it, and plan nothing else on this trigger;
            # if the host is still short once the statuses show its memory back, the next one moves.
            sb = self.standby
            stopped = self._stop_standby()
            self._standby_paused = True
            self._settled_after = time.time() + self.settings.settle_s
            self._record(Outcome(trigger=trigger, outcome=f"stopped the standby {sb.instance} ({sb.config}@{sb.host}) "
                                 "first" + ("" if stopped else " (its deployer did not answer)"),
                                 detail={"change": Change.STANDBY_STOPPED, "instance": sb.instance,
                                         "standby": {"config": sb.config, "host": sb.host, "instance": sb.instance,
                                                     "run_id": self._standby_run_id}}))
            return
        lost = tuple(h.name for h in a.hosts.values() if not h.online)
        running_lost = self.current is not None and (self.current.host in lost or trigger.kind == TriggerKind.DETECTOR_GONE)
        if self.landing and not (trigger.urgent or running_lost):
            # One decision per kind of change and descent: a descent (forged or not) with a flapping
            # light or repeated triggers must not write a decision per message.
            if trigger.kind not in self._deferred:
                self._deferred.add(trigger.kind)
                self._record(Outcome(trigger=trigger, outcome="deferred: final descent"))
            else:
                log.info("adaptation: %s deferred again (final descent)", trigger.describe())
            return
        started = time.perf_counter()
        try:
            # Only confirmed figures place a detector: a host whose statuses of the window do not
            # all show room (or that has too few yet) is no target, whatever the graph says.
            now = time.time()
            # The running detector's host keeps it unless every status of the window shows it short
            # (a forged "full" between real statuses must not move the detector off it).
            here = self.current.host if self.current is not None else None
            live = {h.name: free for h in a.hosts.values() if h.online
                    and (free := (self._trust.roomiest if h.name == here else self._trust.confirmed_free)(
                        h.name, now)) is not None}
            # Configurations whose detections collapsed in this band stay out until the band changes.
            exclude = tuple(sorted(a.collapsed))
            plan = self._planner.plan(band=band.name, running=None if running_lost else self.current, exclude=exclude,
                                      lost_hosts=lost, live_free=live)
        except (PlanningError, KgadaptError) as exc:
            self._record(Outcome(trigger=trigger, outcome=f"no plan: {exc}"))
            if running_lost:
                self._retry_later(trigger)
            return
        if plan.same_as(self.current) and not running_lost:
            if trigger.kind not in (TriggerKind.HOST_BACK, TriggerKind.STARTUP):
                self._record(Outcome(trigger=trigger, plan=plan, outcome="kept"))
            return
        try:
            via = self._standby_for(plan, lost, running_lost)
            if via is not None:
                result = self._activate_standby(plan, trigger, reconfigure_to=via[1], why=via[0],
                                                old=None if running_lost else self.current)
            elif self.current is None or running_lost:
                result = self._start_fresh(plan, trigger)
            else:
                change = plan.inputs.get("change", Change.MIGRATE)  # the planner's choice, from the graph
                why = plan.inputs.get("change_why", "")
                result = None
                if change == Change.RECONFIGURE:
                    try:
                        result = self._reconfigure(plan, trigger)
                    except KgadaptError as exc:  # refused or unanswered: the old one still runs; migrate
                        why = f"in-place change refused ({exc}); migrated instead"
                if result is None:
                    result = self._switch(plan, trigger)
                result.detail["change"] = Change.RECONFIGURE if result.outcome == "reconfigured" else Change.MIGRATE
                result.detail["change_why"] = why
        except KgadaptError as exc:
            result = Outcome(trigger=trigger, plan=plan, outcome=f"failed: {exc}")
        result.detail["plan_ms"] = round((time.perf_counter() - started) * 1000.0, 1)
        if trigger.kind == TriggerKind.DETECTOR_GONE and not result.outcome.startswith("failed"):
            twins = self._stop_twins()  # e.g. what an outside migrate started elsewhere
            if twins:
                result.detail["stopped_twins"] = twins
        self._record(result)
        if running_lost and not result.outcome.startswith("failed"):
            a.reset_rate()
        elif running_lost:
            self._retry_later(trigger)

    def _retry_later(self, trigger: Trigger) -> None:
        """The detector is gone and none replaced it: act on ``trigger`` again after ``retry_s``.

        Without this, a failover that fails once (the knowledge service restarting
        its store, a deployer not answering) would leave the robot without a
        detector until some other trigger came. The trigger keeps its time, so the
        recorded latency runs from the loss.
        """
        self._retry = trigger
        self._retry_at = time.monotonic() + self.settings.retry_s

    def _due_retry(self) -> Trigger | None:
        if self._retry is None or time.monotonic() < self._retry_at:
            return None
        trigger, self._retry = self._retry, None
        return trigger

    def _start_fresh(self, plan: Plan, trigger: Trigger) -> Outcome:
        t = plan.target
        instance = new_instance_name(t.config, t.host)
        first = FirstOutput()
        sub = self._session.declare_subscriber(keys.detector_markers(self.settings.robot, instance), first)
        try:
            snapshot = self._deployers.start(t.host, t.deployment, t.config, instance=instance, wait_ready=True,
                                             ready_timeout=self.settings.ready_timeout)
            got = first.event.wait(self.settings.output_timeout)
        finally:
            sub.undeclare()
        self._set_current(plan, instance, snapshot.get("run_id"))
        latency = (first.wall - trigger.time) * 1000.0 if got and first.wall else None
        return Outcome(trigger=trigger, plan=plan, outcome="started" if got else "started, no detections yet",
                       latency_ms=latency, detail={"instance": instance, "pid": snapshot.get("pid")})

    def _reconfigure(self, plan: Plan, trigger: Trigger) -> Outcome:
        t, old = plan.target, self.current
        first = FirstOutput(config=t.config)
        sub = self._session.declare_subscriber(keys.detector_markers(self.settings.robot, old.instance), first)
        report = None
        try:
            try:
                report = reconfigure(self._session, self.settings.robot, old.host, old.instance, t.config,
                                     timeout=self.settings.output_timeout)
            except KgadaptError:
                # Unanswered is not refused: if its deployer's record names the new configuration,
                # the detector took it (a migration now would find nothing to change).
                if self._deployers.status(old.host, old.instance).get("config") != t.config:
                    raise
            got = first.event.wait(self.settings.output_timeout)
        finally:
            sub.undeclare()
        self.current = Placement(config=t.config, deployment=t.deployment, host=t.host, instance=old.instance,
                                 demand_mb=t.demand_mb, held_mb=old.held_mb)
        run_id = getattr(self, "_run_id", None)
        self._set_current(plan, old.instance, run_id)
        latency = (first.wall - trigger.time) * 1000.0 if got and first.wall else None
        return Outcome(trigger=trigger, plan=plan, outcome="reconfigured", latency_ms=latency, frames_lost=0,
                       detail={"instance": old.instance, "previous_instance": old.instance,
                               "from": f"{old.config}@{old.host}",
                               **({} if report is None else {
                                   "first_seq": report.first_seq, "check_ms": report.check_ms,
                                   "build_ms": report.build_ms, "reply_ms": round(report.reply_ms, 1)})})

    def _switch(self, plan: Plan, trigger: Trigger) -> Outcome:
        t, old = plan.target, self.current
        called_at = time.time()
        left_running = ""
        try:
            report = migrate(self._session, self.settings.robot, old.instance, t.host, source_host=old.host,
                             deployment=t.deployment, config=t.config, client=self._deployers,
                             ready_timeout=self.settings.ready_timeout, output_timeout=self.settings.output_timeout)
        except SourceNotStopped as exc:
            # The new detector runs and detects: it is ours now. The old one is a twin, stopped
            # as soon as its deployer answers (or by host_back's reconcile).
            report = exc.report
            left_running = str(exc)
            self._leftovers.append((old.host, old.instance))
            log.warning("adaptation: %s; %s is the detector now, %s will be stopped when %s answers",
                        exc, report.new_instance, old.instance, old.host)
        # The start's own snapshot names the run: no request to a host that may be gone by now.
        self._set_current(plan, report.new_instance, report.new_run_id)
        # migrate() measures from its own start; add the time from the trigger to that start.
        latency = (called_at - trigger.time) * 1000.0 + report.first_output_ms
        return Outcome(trigger=trigger, plan=plan, outcome="migrated", latency_ms=latency,
                       detail={"instance": report.new_instance, "previous_instance": old.instance,
                               "from": f"{old.config}@{old.host}", "target_ready_ms": report.target_ready_ms,
                               **({"source_not_stopped": left_running[:200]} if left_running else {})})

    # -- the warm standby ---------------------------------------------------

    def _standby_for(self, plan: Plan, lost: tuple[str, ...], running_lost: bool) -> tuple[str, str | None] | None:
        """How the standby can serve ``plan``: (why, configuration to reconfigure it to or None), or None."""
        sb = self.standby
        if sb is None or sb.host in lost or self.current is None:
            return None
        if sb.config == plan.target.config:
            return f"the plan's configuration {sb.config} is the standby's, idle on {sb.host}: a switch", None
        if not running_lost:
            return None
        # Failover: a standby of another configuration, changed in place, still beats a new process.
        change, why = self._planner.change(sb, dataclasses.replace(plan.target, host=sb.host))
        if change != Change.RECONFIGURE:
            return None
        return f"{self.current.host} lost; the standby {sb.config} on {sb.host} takes over, {why}", plan.target.config

    def _activate_standby(self, plan: Plan, trigger: Trigger, *, reconfigure_to: str | None, why: str,
                          old: Placement | None) -> Outcome:
        """Make the standby the running detector; idle ``old`` (it becomes the standby) or stop it."""
        sb = self.standby
        s = self.settings
        config = reconfigure_to or sb.config
        first = FirstOutput(config=config)
        sub = self._session.declare_subscriber(keys.detector_markers(s.robot, sb.instance), first)
        try:
            set_active(self._session, s.robot, sb.host, sb.instance, True, timeout=s.output_timeout)
            if reconfigure_to is not None:
                reconfigure(self._session, s.robot, sb.host, sb.instance, reconfigure_to, timeout=s.output_timeout)
            got = first.event.wait(s.output_timeout)
        finally:
            sub.undeclare()
        run_id = self._standby_run_id
        self.standby, self._standby_run_id = None, None
        target = dataclasses.replace(plan.target, config=config, host=sb.host, deployment=sb.deployment,
                                     demand_mb=plan.target.demand_mb if config == plan.target.config else sb.demand_mb)
        plan = dataclasses.replace(plan, target=target)
        self._set_current(plan, sb.instance, run_id)
        detail: dict[str, Any] = {"instance": sb.instance, "change": Change.STANDBY, "change_why": why,
                                  "standby": {"config": sb.config, "host": sb.host, "instance": sb.instance}}
        if old is not None and old.instance:
            detail["previous_instance"] = old.instance
            detail["from"] = f"{old.config}@{old.host}"
            old_run_id = getattr(self, "_old_run_id", None)
            try:
                set_active(self._session, s.robot, old.host, old.instance, False, timeout=s.output_timeout)
                self.standby, self._standby_run_id = old, old_run_id
                detail["old"] = "idle: the standby now"
            except KgadaptError as exc:
                log.info("adaptation: could not idle %s (%s); stopping it", old.instance, exc)
                try:
                    self._deployers.stop(old.host, old.instance)
                    detail["old"] = "stopped"
                except KgadaptError as err:
                    self._leftovers.append((old.host, old.instance))
                    detail["old"] = f"left running: {err}"[:200]
        latency = (first.wall - trigger.time) * 1000.0 if got and first.wall else None
        return Outcome(trigger=trigger, plan=plan, outcome="switched to the standby" if got
                       else "switched to the standby, no detections yet", latency_ms=latency,
                       detail=detail)

    def _stop_standby(self) -> bool:
        sb, self.standby = self.standby, None
        self._standby_run_id = None
        if sb is None or not sb.instance:
            return True
        try:
            self._deployers.stop(sb.host, sb.instance)
            log.info("adaptation: stopped the standby %s on %s", sb.instance, sb.host)
            return True
        except DeploymentError as exc:  # gone already
            log.info("adaptation: the standby %s is gone: %s", sb.instance, exc)
            return True
        except KgadaptError as exc:
            log.warning("adaptation: could not stop the standby %s on %s: %s", sb.instance, sb.host, exc)
            self._leftovers.append((sb.host, sb.instance))
            return False

    def _refresh_standby_held(self) -> None:
        sb, run_id = self.standby, self._standby_run_id
        if sb is None or not run_id:
            return
        rss = self._profile_rss(run_id)
        if rss is not None and self.standby is sb:
            self.standby = dataclasses.replace(sb, held_mb=rss)

    def _profile_rss(self, run_id: str) -> float | None:
        try:
            rows = self._knowledge.cypher(
                "MATCH (r:ProcessProfile {name: $run_id}) RETURN r.rss_mb_max AS rss", {"run_id": run_id})
        except KgadaptError as exc:
            log.debug("adaptation: no profile figures yet: %s", exc)
            return None
        return float(rows[0]["rss"]) if rows and rows[0].get("rss") is not None else None

    def _keep_standby(self) -> None:
        """Start, keep or replace the warm standby as the graph allows (see the module's docstring)."""
        now = time.monotonic()
        if now < self._next_standby_check:
            return
        self._next_standby_check = now + self.settings.standby_check_s
        a, current = self._analyzer, self.current
        if current is None or not current.instance or self.landing or self._standby_paused or self._retry is not None:
            return
        band = a.tracker.neighbour(a.level)
        sb = self.standby
        if band is None:
            return
        view = a.hosts.get(sb.host) if sb is not None else None
        if sb is not None and view is not None and not view.online:
            # Gone with its host; should it come back from a partition, host_back's reconcile stops it.
            log.info("adaptation: the standby %s went with %s", sb.instance, sb.host)
            self.standby = self._standby_run_id = None
            return
        if sb is not None:
            try:
                _full, left = self._planner.candidates(band.name)
            except (PlanningError, KgadaptError):
                return
            if left[0].get("config") == sb.config and sb.config != current.config:
                return  # still the one the neighbouring band wants
            log.info("adaptation: the standby %s (%s) is not band %s's any more", sb.instance, sb.config, band.name)
            self._stop_standby()
            return  # its memory shows free in a later status; start the new one then
        wall = time.time()
        lost = tuple(h.name for h in a.hosts.values() if not h.online)
        live = {h.name: free for h in a.hosts.values() if h.online
                and (free := self._trust.confirmed_free(h.name, wall)) is not None}
        try:
            plan = self._planner.standby(band=band.name, running=current, lost_hosts=lost, live_free=live)
        except KgadaptError as exc:
            log.debug("adaptation: no standby plan: %s", exc)
            return
        if plan is None:
            return
        t = plan.target
        instance = new_instance_name(t.config, t.host)
        trigger = Trigger(TriggerKind.STANDBY, wall, {"band": band.name})
        try:
            snapshot = self._deployers.start(t.host, t.deployment, t.config, instance=instance, wait_ready=True,
                                             ready_timeout=self.settings.ready_timeout)
        except KgadaptError as exc:
            self._record(Outcome(trigger=trigger, plan=plan, outcome=f"failed: {exc}", detail={"change": Change.STANDBY_START}))
            return
        try:
            # Its deployer said ready; the activity queryable's declaration may still be on its way
            # (set_active asks again until then). A standby not made idle is stopped, and the
            # decision says so: it is no standby the failover could count on.
            set_active(self._session, self.settings.robot, t.host, instance, False, timeout=self.settings.output_timeout)
        except KgadaptError as exc:
            try:
                self._deployers.stop(t.host, instance)
            except KgadaptError as err:
                log.warning("adaptation: could not stop %s: %s", instance, err)
            self._record(Outcome(trigger=trigger, plan=plan, outcome=f"failed: not made idle: {exc}",
                                 detail={"change": Change.STANDBY_START}))
            return
        self.standby = dataclasses.replace(t, instance=instance)
        self._standby_run_id = snapshot.get("run_id")
        self._record(Outcome(trigger=trigger, plan=plan, outcome="standby started (idle)",
                             detail={"change": Change.STANDBY_START, "instance": instance, "pid": snapshot.get("pid"),
                                     "standby": {"config": t.config, "host": t.host, "instance": instance,
                                                 "run_id": snapshot.get("run_id")}}))

    def _set_current(self, plan: Plan, instance: str, run_id: str | None) -> None:
        t = plan.target
        self.current = Placement(config=t.config, deployment=t.deployment, host=t.host, instance=instance,
                                 demand_mb=t.demand_mb, held_mb=0.0)
        self._old_run_id = getattr(self, "_run_id", None)  # the replaced detector's (it may become the standby)
        self._run_id = run_id
        self._held_checked = 0.0
        self._changed_at = time.time()
        self._settled_after = self._changed_at + self.settings.settle_s
        self._analyzer.reset_rate()
        rate = plan.inputs.get("expected_rate")
        self._expected = (t.config, plan.inputs.get("band"), float(rate) if rate is not None else None)

    def _adopt_running(self) -> None:
        """After a restart: adopt one live detector of ours, stop any twin."""
        try:
            processes = self._deployers.list("*")
        except KgadaptError as exc:
            log.info("adaptation: no deployer answered at start (%s); nothing to adopt", exc)
            return
        live = [p for p in processes if p.get("state") in KEPT_STATES and p.get("config") in self._configs]
        if not live:
            return
        keep, *twins = sorted(live, key=lambda p: (p.get("host") != self.settings.onboard_host, p.get("instance")))
        row = self._configs[keep["config"]]
        self.current = Placement(config=keep["config"], deployment=keep["deployment"], host=keep["host"],
                                 instance=keep["instance"], demand_mb=float(row.get("memory_demand_mb") or 0))
        self._run_id = keep.get("run_id")
        log.info("adaptation: adopted %s on %s", keep["instance"], keep["host"])
        if self.settings.standby:  # it may have been our standby, idle
            try:
                set_active(self._session, self.settings.robot, keep["host"], keep["instance"], True)
            except KgadaptError as exc:
                log.warning("adaptation: could not make the adopted %s active: %s", keep["instance"], exc)
        for twin in twins:
            try:
                self._deployers.stop(twin["host"], twin["instance"])
                log.info("adaptation: stopped twin %s on %s", twin["instance"], twin["host"])
            except KgadaptError as exc:
                log.warning("adaptation: could not stop twin %s: %s", twin["instance"], exc)

    def reconcile(self, host: str) -> list[str]:
        """Stop detectors on ``host`` that are not the current one (after a partition heals)."""
        stopped = []
        try:
            processes = self._deployers.list(host)
        except KgadaptError:
            return stopped
        for p in processes:
            if (p.get("state") in KEPT_STATES and p.get("config") in self._configs
                    and (self.current is None or p.get("instance") != self.current.instance)
                    and (self.standby is None or p.get("instance") != self.standby.instance)):
                try:
                    self._deployers.stop(host, p["instance"])
                    stopped.append(p["instance"])
                except KgadaptError as exc:
                    log.warning("adaptation: could not stop twin %s on %s: %s", p["instance"], host, exc)
        return stopped

    # -- knowledge -------------------------------------------------------

    def _record(self, outcome: Outcome) -> None:
        trigger, plan = outcome.trigger, outcome.plan
        self._decisions += 1
        now = time.time()
        name = f"{self.settings.robot}-decision-{int(now * 1000)}-{self._decisions}"
        target = plan.target if plan else None
        inputs = {"trigger": dict(trigger.detail), **(dict(plan.inputs) if plan else {}), **outcome.detail}
        params = {
            "name": name, "time": now, "trigger": trigger.describe(),
            "inputs_json": json.dumps(inputs, default=str),
            "query": ",".join(plan.queries) if plan else None,
            "config": target.config if target else None, "host": target.host if target else None,
            "duration_ms": None if outcome.latency_ms is None else round(outcome.latency_ms, 1),
            "outcome": outcome.outcome if not plan else f"{outcome.outcome}: {plan.reason}",
        }
        try:
            self._knowledge.write("decision", params)
        except KgadaptError as exc:
            log.warning("adaptation: could not record decision %s: %s", name, exc)
        with self._lock:
            self.history.append(outcome)
        event = {
            "time": now, "trigger": trigger.describe(), "outcome": outcome.outcome[:256],
            "decision": {
                "config": params["config"], "host": params["host"], "latency_ms": params["duration_ms"],
                "trigger_kind": trigger.kind, "frames_lost": outcome.frames_lost, "name": name,
                "instance": self.current.instance if self.current else None,
                "previous_instance": outcome.detail.get("previous_instance"),
                "trigger_time": trigger.time, "change": outcome.detail.get("change"),
            },
        }
        try:
            self._events_pub.put(messages.encode("adaptation_event", event))
        except Exception as exc:  # publishing is best effort; the graph has the record
            log.debug("adaptation event not published: %s", exc)
        log.info("decision %s: %s -> %s@%s (%s, %s ms)", name, trigger.describe(), params["config"],
                 params["host"], outcome.outcome, params["duration_ms"])
