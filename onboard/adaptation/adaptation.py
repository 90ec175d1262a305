"""Run-time adaptation (MAPE-K): analyse what the monitors saw, plan with the knowledge graph.

This module is the decision logic only; it does no I/O of its own. The
adaptation manager (``onboard/adaptation/adaptation_manager.py``) feeds it observations
from Zenoh, hands it a ``KnowledgeAsk`` (named queries over Zenoh or on a
store), and executes its plans through the deployers.

Analyse
    :class:`BandTracker` turns smoothed illumination levels into band changes
    with hysteresis (a margin beyond the band edge) and a minimum dwell (the
    new band must hold that long), so light hovering at a threshold does not
    make the detector flap. :class:`Analyzer` adds the other triggers: the
    running host can no longer hold the detector, a host was lost or came
    back, the detection rate collapsed.

Plan
    :class:`Planner` asks the graph which configuration suits the band (best
    calibrated detection rate; of equal ones the faster beyond timing noise,
    then the more robust in the band's other conditions) and which platforms
    can hold it (the ``placement`` query, with live free memory), then picks a
    host by the preference setting. The default, ``onboard-first``, keeps the
    detector on the quadcopter while it fits, because the link to the remote
    host can fail and a detector on the far side of a broken link sees no
    frames; ``remote-first`` saves onboard CPU and memory instead.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from kgadapt.onboard.adaptation.live_rate import LIVE, LiveSettings, decided_by, weigh
from kgadapt.onboard.adaptation.planning_defaults import DEFAULT_PREFERENCE, IN_PLACE, ONBOARD_FIRST, ONBOARD_HOST, PREFERENCES
from kgadapt.onboard.perception.illumination import Band, bands_from_rows
from kgadapt.onboard.perception.ranking import OTHER_FIGURES, PENALTY, TIE_RATE, rank_graph_rows, ties
from kgadapt.shared.states import URGENT_TRIGGERS, Change, TriggerKind

__all__ = ["Band", "bands_from_rows", "BandTracker", "Analyzer", "Planner", "Placement", "Plan", "Trigger",
           "PlanningError", "HostView", "KnowledgeAsk", "FEATURE", "PREFERENCES", "memory_short", "room_for"]

# A function that answers a named query: (name, params) -> rows.
KnowledgeAsk = Callable[[str, Mapping[str, Any]], list[dict[str, Any]]]

FEATURE = "MarkerDetection"


@dataclass(kw_only=True)
class BandTracker:
    """The current band, changed only past a margin and after a dwell."""

    bands: Sequence[Band]
    hysteresis: float = 4.0  # luminance levels beyond the edge before a change counts
    dwell_s: float = 1.0  # how long the new band must hold
    current: Band | None = None
    previous: Band | None = None  # the band before the last change
    _pending: Band | None = field(default=None, repr=False)
    _pending_since: float = field(default=0.0, repr=False)
    _hold_until: float = field(default=0.0, repr=False)

    def band_of(self, level: float) -> Band | None:
        for band in self.bands:
            if band.contains(level):
                return band
        if not self.bands:
            return None
        # Outside every band: the nearest one (levels beyond the extremes).
        return min(self.bands, key=lambda b: min(abs(level - b.min_level), abs(level - b.max_level)))

    def neighbour(self, level: float | None) -> Band | None:
        """The band the light most likely goes to next: the one it left at the last change (light
        comes back: a shadow, a doorway, a window); before any change, of the current band's
        neighbours the one whose shared edge is nearest ``level`` (where the light heads near an edge)."""
        if self.current is None or self.current not in self.bands:
            return None
        if self.previous is not None and self.previous != self.current:
            return self.previous
        ordered = sorted(self.bands, key=lambda b: b.min_level)
        i = ordered.index(self.current)
        around = [b for b in (ordered[i - 1] if i > 0 else None, ordered[i + 1] if i + 1 < len(ordered) else None) if b]
        if not around:
            return None
        if level is None or not math.isfinite(level):
            return around[0]
        current = self.current
        return min(around, key=lambda b: abs(level - (b.max_level if b.max_level <= current.min_level
                                                        else b.min_level)))

    def jump(self, name: str, now: float, hold_s: float) -> Band | None:
        """The detector's reflex says the light is in band ``name`` now: take it, and give the smoothed
        level ``hold_s`` to catch up before its disagreement counts (then, past the dwell, it undoes it)."""
        band = next((b for b in self.bands if b.name == name), None)
        if band is None:
            return None
        if band != self.current:
            self.previous, self.current = self.current, band
        self._pending, self._hold_until = None, now + hold_s
        return band

    def update(self, level: float, now: float) -> Band | None:
        """Feed one smoothed level; return the new band when it changes, else None."""
        if not math.isfinite(level):
            return None
        if self.current is None:
            self.current = self.band_of(level)
            return self.current
        if self.current.contains(level, self.hysteresis) or now < self._hold_until:
            self._pending = None
            return None
        candidate = self.band_of(level)
        if candidate is None or candidate == self.current:
            self._pending = None
            return None
        if candidate != self._pending:
            self._pending, self._pending_since = candidate, now
        if now - self._pending_since >= self.dwell_s:
            self.previous, self.current, self._pending = self.current, candidate, None
            return candidate
        return None


@dataclass(frozen=True)
class Trigger:
    """Why the manager reconsiders the placement."""

    kind: TriggerKind
    time: float
    detail: Mapping[str, Any] = field(default_factory=dict)

    @property
    def urgent(self) -> bool:
        """Urgent triggers act even during final descent: the detector is gone or about to be."""
        return self.kind in URGENT_TRIGGERS

    def describe(self) -> str:
        bits = ", ".join(f"{k}={v}" for k, v in self.detail.items())
        return f"{self.kind}({bits})" if bits else str(self.kind)


@dataclass(frozen=True)
class Placement:
    """Where the detector runs (or should): configuration, deployment, host, instance."""

    config: str
    deployment: str
    host: str
    instance: str | None = None
    demand_mb: float = 0.0  # declared in the graph (sum of the components' memory demand)
    held_mb: float = 0.0  # what the running process actually holds (its profile's last RSS)
    run_id: str | None = None  # the deployer's run of that process (its ProcessProfile), when known


@dataclass(frozen=True)
class Plan:
    """A planned placement with the evidence it rests on."""

    target: Placement
    reason: str
    inputs: Mapping[str, Any]
    queries: tuple[str, ...]

    def same_as(self, current: Placement | None) -> bool:
        return current is not None and (current.config, current.host) == (self.target.config, self.target.host)


def room_for(demand_mb: float, *, free_mb: float, held_mb: float = 0.0) -> bool:
    """A host with ``free_mb`` free can hold ``demand_mb``, given back the ``held_mb`` that a detector it
    replaces holds there (free memory excludes what that detector holds)."""
    return free_mb + held_mb >= demand_mb


def memory_short(free_mb: float, placement: Placement) -> bool:
    """``placement``'s host can no longer cover the demand the graph declares for it."""
    return not room_for(placement.demand_mb, free_mb=free_mb, held_mb=placement.held_mb)


