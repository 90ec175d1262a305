"""The adaptation manager's decisions, as pure functions over plain values.

The manager (``onboard/adaptation/adaptation_manager.py``) observes (Zenoh), asks (the
knowledge service, the deployers) and executes. What it decides lives here:
when a check is due, whose held memory to measure before calling a host
short, what a trigger leads to (stop the standby, defer, plan), how a plan is
carried out (keep, switch to the standby, start, reconfigure, migrate), what
the warm standby needs, which processes are twins, and what a decision
record says. Nothing here does I/O or reads a clock: times are arguments
(``wall``: ``time.time()``, the clock of received statuses and triggers;
``mono``: ``time.monotonic()``, the clock of the manager's own schedule), and
where a rule needs the graph it takes a function that answers (as the
:class:`~kgadapt.onboard.adaptation.adaptation.Planner` does).

The manager's timers and the facts of the running detector's last change are
one :class:`LoopState`; each function that changes it returns a new one.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Callable, Iterable, Mapping, Sequence

from kgadapt.onboard.adaptation.adaptation import FEATURE, Analyzer, HostView, Placement, Plan, Trigger, memory_short
from kgadapt.onboard.adaptation.live_rate import LiveSettings
from kgadapt.onboard.adaptation.planning_defaults import DEFAULT_PREFERENCE, IN_PLACE, ONBOARD_HOST
from kgadapt.shared import messages
from kgadapt.shared.states import ENDED_EVENTS, KEPT_STATES, Change, ProcessEventKind, ReflexEvidence, TriggerKind

UNMEASURED_MB = 5.0  # a detector's profile below this has only its exec-time sample
MEASURE_WITHIN_S = 10.0  # how long after a change an unmeasured detector is given the benefit of the doubt
REFUSAL_LOG_EVERY_S = 5.0  # a flood of refused statuses logs once per host this often
IDLE_WAKE_S = 1.0  # nothing of its own due: the loop still wakes this often

Rows = list[dict[str, Any]]

# Trigger kinds and changes newer than the adaptation_event contract that outside receivers were written
# for (docs/CONTRACTS.md): the event leaves them out of ``trigger_kind`` and ``change``; its ``trigger``
# text starts with the kind, and the graph's decision records both.
NEWER_TRIGGERS = frozenset({TriggerKind.REFLEX})
NEWER_CHANGES = frozenset({Change.REFLEX})


@dataclass(frozen=True, kw_only=True)
class AdaptationSettings:
    """How the manager decides. ``preference``: see :mod:`kgadapt.onboard.adaptation.adaptation`."""

    robot: str
    camera: str = "cam0"
    feature: str = FEATURE
    preference: str = DEFAULT_PREFERENCE
    onboard_host: str = ONBOARD_HOST
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
    in_place: bool = IN_PLACE  # reconfigure in place where the graph allows it (False: always migrate)
    status_window_s: float = 1.5  # a host's free memory counts when its statuses of this window (>= 2) agree
    standby: bool = False  # keep the neighbouring band's configuration started but idle where a host has room
    standby_check_s: float = 1.0  # how often the standby is checked against the graph
    # The next move for the loss of the running detector's host is planned ahead and planned again when
    # what it rests on changes, or after this long (the graph's memory figures move); 0: plan at the loss.
    ready_move_s: float = 2.0
    startup_poll_s: float = 0.2  # nothing runs yet: how often the first placement is reconsidered without news
    reflex_hold_s: float = 2.0  # after a detector's reflex, how long the smoothed light is given to agree
    history_size: int = 1000  # decisions kept in memory (``AdaptationManager.history``); the graph has them all
    live: LiveSettings = field(default_factory=LiveSettings)  # live evidence: gathered, written, weighed

    def __post_init__(self) -> None:
        if self.history_size < 1:
            raise ValueError(f"history_size {self.history_size!r}: keep at least one decision")


@dataclass(frozen=True, kw_only=True)
class LoopState:
    """The manager's schedule and what it knows of the running detector's last change."""

    setup_at: float = 0.0  # mono: the manager started (the startup grace runs from here)
    changed_at: float = 0.0  # wall: the running detector last changed
    settled_after: float = 0.0  # wall: host statuses received before this were measured mid-change
    held_checked: float = 0.0  # wall: the running detector's held memory was last asked for
    next_check: float = 0.0  # mono: ask the running detector's deployer at or after this
    next_leftover_check: float = 0.0  # mono: try to stop left-over migration sources at or after this
    next_standby_check: float = 0.0  # mono: check the warm standby against the graph at or after this
    retry: Trigger | None = None  # a trigger to act on again (a detector not replaced; a host_back to confirm)
    retry_at: float = 0.0  # mono
    standby_paused: bool = False  # the standby was stopped for memory: none again until the band changes
    expected: tuple[str, str | None, float | None] | None = None  # (config, band, rate) from the last plan


# -- the schedule --------------------------------------------------------------


def after_change(state: LoopState, plan: Plan, *, wall: float, settle_s: float) -> LoopState:
    """The running detector changed to ``plan``'s target: statuses settle, held memory is asked afresh."""
    rate = plan.inputs.get("expected_rate")
    return dataclasses.replace(state, changed_at=wall, settled_after=wall + settle_s, held_checked=0.0,
                               expected=(plan.target.config, plan.inputs.get("band"),
                                         float(rate) if rate is not None else None))


