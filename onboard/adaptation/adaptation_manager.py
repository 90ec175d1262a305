"""The adaptation manager: the paper's Fig. 6 loop as a part of the onboard agent.

Monitor (Zenoh subscribers: illumination, host status, host liveliness, flight
state, the running detector's detections) -> analyse (:mod:`kgadapt.onboard.adaptation.adaptation`)
-> plan (named queries through the knowledge service) -> execute (the hosts'
deployers) -> knowledge (every decision written into the graph).

This module only observes and executes: every decision (what an observation
means, what a trigger leads to, how a plan is carried out, when a check is due)
is a pure function of :mod:`kgadapt.onboard.adaptation.adaptation` (analyse, plan) or
:mod:`kgadapt.onboard.adaptation.adaptation_policy` (the loop's rules and its schedule, one
:class:`~kgadapt.onboard.adaptation.adaptation_policy.LoopState`), tested without processes.

Callbacks only queue observations; one worker thread analyses and acts, so a
migration never runs inside a Zenoh callback and decisions happen one at a time.
It waits on that queue until the next check of its own is due. Host liveliness
changes have their own queue, served first: a host lost during a long action is
acted on next, not after the observations queued meanwhile.

Execution: a planned change on the same host whose deployments the graph
says may be changed in place (the planner asks ``in_place_change``) reconfigures
the running detector between two frames (:func:`kgadapt.deploy.migration.reconfigure`);
otherwise, or when that is refused, it is make-before-break: start the new
detector, wait for its first detections, and only then stop the old one
(:func:`kgadapt.deploy.migration.migrate`). The decision records which and why. When the host running the detector is
lost, a new detector starts at once on a host that can hold it. That move is planned ahead: in the
loop's quiet moments the manager plans the loss of the running detector's host (the placement with
that host counted lost, and whether the standby takes it) and plans it again when what it rests on
changes (band, running detector, standby, hosts lost, configurations left out) or after
``ready_move_s``; at the loss it is carried out with no question to the graph (the decision's inputs
say ``planned_ahead_ms``). A change of band is planned ahead the same way: one band per quiet moment,
the manager plans the move into each band other than the running one (the running detector's host
credited with what it holds, no configuration left out: a band change clears them), again when the
running detector, the standby or the hosts lost change, or after ``ready_move_s``; the detector's
reflex (or the manager's own band change) then acts on it at once. During final
descent (flight state ``LANDING``, or landed state unknown in LAND/RTL:
:func:`kgadapt.onboard.flight.flight_phase.in_final_descent`, from the bridge beside it in the onboard agent,
else from ``flight_state`` messages) planned changes are deferred; losing the running host is still acted
on, another host's loss is deferred like them.

Warm standby (``standby=True``, ``kgadapt onboard --standby``; off by default):
when the ``placement`` query says a host has room for the configuration of the
band the light most likely goes to next as well (the band it left at the last
change, else the neighbour whose edge it is nearest:
:meth:`kgadapt.onboard.adaptation.adaptation.BandTracker.neighbour`), the
manager starts that configuration there through the deployer (supervised and
profiled like any detector, its memory in the graph) and makes it idle
(:func:`kgadapt.onboard.perception.detector.set_active`). A change whose target configuration is the
standby's is then a switch: activate the standby, make it the running detector,
idle the old one (it becomes the standby). Losing the host that runs the
detector activates a standby on another host (reconfigured in place to the
band's configuration if needed) rather than starting a process. The standby is
the first thing stopped when memory gets short: a ``memory_short`` trigger
stops it and nothing else; a new one starts only after the next band change (the smoothed light's, or a
reflex that took another band).

Reflexes: the running detector may switch configuration in place on its own
evidence (:mod:`kgadapt.onboard.perception.reflex`) and says so on its ``reflex`` key (its
last reflex again about once a second, should the message be lost; each count
is acted on once).
The manager takes the detector's configuration as what runs (it does not fight
it), moves its band to the reflex's (the smoothed light gets ``reflex_hold_s``
to agree; past that, a disagreement lasting the dwell undoes it as a band
change), records a decision with trigger ``reflex`` and its inputs, and plans
for the band as for any trigger: where the band's best configuration is
another, or needs another host (the reflex took the best this host can run in
place, or nothing), it reconfigures or migrates as usual.

Live evidence: every frame of the running detector counts towards its live
detection rate in the band the manager holds, while markers are expected (seen
within a second, or the pad in view in final descent); the changed windows are
written every few seconds (write verb ``live_rate``: one ``LIVE_RATE`` relation
per configuration, band and condition, updated), and the planner ranks by them
where they are fresh (:mod:`kgadapt.onboard.adaptation.live_rate`).

Reconciliation: what the manager believes runs is checked against what the
deployers report, on their events for our instance and every
``reconcile_s``. A detector stopped, migrated or killed by anyone else, or
one that ended ``failed``, is a ``detector_gone`` trigger: the planner's
choice starts afresh (a new instance, so a failed one is no dead end), and
any other detector of ours still running is stopped as a twin.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import queue
import threading
import time
from typing import Any, Callable, TypeVar

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.deployer import new_instance_name
from kgadapt.deploy.migration import FirstOutput, MigrationReport, migrate, reconfigure
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.onboard.adaptation import adaptation_policy as policy
from kgadapt.onboard.adaptation.adaptation import (
    Analyzer,
    BandTracker,
    Placement,
    Plan,
    Planner,
    PlanningError,
    Trigger,
    bands_from_rows,
)
from kgadapt.onboard.adaptation.adaptation_policy import Action, AdaptationSettings, Execution, LoopState, Outcome, StandbyStep
from kgadapt.onboard.adaptation.live_rate import LiveRates
from kgadapt.onboard.flight.flight_phase import in_final_descent
from kgadapt.onboard.perception.detector import set_active
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import DeploymentError, KgadaptError, MessageError, SourceNotStopped
from kgadapt.shared.hostmonitor import StatusTrust, TrustSettings, check_status
from kgadapt.shared.rpc import declared
from kgadapt.shared.states import Change, TriggerKind

__all__ = ["AdaptationManager", "AdaptationSettings", "Outcome"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")


def _set_up(part: _T | None) -> _T:
    """A part setup() makes; DeploymentError when used before it."""
    if part is None:
        raise DeploymentError("the adaptation manager is not set up; call setup() first")
    return part


class AdaptationManager:
    """The MAPE-K loop. ``__init__`` does no I/O; ``setup(session)`` starts it."""

    name = "adaptation"

    def __init__(self, settings: AdaptationSettings, *, final_descent: Callable[[], bool] | None = None) -> None:
        self.settings = settings
        # With a flight bridge in the same process: whether its flight state is a final descent
        # (in_final_descent), read directly. Then flight_state messages on Zenoh, which anyone holding a
        # host certificate could forge, are not listened to.
        self._final_descent = final_descent
        self.current: Placement | None = None  # the running detector (its run id and held memory as last known)
        self.standby: Placement | None = None  # the warm standby (idle), when settings.standby
        # This run's decisions, oldest first; the graph keeps every one, memory the last history_size.
        self.history: collections.deque[Outcome] = collections.deque(maxlen=settings.history_size)
        self.landing = False
        self._deferred: set[str] = set()  # kinds of change deferred in this descent: each recorded once
        self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=4096)
        # Liveliness changes, in their order, handled before the queue's backlog: after a long action
        # (a migration) hundreds of observations may wait there, and a lost host must not wait behind them.
        self._alive: collections.deque[tuple[str, bool]] = collections.deque()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._session: Any = None
        self._declarations = contextlib.ExitStack()  # subscribers and the events publisher
        self._events_pub: Any = None
        # Made by setup(); read through the properties below, which refuse before it.
        self._knowledge_or_none: KnowledgeClient | None = None
        self._deployers_or_none: DeployerClient | None = None
        self._probe_or_none: DeployerClient | None = None  # short timeout: a lost host is liveliness' business
        self._analyzer_or_none: Analyzer | None = None
        self._planner_or_none: Planner | None = None
        self._configs: dict[str, dict[str, Any]] = {}
        self._state = LoopState()  # the schedule and the last change's facts (adaptation_policy)
        self._decisions = 0
        self._lock = threading.Lock()
        # (host, instance) of migration sources that could not be stopped (host cut off): twins to stop.
        self._leftovers: list[tuple[str, str]] = []
        self._trust = StatusTrust(TrustSettings(window_s=settings.status_window_s))
        self._refusal_logged: dict[str, float] = {}
        self._reflexes_seen: tuple[str | None, int] = (None, 0)  # (instance, its reflex count) last acted on
        self._live = LiveRates(settings=settings.live)  # the running detector's live rate per band
        self._ready_move: policy.ReadyMove | None = None  # the move for the running host's loss, planned ahead
        self._band_moves: dict[str, policy.BandMove] = {}  # band -> the move for a change into it, planned ahead

    @property
    def _knowledge(self) -> KnowledgeClient:
        return _set_up(self._knowledge_or_none)

    @property
    def _deployers(self) -> DeployerClient:
        return _set_up(self._deployers_or_none)

    @property
    def _probe(self) -> DeployerClient:
        return _set_up(self._probe_or_none)

    @property
    def _analyzer(self) -> Analyzer:
        return _set_up(self._analyzer_or_none)

    @property
    def _planner(self) -> Planner:
        return _set_up(self._planner_or_none)

    # -- lifecycle -------------------------------------------------------

    def setup(self, session: Any) -> None:
        s = self.settings
        self._stop.clear()
        self._session = session
        self._knowledge_or_none = KnowledgeClient(session, s.robot, own=True, host=s.onboard_host)  # writes as its host's
        self._deployers_or_none = DeployerClient(session, s.robot)
        # Not sent again when it reaches nobody: the running host's deployer is known long since, so no
        # responder means the host just went, and a probe resending for its whole timeout kept the loss
        # of the host waiting in the queue behind it (a failover once took 480 ms that way).
        self._probe_or_none = DeployerClient(session, s.robot, timeout=min(0.5, s.reconcile_s), resend_for=0.0)
        rows = self._wait_for_knowledge()
        self._configs = {str(r["config"]): r for r in rows}
        bands = bands_from_rows(rows)
        if not bands:
            raise KgadaptError(f"the knowledge graph has no detector configuration with a band for {s.feature}")
        self._analyzer_or_none = Analyzer(tracker=BandTracker(bands=bands, hysteresis=s.hysteresis, dwell_s=s.dwell_s))
        self._planner_or_none = Planner(ask=self._knowledge.query, feature=s.feature, preference=s.preference,
                                        onboard_host=s.onboard_host, in_place=s.in_place, live=s.live)
        stack = contextlib.ExitStack()
        self._events_pub = declared(stack, session.declare_publisher(keys.adaptation_events(s.robot)))
        declared(stack, session.declare_subscriber(keys.camera_illumination(s.robot, s.camera), self._on("illumination")))
        declared(stack, session.declare_subscriber(keys.host_status(s.robot), self._on("host_status")))
        declared(stack, session.liveliness().declare_subscriber(keys.host_alive(s.robot), self._on_alive, history=True))
        declared(stack, session.declare_subscriber(keys.flight_state(s.robot), self._on("flight_state")))
        declared(stack, session.declare_subscriber(keys.detector_markers(s.robot), self._on("detections")))
        declared(stack, session.declare_subscriber(keys.detector_reflex(s.robot), self._on("reflex")))
        declared(stack, session.declare_subscriber(keys.deployer_events(s.robot), self._on("deploy_event")))
        self._declarations = stack
        self._state = LoopState(setup_at=time.monotonic())
        self._worker = threading.Thread(target=self._run, name="adaptation", daemon=True)
        self._worker.start()
        log.info("adaptation manager up: bands %s, preference %s", [b.name for b in bands], s.preference)

    def shutdown(self) -> None:
        self._stop.set()
        self._put(("wake", None))  # the worker may be waiting on the queue
        if self._worker is not None:
            self._worker.join(timeout=30)
            self._worker = None
        current, self.current = self.current, None
        standby, self.standby = self.standby, None
        if standby is not None and standby.instance and self._deployers_or_none is not None:
            try:
                self._deployers.stop(standby.host, standby.instance)
            except KgadaptError as exc:
                log.warning("could not stop the standby %s on %s: %s", standby.instance, standby.host, exc)
        if current is not None and current.instance and self._deployers_or_none is not None:
            # We started it; a clean shutdown stops it wherever it runs.
            try:
                self._deployers.stop(current.host, current.instance)
            except KgadaptError as exc:
                log.warning("could not stop %s on %s: %s", current.instance, current.host, exc)
        self._declarations.close()  # quietly: the session may be closing
        self._events_pub = None

    def _wait_for_knowledge(self) -> list[dict[str, Any]]:
        # The client sends again while nobody answers; this waits out refusals (a store still loading).
        deadline = time.monotonic() + self.settings.knowledge_timeout
        while True:
            try:
                rows: list[dict[str, Any]] = self._knowledge.query("detector_configs", {"feature": self.settings.feature})
                return rows
            except KgadaptError as exc:
                if time.monotonic() >= deadline or self._stop.wait(0.2):
                    raise KgadaptError(f"adaptation: the knowledge service did not answer: {exc}") from exc

    # -- monitor: callbacks only queue -----------------------------------

    def _on(self, kind: str) -> Callable[[Any], None]:
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

    # -- the loop: observe, decide (policy), execute -----------------------

    def _run(self) -> None:
        self._adopt_running()
        while not self._stop.is_set():
            if self._alive:
                kind, data = "alive", self._alive.popleft()
            else:
                try:
                    kind, data = self._queue.get(timeout=self._next_wake())
                except queue.Empty:
                    kind, data = "tick", None
            try:
                trigger = self._observe(kind, data)
                if self.current is None:
                    # Nothing runs: whatever was observed, the question is where to start.
                    trigger = self._startup_trigger()
                if trigger is None:
                    trigger, self._state = policy.due_retry(self._state, mono=time.monotonic())
                if trigger is None:
                    trigger = self._check_running()
                if trigger is None and self._leftovers:
                    self._stop_leftovers()
                if trigger is not None:
                    self._act(trigger)
                else:
                    if self.settings.standby:
                        self._keep_standby()
                    self._prepare_move()
                    self._prepare_band_move()
            except Exception:  # the loop must survive any single bad observation or failed action
                log.exception("adaptation: handling %s failed", kind)

    def _next_wake(self) -> float:
        c = self.current
        return policy.next_wake(self._state, mono=time.monotonic(),
                                probing=policy.probing(c, self._analyzer.hosts), starting=c is None,
                                leftovers=bool(self._leftovers), standby=self.settings.standby,
                                startup_poll_s=self.settings.startup_poll_s)

    def _observe(self, kind: str, data: Any) -> Trigger | None:
        now = time.time()
        a = self._analyzer
        if kind == "alive":
            host, alive = data
            self._trust.alive(host, alive)
            if host == self.settings.onboard_host and not alive:
                # Our own token goes first when our agent shuts down; we go with it.
                return None
            trigger: Trigger | None = a.on_liveliness(host, alive, now, self.current)
            return trigger
        if kind in ("tick", "wake"):
            return None
        key, payload, received = data
        try:
            if kind == "illumination":
                light = messages.decode_as(payload, messages.Illumination)
                trigger = a.on_illumination(float(light.smoothed), now)
                return trigger
            if kind == "host_status":
                return self._on_host_status(keys.last_chunk(key, 2), payload, received, now)
            if kind == "flight_state":
                flight = messages.decode_as(payload, messages.FlightState)  # malformed ones: dropped and logged
                if self._final_descent is not None:
                    return None  # the bridge beside us is the one source
                self._set_landing(in_final_descent(flight))  # landed state unknown in LAND/RTL counts as descent
                return None
            if kind == "deploy_event":
                event = messages.decode_as(payload, messages.DeployEvent)
                if policy.ended(self.standby, instance=event.instance, event=event.event):
                    log.info("adaptation: the standby %s %s", event.instance, event.event)
                    if policy.crashed_standby(self.standby, instance=event.instance, event=event.event):
                        self._end_crashed_standby(self.standby)
                    self.standby = None
                if policy.ended(self.current, instance=event.instance, event=event.event):
                    self._state = dataclasses.replace(self._state, next_check=0.0)  # ask its deployer now
                return None
            if kind == "reflex":
                reflex = messages.decode_as(payload, messages.Reflex)
                if not policy.own_detection(self.current, body_instance=reflex.instance,
                                            key_instance=keys.last_chunk(key, 2)):
                    return None
                return self._on_reflex(reflex, now)
            if kind == "detections":
                detections = messages.decode_as(payload, messages.Detections)
                running = self.current
                if running is None or not policy.own_detection(running, body_instance=detections.instance,
                                                               key_instance=keys.last_chunk(key, 2)):
                    return None
                band = a.tracker.current.name if a.tracker.current else None
                found = policy.clean_markers(detections.ids, detections.clean)
                expected = policy.expected_rate(self._state, self._configs, running.config, band)
                trigger = a.on_detection(found, now, expected, running.config)
                if band is not None:
                    # The frame's own configuration: a reflex may have changed it before its message arrives.
                    pad = self.landing or (self._final_descent is not None and self._final_descent())
                    self._live.add(config=str(detections.config), band=band, found=found, now=now, pad_in_view=pad,
                                   run_id=running.run_id, host=running.host)
                    self._write_live(now)
                return trigger
        except MessageError as exc:
            log.info("adaptation: dropped a %s message on %s: %s", kind, key, exc)
        return None

    def _write_live(self, now: float) -> None:
        """The live windows changed since the last write, every ``live.write_every_s`` (onboard/adaptation/live_rate.py)."""
        for params in self._live.due(now):
            try:
                self._knowledge.write("live_rate", params)
            except KgadaptError as exc:  # the next window's write has the figures again
                log.warning("adaptation: could not record the live rate of %s in %s: %s", params["config"],
                            params["band"], exc)

    def _reflex_count(self, instance: str | None) -> int:
        seen_instance, count = self._reflexes_seen
        return count if seen_instance == instance else 0

    def _on_reflex(self, m: messages.Reflex, now: float) -> Trigger | None:
        """The running detector switched on its own: follow it (see the module's docstring)."""
        running = self.current
        assert running is not None  # own_detection: it is our running detector's
        count = int(m.count)
        if count <= self._reflex_count(running.instance):
            return None  # already followed (the message is put again once a second, with the same count)
        self._reflexes_seen = (running.instance, count)
        config = m.config
        detail = {**policy.reflex_trigger_detail(m), "answered_ms": round((float(m.time) - float(m.frame_time))
                                                                         * 1000.0, 1)}
        if config is not None and config != running.config:
            row = self._configs.get(str(config), {})
            deployment = m.deployment or row.get("deployment") or running.deployment
            self.current = dataclasses.replace(running, config=str(config), deployment=str(deployment),
                                               demand_mb=float(row.get("memory_demand_mb") or running.demand_mb))
            band = m.band
            self._state = policy.after_reflex(
                self._state, config=str(config), band=band,
                rate=policy.expected_rate(LoopState(), self._configs, str(config), band), wall=now,
                settle_s=self.settings.settle_s)
        now_band = m.band or (self._analyzer.tracker.current.name if self._analyzer.tracker.current else None)
        return self._analyzer.on_reflex(str(now_band), now, detail, hold_s=self.settings.reflex_hold_s)

    def _on_host_status(self, host: str, payload: bytes, received: float, now: float) -> Trigger | None:
        # Refused: what the knowledge service refuses, a host without a liveliness token,
        # a stale status, free memory its running detector's profile shows as used.
        a = self._analyzer
        held = self.current.held_mb if self.current is not None and self.current.host == host else 0.0
        m = check_status(host, messages.decode_as(payload, messages.HostStatus))  # malformed: dropped by the caller
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
        free = float(roomiest)
        if self.current is not None and self.current.host == host:
            self._refresh_held(now)
        settled = received >= self._state.settled_after
        short = policy.to_measure(host, free, running=self.current, standby=self.standby, settled=settled)
        if short is not None and short is self.current:
            self._refresh_held(now, force=True)  # before calling it unfit, make sure "held" is a measurement
        elif short is not None and short is self.standby:
            self._refresh_standby_held()
        trigger = policy.host_status_trigger(a, host, free_mb=free, cpu_load=float(m.cpu_load), wall=now,
                                             running=self.current, standby=self.standby, state=self._state,
                                             received=received)
        view.memory_free_mb = self._trust.confirmed_free(host, received)
        return trigger

    def _set_landing(self, landing: bool) -> None:
        if not landing:
            self._deferred.clear()  # the next descent records its deferrals again
        self.landing = landing

    def _check_running(self) -> Trigger | None:
        """A ``detector_gone`` trigger when the deployer says our detector no longer runs."""
        current = self.current
        if (current is None or current.instance is None
                or not policy.probe_due(self._state, current, self._analyzer.hosts, mono=time.monotonic())):
            return None
        try:
            state = str(self._probe.status(current.host, current.instance).state)
        except DeploymentError as exc:  # the deployer does not know it (any more)
            state = f"unknown to its deployer ({exc})"
        except KgadaptError as exc:  # no answer: the host's liveliness decides
            log.debug("adaptation: no status for %s: %s", current.instance, exc)
            return None
        finally:
            # Counted from the answer (or the timeout): unanswered probes back to back would leave
            # the loop no time for the observations waiting in the queue.
            self._state = dataclasses.replace(self._state, next_check=time.monotonic() + self.settings.reconcile_s)
        trigger = policy.gone_trigger(current, state, wall=time.time())
        if trigger is not None:
            log.warning("adaptation: detector %s on %s is %s; replacing it", current.instance, current.host, state)
        return trigger

    def _stop_leftovers(self) -> None:
        """Stop the sources of migrations that could not be stopped, once their deployers answer."""
        mono = time.monotonic()
        if mono < self._state.next_leftover_check:
            return
        self._state = dataclasses.replace(self._state, next_leftover_check=mono + self.settings.reconcile_s)
        for host, instance in list(self._leftovers):
            view = self._analyzer.hosts.get(host)
            if view is not None and not view.online:
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

    def _stop_twins(self, host: str = "*", *, running_only: bool = True) -> list[str]:
        """Stop every live detector of ours on ``host`` ("*": any) but the current one and the standby.

        ``running_only``: nothing is stopped while no detector runs.
        """
        if running_only and self.current is None:
            return []
        try:
            processes = self._deployers.processes(host)
        except KgadaptError:
            return []
        stopped = []
        for p in policy.twins(processes, self._configs, running=self.current, standby=self.standby):
            try:
                self._deployers.stop(str(p.host) if host == "*" else host, str(p.instance))
                stopped.append(str(p.instance))
            except KgadaptError as exc:
                log.warning("adaptation: could not stop twin %s on %s: %s", p.instance, p.host, exc)
        return stopped

    def reconcile(self, host: str) -> list[str]:
        """Stop detectors on ``host`` that are not the current one (after a partition heals)."""
        return self._stop_twins(host, running_only=False)

    def _startup_trigger(self) -> Trigger | None:
        wall = time.time()
        within_grace = time.monotonic() - self._state.setup_at <= self.settings.startup_grace_s
        return policy.startup_trigger(self._analyzer, own_host=self.settings.onboard_host, within_grace=within_grace,
                                      platforms=self._platforms,
                                      confirmed=lambda h: self._trust.confirmed_free(h, wall) is not None, wall=wall)

    def _platforms(self) -> list[dict[str, Any]]:
        try:
            rows: list[dict[str, Any]] = self._knowledge.query("platforms", {})
            return rows
        except KgadaptError:
            return []

    def _log_refusal(self, host: str, exc: Exception) -> None:
        now = time.monotonic()
        if policy.refusal_log_due(self._refusal_logged.get(host), now):
            self._refusal_logged[host] = now
            log.warning("adaptation: refused %s (%d refused so far)", exc, self._trust.refused)

    def _graph_shows_online(self, host: str, timeout: float) -> bool:
        """Wait (bounded) until the graph shows ``host`` online with a free-memory figure.

        We and the knowledge service see a liveliness token at the same moment;
        planning before the service has written it would leave the host out.
        No event says when it has: the graph is asked again every 50 ms.
        """
        deadline = time.monotonic() + timeout
        while not policy.shows_online(self._platforms(), host):
            if time.monotonic() >= deadline or self._stop.wait(0.05):
                return False
        return True

    def _profile_rss(self, run_id: str | None) -> float | None:
        """The most the process of run ``run_id`` held (its profile's rss_mb_max), None when not known yet.

        The maximum, not the last sample: the first sample is taken right after
        exec (a few MiB) and would make the detector look as if it held nothing.
        """
        if not run_id:
            return None
        try:
            rows = self._knowledge.query("process_profile", {"run_id": run_id})
        except KgadaptError as exc:
            log.debug("adaptation: no profile figures yet: %s", exc)
            return None
        return float(rows[0]["rss_mb_max"]) if rows and rows[0].get("rss_mb_max") is not None else None

    def _refresh_held(self, now: float, *, force: bool = False) -> None:
        if self.current is None:
            return
        state = policy.held_refresh(self._state, wall=now, every_s=self.settings.rss_refresh_s, force=force)
        if state is None:
            return
        self._state = state
        current = self.current
        rss = self._profile_rss(current.run_id)
        if rss is not None and self.current is current:
            self.current = dataclasses.replace(current, held_mb=rss)

    def _act(self, trigger: Trigger) -> None:
        a = self._analyzer
        if a.tracker.current is None:
            return
        band = a.tracker.current
        if trigger.kind == TriggerKind.HOST_BACK:
            host = str(trigger.detail.get("host"))
            self._graph_shows_online(host, self.settings.graph_catch_up_s)
            # A host back from a partition may still run the detector we replaced: no twins.
            twins = self.reconcile(host)
            if twins:
                self._record(Outcome(trigger=trigger, outcome=f"stopped twin(s) {', '.join(twins)}"))
        waiting = policy.confirm_host_back(
            self._state, trigger, mono=time.monotonic(), window_s=self.settings.status_window_s,
            host_confirmed=self._trust.confirmed_free(str(trigger.detail.get("host")), time.time()) is not None)
        if waiting is not None:
            self._state = waiting
        if self._final_descent is not None:
            self._set_landing(self._final_descent())
        if policy.band_moved(trigger):  # the standby stopped for memory may come back in a new band
            self._state = dataclasses.replace(self._state, standby_paused=False)
        lost = policy.lost_hosts(a.hosts)
        # Configurations whose detections collapsed in this band stay out until the band changes.
        exclude = tuple(sorted(a.collapsed))
        # A change of band: the move planned ahead for it, if what it rests on still holds.
        ahead = policy.band_move(
            self._band_moves.pop(band.name, None), trigger, mono=time.monotonic(), max_age_s=self.settings.ready_move_s,
            basis=policy.move_basis(band=band.name, running=self.current, standby=self.standby, lost=lost,
                                    exclude=exclude))
        ahead_plan = None
        if ahead is not None and ahead.plan is not None:
            ahead_plan = dataclasses.replace(ahead.plan, inputs={**ahead.plan.inputs, "planned_ahead_ms": round(
                (time.monotonic() - ahead.at) * 1000.0)})
        reflex_plan = None
        if trigger.kind == TriggerKind.REFLEX:
            done, reflex_plan = self._record_reflex(trigger, band.name, ahead_plan)
            if done:
                return
        action = policy.triage(trigger, running=self.current, standby=self.standby, lost=lost, landing=self.landing,
                               deferred=self._deferred, waiting=waiting is not None)
        if action == Action.WAIT:
            return
        if action == Action.STOP_STANDBY:
            self._stop_standby_first(trigger)
            return
        if action == Action.DEFER:
            self._deferred.add(trigger.kind)
            self._record(Outcome(trigger=trigger, outcome="deferred: final descent"))
            return
        if action == Action.DEFER_AGAIN:
            log.info("adaptation: %s deferred again (final descent)", trigger.describe())
            return
        running_lost = policy.running_lost(self.current, trigger, lost)
        started = time.perf_counter()
        # The running host lost: the move planned ahead for it, if what it rests on still holds.
        ready = policy.ready_move(
            self._ready_move, trigger, running=self.current, mono=time.monotonic(),
            max_age_s=self.settings.ready_move_s,
            basis=policy.move_basis(band=band.name, running=self.current, standby=self.standby,
                                    lost=[h for h in lost if h != trigger.detail.get("host")], exclude=exclude))
        self._ready_move = None  # used or not, what it rests on is changing now
        how: policy.Execute | None = None  # decided ahead with its plan, or below
        if ready is not None:
            plan, how = ready.plan, ready.how
            plan = dataclasses.replace(plan, inputs={**plan.inputs, "planned_ahead_ms": round(
                (time.monotonic() - ready.at) * 1000.0)})
        elif ahead_plan is not None and ahead is not None and ahead.how is not None:
            plan, how = ahead_plan, ahead.how
        elif reflex_plan is not None and not running_lost:
            plan = reflex_plan  # the reflex's record planned what this would plan now
        else:
            try:
                here = self.current.host if self.current is not None else None
                wall = time.time()
                live = policy.live_free(a.hosts, here=here, roomiest=lambda h: self._trust.roomiest(h, wall),
                                        confirmed=lambda h: self._trust.confirmed_free(h, wall))
                plan = self._planner.plan(band=band.name, running=None if running_lost else self.current,
                                          exclude=exclude, lost_hosts=lost, live_free=live)
            except (PlanningError, KgadaptError) as exc:
                self._record(Outcome(trigger=trigger, outcome=f"no plan: {exc}"))
                if running_lost:
                    self._retry_later(trigger)
                return
        result: Outcome | None
        try:
            if how is None:
                how = policy.execution(plan, trigger, running=self.current, standby=self.standby, lost=lost,
                                       change=self._planner.change)
            if how.how == Execution.NOTHING:
                return
            if how.how == Execution.KEEP:
                self._record(Outcome(trigger=trigger, plan=plan, outcome="kept"))
                return
            if how.how == Execution.STANDBY:
                result = self._activate_standby(plan, trigger, reconfigure_to=how.reconfigure_to, why=how.why,
                                                old=None if running_lost else self.current)
            elif how.how == Execution.START:
                result = self._start_fresh(plan, trigger)
            else:
                why = how.why
                result = None
                if how.how == Execution.RECONFIGURE:
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
        if trigger.kind == TriggerKind.DETECTOR_GONE and not policy.failed(result.outcome):
            twins = self._stop_twins()  # e.g. what an outside migrate started elsewhere
            if twins:
                result.detail["stopped_twins"] = twins
        self._record(result)
        if running_lost and not policy.failed(result.outcome):
            a.reset_rate()
        elif running_lost:
            self._retry_later(trigger)

    def _prepare_move(self) -> None:
        """Plan ahead the move for the loss of the running detector's host (see ``ready_move_s``): at the
        loss, the switch (or start) follows without a question to the graph."""
        a, current, s = self._analyzer, self.current, self.settings
        if (s.ready_move_s <= 0 or current is None or not current.instance or a.tracker.current is None
                or current.host == s.onboard_host):  # losing our own host, we are gone with it
            return
        band = a.tracker.current.name
        lost = policy.lost_hosts(a.hosts)
        if current.host in lost:
            return
        exclude = tuple(sorted(a.collapsed))
        basis = policy.move_basis(band=band, running=current, standby=self.standby, lost=lost, exclude=exclude)
        mono = time.monotonic()
        if not policy.needs_move(self._ready_move, host=current.host, basis=basis, mono=mono, every_s=s.ready_move_s):
            return
        wall = time.time()
        gone = (*lost, current.host)
        try:
            live = policy.live_free(a.hosts, here=None, roomiest=lambda h: self._trust.roomiest(h, wall),
                                    confirmed=lambda h: self._trust.confirmed_free(h, wall))
            live.pop(current.host, None)
            plan = self._planner.plan(band=band, running=None, exclude=exclude, lost_hosts=gone, live_free=live)
            loss = Trigger(TriggerKind.HOST_LOST, wall, {"host": current.host})
            how = policy.execution(plan, loss, running=current, standby=self.standby, lost=gone,
                                   change=self._planner.change)
        except (PlanningError, KgadaptError) as exc:
            log.debug("adaptation: no move ready for the loss of %s: %s", current.host, exc)
            self._ready_move = None
            return
        self._ready_move = policy.ReadyMove(host=current.host, basis=basis, plan=plan, how=how, at=mono)

    def _prepare_band_move(self) -> None:
        """Plan ahead the move for a change into each other band, one band per quiet moment, again when what
        it rests on changes or after ``ready_move_s``: at the detector's reflex (or the manager's own band
        change) the change follows without a question to the graph (the decision's inputs say
        ``planned_ahead_ms``)."""
        a, current, s = self._analyzer, self.current, self.settings
        if s.ready_move_s <= 0 or current is None or not current.instance or a.tracker.current is None:
            self._band_moves.clear()
            return
        here = a.tracker.current.name
        others = [b.name for b in a.tracker.bands if b.name != here]
        self._band_moves.pop(here, None)
        lost = policy.lost_hosts(a.hosts)
        standby = self.standby

        def basis(band: str) -> tuple[Any, ...]:
            # A band change clears the configurations left out: none is left out of another band's move.
            return policy.move_basis(band=band, running=current, standby=standby, lost=lost, exclude=())

        mono = time.monotonic()
        band = policy.band_move_due(self._band_moves, bands=others, basis=basis, mono=mono, every_s=s.ready_move_s)
        if band is None:
            return
        wall = time.time()
        move = policy.BandMove(band=band, basis=basis(band), at=mono)
        try:
            live = policy.live_free(a.hosts, here=current.host, roomiest=lambda h: self._trust.roomiest(h, wall),
                                    confirmed=lambda h: self._trust.confirmed_free(h, wall))
            plan = self._planner.plan(band=band, running=current, exclude=(), lost_hosts=lost, live_free=live)
            how = policy.execution(plan, Trigger(TriggerKind.BAND_CHANGED, wall, {"band": band}), running=current,
                                   standby=standby, lost=lost, change=self._planner.change)
            move = dataclasses.replace(move, plan=plan, how=how)
        except (PlanningError, KgadaptError) as exc:
            log.debug("adaptation: no move ready for band %s: %s", band, exc)
        self._band_moves[band] = move

    def _record_reflex(self, trigger: Trigger, band: str, ahead: Plan | None) -> tuple[bool, Plan | None]:
        """Record what the detector did on its own; (True, ...) when nothing is left to plan (the plan for the
        band is what runs now, or final descent: placement is not reconsidered then), with the plan for the
        band: ``ahead`` (planned before the reflex came) or asked now."""
        d, running = trigger.detail, self.current
        assert running is not None  # a reflex comes from the running detector
        took = d.get("config")
        plan: Plan | None = ahead
        try:
            plan = plan or self._planner.plan(band=band, running=running, exclude=tuple(sorted(self._analyzer.collapsed)),
                                      lost_hosts=policy.lost_hosts(self._analyzer.hosts),
                                      live_free=policy.live_free(self._analyzer.hosts, here=running.host,
                                                                 roomiest=lambda h: self._trust.roomiest(h, time.time()),
                                                                 confirmed=lambda h: self._trust.confirmed_free(h, time.time())))
        except (PlanningError, KgadaptError) as exc:
            log.info("adaptation: no plan after the reflex: %s", exc)
        planned = plan is not None and plan.same_as(running)
        # A try on the frames' own evidence stands until its trial or the band ends it (the plan for the
        # band is what collapsed); the manager records it and keeps placement and memory in its charge.
        stands = not planned and policy.reflex_stands(d)
        kept = planned or stands
        # What the detector took, as the decision's choice; the manager's own plan, where it agrees, with it.
        shown = plan if planned else Plan(target=running, reason=f"the detector's reflex took {running.config} in place "
                                       f"on {running.host}", inputs={"band": band}, queries=("reflex_table",))
        if took is not None:
            outcome = "reconfigured by reflex" + (
                "" if planned or plan is None else
                f"; {'kept on its evidence (collapse); ' if stands else ''}the plan for band {band} "
                f"is {plan.target.config}@{plan.target.host}")
            self._record(Outcome(trigger=trigger, plan=shown, outcome=outcome, latency_ms=d.get("answered_ms"),
                                 frames_lost=0,
                                 detail={"change": Change.REFLEX, "instance": running.instance,
                                         "previous_instance": running.instance,
                                         "from": f"{d.get('previous')}@{running.host}"}))
        elif kept:  # the light came back to the band of what runs: nothing happened, nothing to record
            log.info("adaptation: %s: %s runs already", trigger.describe(), running.config)
        if self.landing:
            if not kept and trigger.kind not in self._deferred:  # one per descent, as for any kind of change
                self._deferred.add(trigger.kind)
                self._record(Outcome(trigger=trigger, outcome="deferred: final descent"))
            elif not kept:
                log.info("adaptation: %s deferred again (final descent)", trigger.describe())
            return True, plan
        return kept or plan is None, plan

    def _retry_later(self, trigger: Trigger) -> None:
        """The detector is gone and none replaced it: act on ``trigger`` again after ``retry_s``.

        Without this, a failover that fails once (the knowledge service restarting
        its store, a deployer not answering) would leave the robot without a
        detector until some other trigger came.
        """
        self._state = policy.retry_later(self._state, trigger, mono=time.monotonic(), retry_s=self.settings.retry_s)

    def _start_fresh(self, plan: Plan, trigger: Trigger) -> Outcome:
        t = plan.target
        instance = new_instance_name(t.config, t.host)
        first = FirstOutput()
        with contextlib.ExitStack() as stack:
            declared(stack, self._session.declare_subscriber(keys.detector_markers(self.settings.robot, instance), first))
            snapshot = self._deployers.start(t.host, t.deployment, t.config, instance=instance, wait_ready=True,
                                             ready_timeout=self.settings.ready_timeout)
            got = first.event.wait(self.settings.output_timeout)
        self._set_current(plan, instance, snapshot.run_id)
        latency = (first.wall - trigger.time) * 1000.0 if got and first.wall else None
        return Outcome(trigger=trigger, plan=plan, outcome="started" if got else "started, no detections yet",
                       latency_ms=latency, detail={"instance": instance, "pid": snapshot.pid})

    def _reconfigure(self, plan: Plan, trigger: Trigger) -> Outcome:
        t, old = plan.target, self.current
        assert old is not None and old.instance is not None  # Execution.RECONFIGURE: a detector runs
        first = FirstOutput(config=t.config)
        report = None
        with contextlib.ExitStack() as stack:
            declared(stack, self._session.declare_subscriber(keys.detector_markers(self.settings.robot, old.instance),
                                                             first))
            try:
                report = reconfigure(self._session, self.settings.robot, old.host, old.instance, t.config,
                                     timeout=self.settings.output_timeout)
            except KgadaptError:
                # Unanswered is not refused: if its deployer's record names the new configuration,
                # the detector took it (a migration now would find nothing to change).
                if self._deployers.status(old.host, old.instance).config != t.config:
                    raise
            got = first.event.wait(self.settings.output_timeout)
        self._set_current(plan, old.instance, old.run_id)
        latency = (first.wall - trigger.time) * 1000.0 if got and first.wall else None
        return Outcome(trigger=trigger, plan=plan, outcome="reconfigured", latency_ms=latency, frames_lost=0,
                       detail={"instance": old.instance, "previous_instance": old.instance,
                               "from": f"{old.config}@{old.host}",
                               **({} if report is None else {
                                   "first_seq": report.first_seq, "check_ms": report.check_ms,
                                   "build_ms": report.build_ms, "reply_ms": round(report.reply_ms, 1)})})

    def _switch(self, plan: Plan, trigger: Trigger) -> Outcome:
        t, old = plan.target, self.current
        assert old is not None and old.instance is not None  # Execution.MIGRATE: a detector runs
        called_at = time.time()
        left_running = ""
        try:
            report = migrate(self._session, self.settings.robot, old.instance, t.host, source_host=old.host,
                             deployment=t.deployment, config=t.config, client=self._deployers,
                             ready_timeout=self.settings.ready_timeout, output_timeout=self.settings.output_timeout)
        except SourceNotStopped as exc:
            # The new detector runs and detects: it is ours now. The old one is a twin, stopped
            # as soon as its deployer answers (or by host_back's reconcile).
            if not isinstance(exc.report, MigrationReport):
                raise  # never: migrate() raises it with its report
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

    def _activate_standby(self, plan: Plan, trigger: Trigger, *, reconfigure_to: str | None, why: str,
                          old: Placement | None) -> Outcome:
        """Make the standby the running detector; idle ``old`` (it becomes the standby) or stop it."""
        sb = self.standby
        assert sb is not None and sb.instance is not None  # Execution.STANDBY: there is one
        s = self.settings
        config = reconfigure_to or sb.config
        first = FirstOutput(config=config)
        with contextlib.ExitStack() as stack:
            declared(stack, self._session.declare_subscriber(keys.detector_markers(s.robot, sb.instance), first))
            try:
                set_active(self._session, s.robot, sb.host, sb.instance, True, timeout=s.output_timeout)
                if reconfigure_to is not None:
                    reconfigure(self._session, s.robot, sb.host, sb.instance, reconfigure_to,
                                timeout=s.output_timeout)
            except KgadaptError:
                # Dead without an exit event, or refusing: forget it, so that the retry of a failover
                # starts a process instead of asking the same standby again.
                self.standby = None
                self._end_standby_quietly(sb)
                raise
            got = first.event.wait(s.output_timeout)
        self.standby = None
        target = dataclasses.replace(plan.target, config=config, host=sb.host, deployment=sb.deployment,
                                     demand_mb=plan.target.demand_mb if config == plan.target.config else sb.demand_mb)
        plan = dataclasses.replace(plan, target=target)
        self._set_current(plan, sb.instance, sb.run_id)
        detail: dict[str, Any] = {"instance": sb.instance, "change": Change.STANDBY, "change_why": why,
                                  "standby": {"config": sb.config, "host": sb.host, "instance": sb.instance}}
        if old is not None and old.instance:
            detail["previous_instance"] = old.instance
            detail["from"] = f"{old.config}@{old.host}"
            try:
                set_active(self._session, s.robot, old.host, old.instance, False, timeout=s.output_timeout)
                self.standby = old
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

    def _end_standby_quietly(self, standby: Placement) -> None:
        try:
            if self._deployers_or_none is not None and standby.instance:
                self._deployers.stop(standby.host, standby.instance)
        except KgadaptError as exc:
            assert standby.instance is not None
            self._leftovers.append((standby.host, standby.instance))  # stopped once its deployer answers
            log.info("adaptation: could not stop the unanswering standby %s: %s", standby.instance, exc)

    def _end_crashed_standby(self, standby: Placement | None) -> None:
        if standby is None or not standby.instance or self._deployers_or_none is None:
            return
        try:
            self._deployers.stop(standby.host, standby.instance)
            log.warning("adaptation: the standby %s on %s exited; stopped rather than restarted active",
                        standby.instance, standby.host)
        except KgadaptError as exc:  # its host gone with it: nothing left to restart it
            log.warning("could not stop the crashed standby %s on %s: %s", standby.instance, standby.host, exc)

    def _stop_standby_first(self, trigger: Trigger) -> None:
        """Memory short with a standby: stop it, and plan nothing else on this trigger; if the host is
        still short once the statuses show its memory back, the next one moves."""
        sb = self.standby
        assert sb is not None  # Action.STOP_STANDBY: there is one
        stopped = self._stop_standby()
        self._state = dataclasses.replace(self._state, standby_paused=True,
                                          settled_after=time.time() + self.settings.settle_s)
        self._record(Outcome(trigger=trigger, outcome=f"stopped the standby {sb.instance} ({sb.config}@{sb.host}) "
                             "first" + ("" if stopped else " (its deployer did not answer)"),
                             detail={"change": Change.STANDBY_STOPPED, "instance": sb.instance,
                                     "standby": {"config": sb.config, "host": sb.host, "instance": sb.instance,
                                                 "run_id": sb.run_id}}))

    def _stop_standby(self) -> bool:
        sb, self.standby = self.standby, None
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
        sb = self.standby
        if sb is None:
            return
        rss = self._profile_rss(sb.run_id)
        if rss is not None and self.standby is sb:
            self.standby = dataclasses.replace(sb, held_mb=rss)

    def _first_for(self, band: str) -> str | None:
        try:
            _full, left = self._planner.candidates(band)
        except (PlanningError, KgadaptError):
            return None
        first = left[0].get("config")
        return None if first is None else str(first)

    def _keep_standby(self) -> None:
        """Start, keep or replace the warm standby as the graph allows (see the module's docstring)."""
        mono = time.monotonic()
        if mono < self._state.next_standby_check:
            return
        self._state = dataclasses.replace(self._state, next_standby_check=mono + self.settings.standby_check_s)
        a, current, sb = self._analyzer, self.current, self.standby
        band = a.tracker.neighbour(a.level)
        step = policy.standby_step(running=current, standby=sb, landing=self.landing,
                                   paused=self._state.standby_paused, retrying=self._state.retry is not None,
                                   band=None if band is None else band.name, hosts=a.hosts, first_for=self._first_for)
        if step == StandbyStep.DROP and sb is not None:
            # Gone with its host; should it come back from a partition, host_back's reconcile stops it.
            log.info("adaptation: the standby %s went with %s", sb.instance, sb.host)
            self.standby = None
        elif step == StandbyStep.STOP and sb is not None and band is not None:
            log.info("adaptation: the standby %s (%s) is not band %s's any more", sb.instance, sb.config, band.name)
            self._stop_standby()  # its memory shows free in a later status; start the new one then
        elif step == StandbyStep.START and current is not None and band is not None:
            self._start_standby(band.name, current)

    def _start_standby(self, band: str, current: Placement) -> None:
        a = self._analyzer
        wall = time.time()
        lost = policy.lost_hosts(a.hosts)
        live = policy.live_free(a.hosts, here=None, roomiest=lambda h: None,
                                confirmed=lambda h: self._trust.confirmed_free(h, wall))
        try:
            plan = self._planner.standby(band=band, running=current, lost_hosts=lost, live_free=live)
        except KgadaptError as exc:
            log.debug("adaptation: no standby plan: %s", exc)
            return
        if plan is None:
            return
        t = plan.target
        instance = new_instance_name(t.config, t.host)
        trigger = Trigger(TriggerKind.STANDBY, wall, {"band": band})
        try:
            snapshot = self._deployers.start(t.host, t.deployment, t.config, instance=instance, wait_ready=True,
                                             ready_timeout=self.settings.ready_timeout, idle=True)
        except KgadaptError as exc:
            self._record(Outcome(trigger=trigger, plan=plan, outcome=f"failed: {exc}",
                                 detail={"change": Change.STANDBY_START}))
            return
        try:
            # It started idle; asking confirms that its activity switch answers (its declaration may
            # still be on its way: set_active asks again until then). A standby that does not answer
            # is stopped, and the decision says so: it is no standby the failover could count on.
            set_active(self._session, self.settings.robot, t.host, instance, False, timeout=self.settings.output_timeout)
        except KgadaptError as exc:
            try:
                self._deployers.stop(t.host, instance)
            except KgadaptError as err:
                log.warning("adaptation: could not stop %s: %s", instance, err)
            self._record(Outcome(trigger=trigger, plan=plan, outcome=f"failed: not made idle: {exc}",
                                 detail={"change": Change.STANDBY_START}))
            return
        self.standby = dataclasses.replace(t, instance=instance, run_id=snapshot.run_id)
        self._record(Outcome(trigger=trigger, plan=plan, outcome="standby started (idle)",
                             detail={"change": Change.STANDBY_START, "instance": instance, "pid": snapshot.pid,
                                     "standby": {"config": t.config, "host": t.host, "instance": instance,
                                                 "run_id": snapshot.run_id}}))

    # -- execute: the running detector -----------------------------------------

    def _set_current(self, plan: Plan, instance: str, run_id: str | None) -> None:
        t = plan.target
        self.current = Placement(config=t.config, deployment=t.deployment, host=t.host, instance=instance,
                                 demand_mb=t.demand_mb, held_mb=0.0, run_id=run_id)
        self._state = policy.after_change(self._state, plan, wall=time.time(), settle_s=self.settings.settle_s)
        self._analyzer.reset_rate()

    def _adopt_running(self) -> None:
        """After a restart: adopt one live detector of ours, stop any twin."""
        try:
            processes = self._deployers.processes("*")
        except KgadaptError as exc:
            log.info("adaptation: no deployer answered at start (%s); nothing to adopt", exc)
            return
        keep, twins = policy.adoption(processes, self._configs, onboard_host=self.settings.onboard_host)
        if keep is None:
            return
        assert keep.config is not None and keep.instance is not None  # ours(): a live one of our configurations
        row = self._configs[keep.config]
        self.current = Placement(config=keep.config, deployment=str(keep.deployment), host=str(keep.host),
                                 instance=keep.instance, demand_mb=float(row.get("memory_demand_mb") or 0),
                                 run_id=keep.run_id)
        log.info("adaptation: adopted %s on %s", keep.instance, keep.host)
        if self.settings.standby:  # it may have been our standby, idle
            try:
                set_active(self._session, self.settings.robot, str(keep.host), keep.instance, True)
            except KgadaptError as exc:
                log.warning("adaptation: could not make the adopted %s active: %s", keep.instance, exc)
        for twin in twins:
            try:
                self._deployers.stop(str(twin.host), str(twin.instance))
                log.info("adaptation: stopped twin %s on %s", twin.instance, twin.host)
            except KgadaptError as exc:
                log.warning("adaptation: could not stop twin %s: %s", twin.instance, exc)

    # -- knowledge -------------------------------------------------------

    def _record(self, outcome: Outcome) -> None:
        self._decisions += 1
        params, event = policy.decision_record(outcome, robot=self.settings.robot, wall=time.time(),
                                               seq=self._decisions,
                                               instance=self.current.instance if self.current else None)
        name = params["name"]
        try:
            self._knowledge.write("decision", params)
        except KgadaptError as exc:
            log.warning("adaptation: could not record decision %s: %s", name, exc)
        with self._lock:
            self.history.append(outcome)
        try:
            self._events_pub.put(messages.encode(event))
        except Exception as exc:  # noqa: BLE001 - publishing is best effort; the graph has the record
            log.debug("adaptation event not published: %s", exc)
        log.info("decision %s: %s -> %s@%s (%s, %s ms)", name, outcome.trigger.describe(), params["config"],
                 params["host"], outcome.outcome, params["duration_ms"])