class PlanningError(Exception):
    """No configuration or no platform can realise the feature now."""


@dataclass(kw_only=True)
class HostView:
    """What the monitors know of one host."""

    name: str
    online: bool = False
    memory_free_mb: float | None = None
    cpu_load: float | None = None
    last_seen: float = 0.0


@dataclass(kw_only=True)
class CollapseWatch:
    """The running detector's own evidence: has its detection rate collapsed while markers are expected?

    Its rate is the markers it found per frame over the last ``window`` frames,
    against the most it found in one frame over the last ``memory_s`` seconds
    (how many markers are in view when detection works). It has collapsed when
    that falls below ``drop`` x the rate calibration promised for this
    configuration in this band, while markers are expected (some were seen in
    the last ``memory_s`` seconds). After it fires it stays quiet (hysteresis)
    until the rate is back above ``recover`` x the promise or a band change
    re-arms it, so a marker that simply left the view costs at most one change,
    not a cascade down the ranking.
    """

    window: int = 30
    drop: float = 0.5
    recover: float = 0.8
    memory_s: float = 5.0
    armed: bool = True
    _recent: list[int] = field(default_factory=list, repr=False)
    _seen: list[tuple[float, int]] = field(default_factory=list, repr=False)  # (time, count) with markers

    def update(self, markers: int, now: float, expected_rate: float | None) -> dict[str, Any] | None:
        """Feed one frame's marker count; the evidence (a dict) when the rate has just collapsed, else None."""
        markers = int(markers)
        self._recent.append(markers)
        if len(self._recent) > self.window:
            del self._recent[0]
        if markers > 0:
            self._seen.append((now, markers))
        while self._seen and now - self._seen[0][0] > self.memory_s:
            del self._seen[0]
        if len(self._recent) < self.window or expected_rate is None or expected_rate <= 0:
            return None
        in_view = max((n for _t, n in self._seen), default=0)
        if in_view == 0:
            return None  # nothing seen for memory_s: no marker is expected, nothing to compare
        rate = sum(self._recent) / len(self._recent) / in_view
        if not self.armed:
            if rate >= self.recover * expected_rate:
                self.armed = True
            return None
        if rate < self.drop * expected_rate:
            self.armed = False
            self._recent.clear()
            return {"rate": round(rate, 3), "expected": round(expected_rate, 3), "in_view": in_view,
                    "window": self.window, "drop": self.drop, "last_marker_s_ago": round(now - self._seen[-1][0], 2)}
        return None

    def reset(self) -> None:
        """A new detector: measure afresh (the hysteresis state and the markers in view stay)."""
        self._recent.clear()

    def rearm(self) -> None:
        self.armed = True
        self._recent.clear()