def after_reflex(state: LoopState, *, config: str, band: str | None, rate: float | None, wall: float,
                 settle_s: float) -> LoopState:
    """The running detector took ``config`` on its own (a reflex): what is expected of it now."""
    return dataclasses.replace(state, changed_at=wall, settled_after=wall + settle_s,
                               expected=(config, band, rate))


def reflex_stands(detail: Mapping[str, Any]) -> bool:
    """Whether a reflex's choice stands without the manager's plan: a try the detector made on its own
    frames' evidence (its detections collapsed or fell in steady light, e.g. under motion blur, which the
    band's plan cannot see). Its trial ends it: a ``revert`` reflex if the try finds no more markers
    than the configuration it replaced; a change of band ends it too."""
    return detail.get("evidence") == ReflexEvidence.COLLAPSE and detail.get("config") is not None


def reflex_trigger_detail(m: messages.Reflex) -> dict[str, Any]:
    """A ``reflex`` trigger's detail from the detector's message: its inputs, as ``why`` shows them."""
    detail = {"evidence": str(m.evidence), "previous": m.previous, "config": m.config, "band": m.band,
              "from_band": m.from_band, "level": m.level, "elsewhere": m.elsewhere}
    return {k: v for k, v in detail.items() if v is not None}


def held_refresh(state: LoopState, *, wall: float, every_s: float, force: bool = False) -> LoopState | None:
    """The state to go on with when the running detector's held memory is due to be asked, else None."""
    if not force and wall - state.held_checked < every_s:
        return None
    return dataclasses.replace(state, held_checked=wall)


def retry_later(state: LoopState, trigger: Trigger, *, mono: float, retry_s: float) -> LoopState:
    """Act on ``trigger`` again after ``retry_s``; it keeps its time, so latency runs from the loss."""
    return dataclasses.replace(state, retry=trigger, retry_at=mono + retry_s)


def due_retry(state: LoopState, *, mono: float) -> tuple[Trigger | None, LoopState]:
    """The trigger to act on again when its time has come (and the state without it)."""
    if state.retry is None or mono < state.retry_at:
        return None, state
    return state.retry, dataclasses.replace(state, retry=None)


def next_wake(state: LoopState, *, mono: float, probing: bool, starting: bool, leftovers: bool, standby: bool,
              startup_poll_s: float) -> float:
    """Seconds the loop may wait for an observation before something of its own is due.

    ``starting``: nothing runs, and the first placement also waits for the
    graph, which no event announces: every ``startup_poll_s``. ``probing``: the
    running detector's deployer is asked on schedule; ``standby``: the warm
    standby is kept.
    """
    if starting:
        return startup_poll_s
    due = [state.retry_at] if state.retry is not None else []
    if probing:
        due.append(state.next_check)
    if standby:
        due.append(state.next_standby_check)
    if leftovers:
        due.append(state.next_leftover_check)
    return min(IDLE_WAKE_S, max(0.0, min(due, default=mono + IDLE_WAKE_S) - mono))