@dataclass(kw_only=True)
class Analyzer:
    """Turns observations into triggers. Keeps the state it needs (hosts, rates)."""

    tracker: BandTracker
    collapse: CollapseWatch = field(default_factory=CollapseWatch)
    collapsed: set[str] = field(default_factory=set)  # configurations whose detections collapsed in this band
    hosts: dict[str, HostView] = field(default_factory=dict)
    level: float | None = None  # the last smoothed illumination level

    def on_illumination(self, level: float, now: float) -> Trigger | None:
        self.level = level
        before = self.tracker.current
        band = self.tracker.update(level, now)
        if band is None or before is None:
            return None
        # A new band: every configuration gets its chance again.
        self.collapsed.clear()
        self.collapse.rearm()
        return Trigger(TriggerKind.BAND_CHANGED, now, {"from": before.name, "to": band.name, "level": round(level, 1)})

    def on_reflex(self, band: str, now: float, detail: Mapping[str, Any], *, hold_s: float) -> Trigger:
        """The running detector switched on its own (or found its band needs another process): a
        ``reflex`` trigger; the band follows it (see :meth:`BandTracker.jump`)."""
        before = self.tracker.current
        after = self.tracker.jump(band, now, hold_s)
        moved = after is not None and after != before
        if moved:
            self.collapsed.clear()
            self.collapse.rearm()
        self.collapse.reset()
        # A band moved by a reflex is a band change too (the smoothed light that follows it changes nothing more).
        return Trigger(TriggerKind.REFLEX, now, {**detail, "band_moved": True} if moved else dict(detail))

    def on_host_status(self, host: str, *, free_mb: float, cpu_load: float, now: float,
                       running: Placement | None) -> Trigger | None:
        view = self.hosts.setdefault(host, HostView(name=host))
        # Only liveliness says a host is online: after a partition heals, a status may
        # arrive before the token, and marking the host online here would swallow the
        # host_back that stops a twin detector there.
        view.memory_free_mb, view.cpu_load, view.last_seen = free_mb, cpu_load, now
        if running is not None and running.host == host and memory_short(free_mb, running):
            return Trigger(TriggerKind.MEMORY_SHORT, now, {"host": host, "free_mb": round(free_mb, 1),
                                                           "held_mb": round(running.held_mb, 1),
                                                           "demand_mb": running.demand_mb})
        return None

    def on_liveliness(self, host: str, alive: bool, now: float, running: Placement | None) -> Trigger | None:
        view = self.hosts.setdefault(host, HostView(name=host))
        was = view.online
        view.online = alive
        if not alive and was:
            if running is not None and running.host == host:
                return Trigger(TriggerKind.HOST_LOST, now, {"host": host})
            return Trigger(TriggerKind.HOST_LOST, now, {"host": host, "running_elsewhere": True})
        if alive and not was:
            return Trigger(TriggerKind.HOST_BACK, now, {"host": host})
        return None

    def on_detection(self, markers: int, now: float, expected_rate: float | None,
                     config: str | None = None) -> Trigger | None:
        """One frame of the running detector (``config``), ``markers`` found (a bool counts as 0 or 1).

        A ``rate_collapsed`` trigger when its rate collapsed (:class:`CollapseWatch`).
        """
        evidence = self.collapse.update(markers, now, expected_rate)
        if evidence is None:
            return None
        if config is not None:
            self.collapsed.add(config)
            evidence = {"config": config, **evidence}
        return Trigger(TriggerKind.RATE_COLLAPSED, now, evidence)

    def reset_rate(self) -> None:
        self.collapse.reset()