def refusal_log_due(last: float | None, now: float) -> bool:
    return last is None or now - last >= REFUSAL_LOG_EVERY_S


# -- analyse: what the observations say ----------------------------------------


def lost_hosts(hosts: Mapping[str, HostView]) -> tuple[str, ...]:
    return tuple(h.name for h in hosts.values() if not h.online)


def to_measure(host: str, free_mb: float, *, running: Placement | None, standby: Placement | None,
               settled: bool) -> Placement | None:
    """The detector (running or standby) on ``host`` that looks short by this figure: its held memory is
    asked for again before it is called short (the profile's first sample, taken at exec, is a few MiB)."""
    if not settled:
        return None
    if running is not None and running.host == host and memory_short(free_mb, running):
        return running
    if (standby is not None and standby.host == host and (running is None or running.host != host)
            and memory_short(free_mb, standby)):
        return standby
    return None


def host_status_trigger(analyzer: Analyzer, host: str, *, free_mb: float, cpu_load: float, wall: float,
                        running: Placement | None, standby: Placement | None, state: LoopState,
                        received: float) -> Trigger | None:
    """A ``memory_short`` trigger for the running detector (or else the standby) from one admitted status.

    A status received before the last change settled was measured while old and
    new detector both ran: it updates the view but cannot say the new one does
    not fit. A detector measured only at exec is not called short within
    ``MEASURE_WITHIN_S`` of the change. The standby (on a host the running
    detector is not on) is short only once measured.
    """
    settled = received >= state.settled_after
    judged = running if settled else None
    if (judged is not None and judged.host == host and memory_short(free_mb, judged)
            and judged.held_mb < UNMEASURED_MB and wall - state.changed_at < MEASURE_WITHIN_S):
        judged = None
    trigger = analyzer.on_host_status(host, free_mb=free_mb, cpu_load=cpu_load, now=wall, running=judged)
    if (trigger is None and settled and standby is not None and standby.host == host
            and (running is None or running.host != host) and memory_short(free_mb, standby)
            and standby.held_mb >= UNMEASURED_MB):
        trigger = Trigger(TriggerKind.MEMORY_SHORT, wall, {"host": host, "free_mb": round(free_mb, 1),
                                                           "held_mb": round(standby.held_mb, 1),
                                                           "demand_mb": standby.demand_mb,
                                                           "standby": standby.instance})
    return trigger


def own_detection(running: Placement | None, *, body_instance: str, key_instance: str) -> bool:
    """Key and body both name the instance we run: any detector may put on detector/*/markers."""
    return running is not None and body_instance == running.instance and key_instance == running.instance


def clean_markers(ids: Sequence[Any], clean: Sequence[Any] | None) -> int:
    """Markers whose cells read clean (phantoms do not hold up a rate); no ``clean`` list: all count."""
    return sum(c is not False for c in (clean or [True] * len(ids))[:len(ids)])


def expected_rate(state: LoopState, configs: Mapping[str, Mapping[str, Any]], config: str,
                  band: str | None) -> float | None:
    """The detection rate calibration promised for ``config`` in ``band``: the plan's, else the graph's."""
    if state.expected is not None and state.expected[:2] == (config, band):
        return state.expected[2]
    row = configs.get(config)
    if row is None or band is None or row.get("band") != band:
        return None
    rate = row.get("detection_rate")
    return float(rate) if rate is not None else None


def ended(placement: Placement | None, *, instance: str, event: str) -> bool:
    """A deployer's event says ``placement``'s process ran its last."""
    return placement is not None and instance == placement.instance and event in ENDED_EVENTS


def crashed_standby(standby: Placement | None, *, instance: str, event: str) -> bool:
    """The standby's process exited unasked: supervision would restart it *active* (a detector starts
    active), beside the running one. It is to be stopped instead; the usual path starts a new, idle one."""
    return ended(standby, instance=instance, event=event) and event == ProcessEventKind.EXITED


def probing(running: Placement | None, hosts: Mapping[str, HostView]) -> bool:
    """The running detector's deployer is asked how it is (not while its host is lost: host_lost covers it)."""
    if running is None or not running.instance:
        return False
    view = hosts.get(running.host)
    return view is None or view.online


def probe_due(state: LoopState, running: Placement | None, hosts: Mapping[str, HostView], *, mono: float) -> bool:
    return probing(running, hosts) and mono >= state.next_check


def gone_trigger(running: Placement, state_name: str, *, wall: float) -> Trigger | None:
    """A ``detector_gone`` trigger when its deployer's answer says our detector no longer runs."""
    if state_name in KEPT_STATES:
        return None
    return Trigger(TriggerKind.DETECTOR_GONE, wall, {"instance": running.instance, "host": running.host,
                                                     "state": state_name[:120]})


def shows_online(rows: Iterable[Mapping[str, Any]], host: str) -> bool:
    """The ``platforms`` rows show ``host`` online with a free-memory figure."""
    return any(r.get("platform") == host and r.get("online") and r.get("memory_free_mb") is not None for r in rows)


def startup_trigger(analyzer: Analyzer, *, own_host: str, within_grace: bool, platforms: Callable[[], Rows],
                    confirmed: Callable[[str], bool], wall: float) -> Trigger | None:
    """Nothing runs: a ``startup`` trigger once the first plan can see what it needs.

    A band known and a host online; our own host in the graph with its figures
    (our agent declares its token only after all its parts are up, so the first
    plan could otherwise see only the remote host), or the grace period over;
    within the grace period every online host's figures confirmed, after it any
    host's. ``platforms`` is asked only when the rest allows a start.
    """
    band = analyzer.tracker.current
    online = [h.name for h in analyzer.hosts.values() if h.online]
    if band is None or not online:
        return None
    if within_grace:
        own = analyzer.hosts.get(own_host)
        if own is None or not own.online or not shows_online(platforms(), own_host):
            return None
    known = [confirmed(h) for h in online]
    if not (all(known) if within_grace else any(known)):
        return None  # a plan now could only fail or go elsewhere
    return Trigger(TriggerKind.STARTUP, wall, {"band": band.name})


# -- plan: what a trigger leads to -----------------------------------------------


class Action(StrEnum):
    """What the manager does with a trigger once a band is known."""

    WAIT = "wait"  # a host back without confirmed figures: act when they can be (the trigger is retried)
    STOP_STANDBY = "stop_standby"  # memory short with a standby: it is the first thing to go, nothing else moves
    DEFER = "defer"  # final descent: recorded once per kind of change
    DEFER_AGAIN = "defer_again"  # ... and only logged after that
    PLAN = "plan"


def band_moved(trigger: Trigger) -> bool:
    """Whether ``trigger`` moved the band: a change of the smoothed light, or a reflex that took another band."""
    return trigger.kind == TriggerKind.BAND_CHANGED or (trigger.kind == TriggerKind.REFLEX
                                                         and bool(trigger.detail.get("band_moved")))


def running_lost(running: Placement | None, trigger: Trigger, lost: Sequence[str]) -> bool:
    """The running detector is gone: its host lost, or its deployer says so."""
    return running is not None and (running.host in lost or trigger.kind == TriggerKind.DETECTOR_GONE)


# A host back waits for confirmed figures at most this many status windows (6 s at 1.5 s): statuses come late on
# a loaded machine; after that it is planned as it stands (the unconfirmed host left out), not retried for ever.
# Other triggers meanwhile are planned as they come.
HOST_BACK_WINDOWS = 4


def confirm_host_back(state: LoopState, trigger: Trigger, *, host_confirmed: bool, mono: float,
                      window_s: float) -> LoopState | None:
    """A host back without a confirmed status yet: the state that retries it a window later, else None (plan).

    Planning now, without it, could move the detector needlessly to the other host. Retried each window
    until the figures are confirmed, at most :data:`HOST_BACK_WINDOWS` times.
    """
    tries = int(trigger.detail.get("confirming") or 0)
    if trigger.kind != TriggerKind.HOST_BACK or state.retry is not None or host_confirmed or tries >= HOST_BACK_WINDOWS:
        return None
    again = Trigger(trigger.kind, trigger.time, {**trigger.detail, "confirming": tries + 1})
    return dataclasses.replace(state, retry=again, retry_at=mono + window_s)