@dataclass(kw_only=True)
class Planner:
    """Chooses configuration and host from the knowledge graph.

    Configurations are ranked by the named query ``config_ranking`` (every
    configuration of the feature calibrated in the band: detection rate minus
    ``penalty`` x false markers per frame, none slower than ``max_ms``; within
    ``tie_rate`` the faster beyond timing noise, then the more robust in the band's
    other conditions (named query ``config_robustness``, asked only on a tie), then by
    name: :mod:`kgadapt.onboard.perception.ranking`, the rule the detector's reflex table
    ranks by too). The first in the ranking that a host can hold
    wins. A graph without calibration falls back to the configuration
    ``SUITED_FOR`` the band. Calibration of ``source`` (synthetic, or a recording's
    ``frames:NAME``) gives way to this robot's own live figures (named query
    ``live_rates``) where they are fresh and rest on enough frames
    (:func:`kgadapt.onboard.adaptation.live_rate.weigh`; ``clock`` says what now is).
    """

    ask: KnowledgeAsk
    feature: str = FEATURE
    preference: str = DEFAULT_PREFERENCE
    onboard_host: str = ONBOARD_HOST
    penalty: float = PENALTY
    max_ms: float = 1000.0
    tie_rate: float = TIE_RATE
    in_place: bool = IN_PLACE  # False: every change is a new process (for comparison)
    source: str = "synthetic"  # the calibration ranked by
    live: LiveSettings = field(default_factory=LiveSettings)
    clock: Callable[[], float] = time.time  # the wall clock live figures are aged by

    def __post_init__(self) -> None:
        if self.preference not in PREFERENCES:
            raise ValueError(f"preference {self.preference!r}: use one of {', '.join(PREFERENCES)}")

    def configs(self) -> list[dict[str, Any]]:
        return self.ask("detector_configs", {"feature": self.feature})

    def ranking(self, band: str, condition: str = "all") -> list[dict[str, Any]]:
        """Every calibrated configuration of the feature for ``band``, best first (each with its ``robustness``)."""
        rows = self.ask("config_ranking", {"feature": self.feature, "band": band, "condition": condition,
                                           "penalty": self.penalty, "max_ms": self.max_ms, "source": self.source})
        if rows:
            live = self.ask("live_rates", {"feature": self.feature, "band": band, "condition": condition})
            rows = weigh(rows, live, now=self.clock(), settings=self.live, penalty=self.penalty, source=self.source)
        if ties([float(r.get("score") or 0.0) for r in rows], self.tie_rate):
            # Only a tie needs the other conditions' figures: one more question, asked when it can matter.
            others = {r.get("config"): r for r in self.ask("config_robustness", {
                "feature": self.feature, "band": band, "condition": condition, "source": self.source})}
            rows = [{**r, **{k: others.get(r.get("config"), {}).get(k) for k in OTHER_FIGURES}} for r in rows]
        return rank_graph_rows(rows, penalty=self.penalty, tie_rate=self.tie_rate)

    def choose_config(self, band: str, *, exclude: Sequence[str] = ()) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """The first configuration of the ranking for ``band`` not in ``exclude``, and the ranking."""
        full, left = self.candidates(band, exclude=exclude)
        return left[0], full

    def candidates(self, band: str, *, exclude: Sequence[str] = ()) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """The whole ranking for ``band``, and what is left of it without ``exclude``."""
        ranked = self.ranking(band)
        if not ranked:
            # Not calibrated: the configuration(s) the models say are suited for the band.
            ranked = [r for r in self.configs() if r.get("band") == band]
        left = [r for r in ranked if r.get("config") not in exclude]
        if not left:
            what = f" other than {', '.join(exclude)}" if exclude and ranked else ""
            raise PlanningError(f"no detector configuration{what} is calibrated or suited for band {band!r}")
        return ranked, left

    def plan(self, *, band: str, running: Placement | None, lost_hosts: Sequence[str] = (),
             live_free: Mapping[str, float] | None = None, exclude: Sequence[str] = ()) -> Plan:
        """The best-ranked configuration for ``band`` that a host can hold now, and that host.

        ``exclude``: configurations not to choose (the one whose detections
        collapsed). The host running a detector gets back what that detector
        holds, since a change replaces it there. ``live_free`` is the caller's own,
        fresher view of free memory (host statuses it confirmed): a host the
        graph still thinks fits but that no longer does by that view is left out,
        and so is a host missing from it (other than the running one).
        """
        full, ranked = self.candidates(band, exclude=exclude)
        skipped: list[dict[str, Any]] = []
        for config_row in ranked:
            config = str(config_row["config"])
            demand = float(config_row.get("memory_demand_mb") or 0.0)
            fits = self._hosts_for(config, demand, running, lost_hosts, live_free)
            if fits:
                break
            skipped.append({"config": config, "why": f"no online platform has {demand:.0f} MiB free"})
        else:
            best = ranked[0]
            raise PlanningError(f"no online platform has {float(best.get('memory_demand_mb') or 0):.0f} MiB free "
                                f"for {best['config']}" + (f" (nor room for {len(ranked) - 1} other(s))"
                                                           if len(ranked) > 1 else ""))
        # The preference decides every time. Plans happen only on triggers (with
        # hysteresis and dwell on the light), so this cannot flap; it brings the
        # detector back to the preferred host when that host returns.
        order = sorted(fits, key=self._host_rank)
        host = order[0]
        row = fits[host]
        target = Placement(config=config, deployment=str(row["deployment"]), host=host, demand_mb=demand)
        position = full.index(config_row) + 1
        live = config_row.get("evidence") == LIVE
        evidence = (f"live rate {_fmt(config_row.get('live_rate'))} on this robot over "
                    f"{config_row.get('live_frames_expected')} frames with markers expected, "
                    f"{_fmt(config_row.get('live_age_s'))} s old; calibrated " if live
                    else f"{config_row['evidence']} calibration: " if config_row.get("evidence") else "")
        reason = (f"band {band}: {config} is {_ordinal(position)} in the ranking "
                  f"({evidence}rate {_fmt(config_row.get('detection_rate'))}, "
                  f"false/frame {_fmt(config_row.get('false_per_frame'))}, {_fmt(config_row.get('ms_per_frame'))} ms)"
                  + (f", {', '.join(exclude)} left out" if exclude else "")
                  + (f", above {', '.join(str(r['config']) for r in full[position:] if r.get('evidence') == LIVE)} "
                     "on their live evidence" if not live and decided_by(full, config_row, tie=self.tie_rate) == LIVE
                     else "")
                  + f"; {host} has {_fmt(row.get('free_mb'))} MiB free for {demand:.0f} MiB ({self.preference})")
        inputs = {
            "band": band,
            "ranking": [{**{k: r.get(k) for k in ("config", "score", "detection_rate", "false_per_frame",
                                                   "ms_per_frame", "memory_demand_mb")},
                         **{k: r[k] for k in ("evidence", "calibrated_score", "live_rate", "live_frames_expected",
                                              "live_age_s", "live_agrees") if k in r},
                         **({"robustness": r["robustness"]} if r.get("robustness") is not None else {})}
                        for r in full],
            "evidence": decided_by(full, config_row, tie=self.tie_rate),
            "excluded": list(exclude),
            "skipped": skipped,
            "expected_rate": config_row.get("live_rate") if live else config_row.get("detection_rate"),
            "platforms": [{"platform": h, "free_mb": fits[h].get("free_mb")} for h in order],
            "running": None if running is None else {"config": running.config, "host": running.host},
        }
        queries: tuple[str, ...] = ("config_ranking",
                                    *(("live_rates",) if any(r.get("live_rate") is not None for r in full) else ()),
                                    *(("config_robustness",) if any("other_conditions" in r for r in full) else ()),
                                    "placement")
        if running is not None and running.instance and (running.config, running.host) != (config, host):
            inputs["change"], inputs["change_why"] = self.change(running, target)
            queries += ("in_place_change",)
        return Plan(target=target, reason=reason, inputs=inputs, queries=queries)

    def change(self, running: Placement, target: Placement) -> tuple[Change, str]:
        """How to get from ``running`` to ``target``: (Change.RECONFIGURE or Change.MIGRATE, why).

        Reconfigure in place when the graph says the running deployment may take
        the target's on that host (named query ``in_place_change``); else migrate.
        """
        if not self.in_place:
            return Change.MIGRATE, "in-place changes are switched off on this agent (--no-in-place)"
        if target.host != running.host:
            return Change.MIGRATE, f"another host ({running.host} -> {target.host})"
        rows = self.ask("in_place_change", {"from": running.deployment, "to": target.deployment, "host": target.host})
        if not rows:
            return Change.MIGRATE, (f"the graph does not let {running.deployment} take {target.deployment} in place "
                               f"on {target.host} (in_place_change)")
        return Change.RECONFIGURE, (f"same host, {running.deployment} and {target.deployment} are both "
                               f"{rows[0].get('family')} (in_place_change)")

    def standby(self, *, band: str, running: Placement, lost_hosts: Sequence[str] = (),
                live_free: Mapping[str, float] | None = None) -> Plan | None:
        """A warm standby for ``band`` (the neighbouring one) beside ``running``, or None.

        The best-ranked configuration for ``band`` that a host has room for *as
        well* (the ``placement`` query with today's free memory, which the
        running detector already uses: no credit for it), onboard first. None when that
        configuration is the running one (a band change would keep it) or no
        host has room.
        """
        try:
            _full, ranked = self.candidates(band)
        except PlanningError:
            return None
        row = ranked[0]
        config = str(row["config"])
        if config == running.config:
            return None
        demand = float(row.get("memory_demand_mb") or 0.0)
        fits = self._hosts_for(config, demand, None, lost_hosts, live_free)
        if not fits:
            return None
        # Onboard first whatever the preference: an idle standby costs memory, not CPU, and onboard it
        # also covers losing the link to the remote host (the manager's own host is never lost to it).
        order = sorted(fits, key=lambda h: (h != self.onboard_host, h))
        host = order[0]
        target = Placement(config=config, deployment=str(fits[host]["deployment"]), host=host, demand_mb=demand)
        reason = (f"standby for band {band}: {config} (first in its ranking) kept idle; {host} has "
                  f"{_fmt(fits[host].get('free_mb'))} MiB free for {demand:.0f} MiB beside the running "
                  f"{running.config}@{running.host} (placement)")
        inputs = {"band": band, "standby": True,
                  "platforms": [{"platform": h, "free_mb": fits[h].get("free_mb")} for h in order],
                  "running": {"config": running.config, "host": running.host}}
        return Plan(target=target, reason=reason, inputs=inputs, queries=("config_ranking", "placement"))

    def _hosts_for(self, config: str, demand: float, running: Placement | None, lost_hosts: Sequence[str],
                   live_free: Mapping[str, float] | None) -> dict[str, dict[str, Any]]:
        rows = self.ask("placement", {"feature": self.feature, "config": config})
        fits: dict[str, dict[str, Any]] = {}
        for row in rows:
            host = str(row["platform"])
            if host in lost_hosts:
                continue
            fits[host] = row
        # The host already running a detector gets that detector's memory back
        # when it is replaced, so it may hold a configuration the query ruled out.
        if running is not None and running.host not in fits and running.host not in lost_hosts:
            for row in self.ask("platforms", {}):
                free = row.get("memory_free_mb")
                if (row.get("platform") == running.host and row.get("online") and free is not None
                        and room_for(demand, free_mb=free, held_mb=running.held_mb)):
                    deployment = self.ask("detector_config", {"config": config})
                    if deployment:
                        fits[running.host] = {"platform": running.host, "free_mb": free + running.held_mb,
                                              "deployment": deployment[0]["deployment"]}
        for host in list(fits):
            free = (live_free or {}).get(host)
            running_here = running is not None and running.host == host
            credit = running.held_mb if running is not None and running_here else 0.0
            if free is not None and not room_for(demand, free_mb=free, held_mb=credit):
                del fits[host]  # the graph has not caught up with a squeeze we already saw
            elif free is None and live_free is not None and not running_here:
                del fits[host]  # the caller has no confirmed figure of this host: the graph's alone moves nothing
        return fits

    def _host_rank(self, host: str) -> tuple[int, str]:
        onboard = host == self.onboard_host
        first = onboard if self.preference == ONBOARD_FIRST else not onboard
        return (0 if first else 1, host)


def _ordinal(n: int) -> str:
    return {1: "first", 2: "second", 3: "third"}.get(n, f"{n}th")


def _fmt(value: Any) -> str:
    if value is None:
        return "?"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)