def triage(trigger: Trigger, *, running: Placement | None, standby: Placement | None, lost: Sequence[str],
           landing: bool, deferred: Iterable[str], waiting: bool = False) -> Action:
    """What ``trigger`` leads to. ``waiting``: a host_back is waiting for its figures (see
    :func:`confirm_host_back`); unless the running detector is lost, nothing moves meanwhile."""
    gone = running_lost(running, trigger, lost)
    if waiting and not (running is not None and running.host in lost):
        return Action.WAIT
    if trigger.kind == TriggerKind.MEMORY_SHORT and standby is not None:
        return Action.STOP_STANDBY
    # In a descent a lost host matters only when it ran the detector (``gone``): another's loss would plan with
    # the band as it is now, carrying out a change the same descent deferred.
    urgent = trigger.urgent and trigger.kind != TriggerKind.HOST_LOST
    if landing and not (urgent or gone):
        # One decision per kind of change and descent: a descent (forged or not) with a flapping
        # light or repeated triggers must not write a decision per message.
        return Action.DEFER_AGAIN if trigger.kind in set(deferred) else Action.DEFER
    return Action.PLAN


def live_free(hosts: Mapping[str, HostView], *, here: str | None, roomiest: Callable[[str], float | None],
              confirmed: Callable[[str], float | None]) -> dict[str, float]:
    """Free memory the plan may count on, per online host.

    Only confirmed figures place a detector (every status of the window shows
    room); the running detector's host keeps it unless every status of the
    window shows it short (a forged "full" between real ones must not move it).
    """
    out: dict[str, float] = {}
    for h in hosts.values():
        if h.online and (free := (roomiest if h.name == here else confirmed)(h.name)) is not None:
            out[h.name] = free
    return out


class Execution(StrEnum):
    """How a plan is carried out."""

    NOTHING = "nothing"  # the plan is what runs (a startup or a host back: not recorded)
    KEEP = "keep"  # the plan is what runs: recorded as kept
    STANDBY = "standby"  # the standby takes over (reconfigured in place first if ``reconfigure_to``)
    START = "start"  # nothing runs (or it is lost): a new detector
    RECONFIGURE = "reconfigure"  # the running detector takes the configuration in place (else migrate)
    MIGRATE = "migrate"  # make-before-break to a new process


@dataclass(frozen=True)
class Execute:
    how: Execution
    why: str = ""
    reconfigure_to: str | None = None  # STANDBY: the configuration the standby takes in place first


def execution(plan: Plan, trigger: Trigger, *, running: Placement | None, standby: Placement | None,
              lost: Sequence[str], change: Callable[[Placement, Placement], tuple[Change, str]]) -> Execute:
    """How to carry ``plan`` out. ``change``: the planner's in-place-or-migrate rule (it asks the graph)."""
    gone = running_lost(running, trigger, lost)
    if plan.same_as(running) and not gone:
        quiet = trigger.kind in (TriggerKind.HOST_BACK, TriggerKind.STARTUP)
        return Execute(Execution.NOTHING if quiet else Execution.KEEP)
    if standby is not None and standby.host not in lost and running is not None:
        if standby.config == plan.target.config:
            return Execute(Execution.STANDBY,
                           f"the plan's configuration {standby.config} is the standby's, idle on {standby.host}: "
                           "a switch")
        if gone:
            # Failover: a standby of another configuration, changed in place, still beats a new process.
            how, why = change(standby, dataclasses.replace(plan.target, host=standby.host))
            if how == Change.RECONFIGURE:
                return Execute(Execution.STANDBY, f"{running.host} lost; the standby {standby.config} on "
                               f"{standby.host} takes over, {why}", reconfigure_to=plan.target.config)
    if running is None or gone:
        return Execute(Execution.START)
    how = plan.inputs.get("change", Change.MIGRATE)  # the planner's choice, from the graph
    why = str(plan.inputs.get("change_why", ""))
    return Execute(Execution.RECONFIGURE if how == Change.RECONFIGURE else Execution.MIGRATE, why)


@dataclass(frozen=True)
class ReadyMove:
    """The move planned ahead for the loss of ``host`` (the running detector's): the plan and how to
    carry it out, as they would be decided at the loss, from what the graph and the statuses said then."""

    host: str
    basis: tuple[Any, ...]  # what it rests on (move_basis): a move whose basis changed is planned again
    plan: Plan
    how: Execute
    at: float  # monotonic time it was planned


def move_basis(*, band: str | None, running: Placement | None, standby: Placement | None,
               lost: Sequence[str], exclude: Sequence[str]) -> tuple[Any, ...]:
    """What a move planned ahead rests on: the band, the running detector, the standby, the hosts lost
    before (not the one the move is for) and the configurations left out."""
    def who(p: Placement | None) -> tuple[Any, ...] | None:
        return None if p is None else (p.instance, p.config, p.host)

    return (band, who(running), who(standby), tuple(sorted(lost)), tuple(sorted(exclude)))


def ready_move(move: ReadyMove | None, trigger: Trigger, *, running: Placement | None, basis: tuple[Any, ...],
               mono: float, max_age_s: float) -> ReadyMove | None:
    """The move planned ahead, when ``trigger`` is the loss it was planned for and nothing it rests on
    changed meanwhile; else None (the loss is planned now). ``basis``: the move basis now, with the lost
    host left out of the lost hosts."""
    if move is None or running is None or trigger.kind != TriggerKind.HOST_LOST:
        return None
    if trigger.detail.get("host") != move.host or running.host != move.host:
        return None
    if move.basis != basis or mono - move.at > max_age_s:
        return None
    return move


def needs_move(move: ReadyMove | None, *, host: str, basis: tuple[Any, ...], mono: float, every_s: float) -> bool:
    """Whether the move for the loss of ``host`` must be planned (again)."""
    return move is None or move.host != host or move.basis != basis or mono - move.at >= every_s


@dataclass(frozen=True)
class BandMove:
    """The move planned ahead for a change into ``band`` (the running detector's band is another): the plan
    and how to carry it out, as a reflex or the band tracker would have them decided; both None when
    planning failed (tried again after ``every_s``, not at every quiet moment)."""

    band: str
    basis: tuple[Any, ...]  # move_basis with this band and no configuration left out (a band change clears them)
    at: float  # monotonic time it was planned
    plan: Plan | None = None
    how: Execute | None = None


def band_move_due(moves: Mapping[str, BandMove], *, bands: Sequence[str], basis: Callable[[str], tuple[Any, ...]],
                  mono: float, every_s: float) -> str | None:
    """The first of ``bands`` whose move must be planned (again): none yet, its basis changed, or older
    than ``every_s`` (the graph's figures move); None when every one is ready."""
    for band in bands:
        move = moves.get(band)
        if move is None or move.basis != basis(band) or mono - move.at >= every_s:
            return band
    return None


def band_move(move: BandMove | None, trigger: Trigger, *, basis: tuple[Any, ...], mono: float,
              max_age_s: float) -> BandMove | None:
    """The move planned ahead for the band ``trigger`` (a reflex or a band change) brings, while nothing it
    rests on changed and it is no older than ``max_age_s``; else None (the band is planned now)."""
    if move is None or move.plan is None or trigger.kind not in (TriggerKind.REFLEX, TriggerKind.BAND_CHANGED):
        return None
    if move.basis != basis or mono - move.at > max_age_s:
        return None
    return move


def failed(outcome: str) -> bool:
    return outcome.startswith("failed")


# -- the warm standby --------------------------------------------------------------


class StandbyStep(StrEnum):
    NOTHING = "nothing"
    DROP = "drop"  # gone with its host: forget it (host_back's reconcile stops it should it come back)
    STOP = "stop"  # not the neighbouring band's any more: stop it (a new one once its memory shows free)
    START = "start"  # none yet: plan and start one


def standby_step(*, running: Placement | None, standby: Placement | None, landing: bool, paused: bool,
                 retrying: bool, band: str | None, hosts: Mapping[str, HostView],
                 first_for: Callable[[str], str | None]) -> StandbyStep:
    """What the warm standby needs now. ``first_for(band)``: the first configuration of the band's
    ranking, None when the graph cannot say (asked only for a standby that runs)."""
    if running is None or not running.instance or landing or paused or retrying or band is None:
        return StandbyStep.NOTHING
    if standby is None:
        return StandbyStep.START
    view = hosts.get(standby.host)
    if view is not None and not view.online:
        return StandbyStep.DROP
    first = first_for(band)
    if first is None or (first == standby.config and standby.config != running.config):
        return StandbyStep.NOTHING  # still the one the neighbouring band wants (or no answer: try later)
    return StandbyStep.STOP


# -- twins ---------------------------------------------------------------------------


def ours(process: messages.ProcessDetail, configs: Mapping[str, Any]) -> bool:
    """A live detector process of one of our configurations."""
    return process.state in KEPT_STATES and process.config in configs


def adoption(processes: Iterable[messages.ProcessDetail], configs: Mapping[str, Any], *,
             onboard_host: str) -> tuple[messages.ProcessDetail | None, list[messages.ProcessDetail]]:
    """After a restart: the live detector of ours to adopt (onboard first), and the twins to stop."""
    live = sorted((p for p in processes if ours(p, configs)),
                  key=lambda p: (p.host != onboard_host, p.instance or ""))
    if not live:
        return None, []
    return live[0], live[1:]


def twins(processes: Iterable[messages.ProcessDetail], configs: Mapping[str, Any], *, running: Placement | None,
          standby: Placement | None) -> list[messages.ProcessDetail]:
    """Live detectors of ours that are neither the running one nor the standby."""
    keep = {p.instance for p in (running, standby) if p is not None}
    return [p for p in processes if ours(p, configs) and p.instance not in keep]


# -- knowledge: what a decision record says ------------------------------------------


@dataclass(kw_only=True)
class Outcome:
    """What one decision did, for the graph, the event stream and the demo's summary."""

    trigger: Trigger
    plan: Plan | None = None
    outcome: str = ""
    latency_ms: float | None = None  # trigger observed -> new detector's first detection
    frames_lost: int | None = None
    detail: dict[str, Any] = field(default_factory=dict)


def decision_record(outcome: Outcome, *, robot: str, wall: float, seq: int,
                    instance: str | None) -> tuple[dict[str, Any], messages.AdaptationEvent]:
    """The ``decision`` write's parameters and the ``adaptation_event`` message for one outcome.

    ``seq`` numbers the manager's decisions; ``instance``: the running detector's after it.
    """
    trigger, plan = outcome.trigger, outcome.plan
    name = f"{robot}-decision-{int(wall * 1000)}-{seq}"
    target = plan.target if plan else None
    inputs = {"trigger": dict(trigger.detail), **(dict(plan.inputs) if plan else {}), **outcome.detail}
    params: dict[str, Any] = {
        "name": name, "time": wall, "trigger": trigger.describe(),
        "inputs_json": json.dumps(inputs, default=str),
        "query": ",".join(plan.queries) if plan else None,
        "config": target.config if target else None, "host": target.host if target else None,
        "duration_ms": None if outcome.latency_ms is None else round(outcome.latency_ms, 1),
        "outcome": outcome.outcome if not plan else f"{outcome.outcome}: {plan.reason}",
    }
    change = outcome.detail.get("change")
    event = messages.AdaptationEvent(
        time=wall, trigger=trigger.describe(), outcome=outcome.outcome[:256],
        decision=messages.Decision(
            config=params["config"], host=params["host"], latency_ms=params["duration_ms"],
            # Values receivers of the first contract do not know are left out (the trigger's text names it).
            trigger_kind=trigger.kind if trigger.kind not in NEWER_TRIGGERS else None,
            frames_lost=outcome.frames_lost, name=name,
            instance=instance, previous_instance=outcome.detail.get("previous_instance"),
            trigger_time=trigger.time, change=change if change not in NEWER_CHANGES else None,
        ),
    )
    return params, event
