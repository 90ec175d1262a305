"""The detector's reflexes: what it switches to on its own, between two frames, and on which evidence.

The adaptation manager's loop decides on a smoothed light level, past a
hysteresis and a dwell, and then asks the detector to change: seconds after a
sudden step of the light. A running detector does not have to wait for it. When
it is configured it reads from the graph (named query ``reflex_table``) what it
may take in place on its host, band by band, and compiles it into a
:class:`ReflexTable`, ranked as the planner ranks (calibration, with this robot's
fresh live figures weighed above it); per frame, :class:`Reflex` weighs the evidence the frame
gives and says what to run:

* light: this frame's light estimate (window-proof, :func:`~kgadapt.onboard.perception.illumination.estimate_light`)
  is past an edge of the current band by more than the band's margin: take the
  new band's best configuration (``Swap``, evidence ``light``); where no
  configuration of that band may run here in place, say so (``Swap`` with no
  configuration: the manager starts one elsewhere);
* collapse: markers were seen within ``memory_s`` and the last
  ``collapse_frames`` frames found none: try the next candidate once (evidence
  ``collapse``), and go back (``revert``) when it finds nothing either;
* a fall: the last ``collapse_frames`` frames found on average less than
  ``fall_fraction`` of the typical count of the frames before them (within
  ``memory_s``): real motion blur leaves a marker or two of many, so the
  count falls without reaching zero. Try the next candidate once (evidence
  ``collapse``); the previous configuration runs beside it on every frame of
  the trial, and it stays only when it found more markers on those same frames
  (else ``revert``). Where the previous one could not run beside it, the count
  that fell (of the frames below the threshold, not those before the fall)
  stands for it, and a count still falling makes that stale: so after
  such a revert the previous configuration's own count is watched for
  ``recheck_frames`` frames (the try beside it within the budget), and when it
  finds fewer than the try did, the try is taken again (``collapse``) and kept.
  Which candidate: when the light is steady (within the band's margin of where
  markers were last seen) the light is not the cause; motion blur (or a harder
  view) is, so the first tried is the in-place choice calibration ranks best
  under blur in the band (``reflex_table``'s ``blur_rate``), when it is ranked
  above the running one there; after a fall, none when the running one holds
  best under blur already. Otherwise, or when the light moved, the band's
  other choices, then the neighbouring bands' best, nearest first.
* evidence, not waiting, is the hysteresis: after a switch the previous
  configuration runs beside the new one on the same frames (a hedge, within the
  graph's ms-per-frame budget, on frames the running one found nothing on: the
  detector asks :meth:`Reflex.hedge_for` only then) for ``trial_frames``; the
  new one stays when it finds markers, and the detector goes back (evidence
  ``revert``) when the old one finds them and the new one does not,
  ``confirm_frames`` times running.
  Near a band edge (within its margin) the neighbouring band's configuration is
  the hedge; finding markers where the running one does not, ``confirm_frames``
  times running, makes it the running one (evidence ``hedge``).

Nothing here does I/O or reads a clock: times are arguments.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from kgadapt.onboard.adaptation.live_rate import LiveSettings
from kgadapt.onboard.perception.illumination import Band
from kgadapt.onboard.perception.ranking import PENALTY, TIE_RATE, rank_graph_rows, rank_rows, score_of
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.states import ReflexEvidence


@dataclass(frozen=True)
class Choice:
    """A configuration a band may switch to in place."""

    config: str
    deployment: str
    ms_per_frame: float | None
    settings: Any  # the parsed configuration (kgadapt.onboard.perception.markers.DetectorConfig)
    blur_score: float | None = None  # calibrated score in the band under motion blur (None: not calibrated)


@dataclass(frozen=True)
class BandEntry:
    """One band of the table: its edges, margin and in-place choices, best first."""

    band: Band
    margin: float
    choices: tuple[Choice, ...]
    best_elsewhere: str | None = None  # the band's best configuration when it may not run here in place
    blur_order: tuple[Choice, ...] = ()  # the choices calibrated under blur, best under blur first

    @property
    def best(self) -> Choice | None:
        return self.choices[0] if self.choices else None


@dataclass(frozen=True)
class ReflexTable:
    """What a detector may switch to on its own, compiled from ``reflex_table`` rows."""

    entries: tuple[BandEntry, ...]  # lowest band first
    budget_ms: float | None = None  # ms per frame a hedge must fit in (None: no hedging)

    @classmethod
    def from_rows(cls, rows: Sequence[Mapping[str, Any]], *, parse: Callable[[str, str, str | None], Any],
                  default_margin: float = 3.0, penalty: float = PENALTY, tie_rate: float = TIE_RATE,
                  now: float | None = None, live: LiveSettings | None = None) -> "ReflexTable":
        """The table of ``reflex_table`` rows; ``parse(name, config_json, dictionary)`` checks a configuration.

        Ranked as the planner ranks (``config_ranking``, then :func:`~kgadapt.onboard.adaptation.live_rate.weigh`,
        then :func:`~kgadapt.onboard.perception.ranking.rank_graph_rows`): calibrated configurations by
        detection rate minus ``penalty`` x false markers per frame, a fresh live figure of this robot (as of
        ``now``; none without it) that disagrees with the calibrated rate in its place; within ``tie_rate``
        the faster beyond timing noise, then the more robust in the band's other conditions, then by name;
        a band without calibration falls back to the configurations suited for it.
        """
        from kgadapt.onboard.adaptation.live_rate import weigh

        by_band: dict[str, list[Mapping[str, Any]]] = {}
        bands: dict[str, tuple[Band, float]] = {}
        budget: float | None = None
        for row in rows:
            name = row.get("band")
            low, high = row.get("min_level"), row.get("max_level")
            if name is None or not isinstance(low, (int, float)) or not isinstance(high, (int, float)):
                raise ConfigError(f"reflex table: band {name!r} has bad limits {low!r}..{high!r}")
            margin = row.get("margin")
            bands[str(name)] = (Band(str(name), float(low), float(high)),
                                float(margin) if isinstance(margin, (int, float)) else default_margin)
            by_band.setdefault(str(name), []).append(row)
            if isinstance(row.get("budget_ms"), (int, float)) and row["budget_ms"] > 0:
                budget = float(row["budget_ms"])
        entries = []
        parsed: dict[str, Any] = {}
        for name, band_rows in by_band.items():
            calibrated: list[dict[str, Any]] = [
                {**r, "score": score_of(float(r["detection_rate"]), r.get("false_per_frame"), penalty)}
                for r in band_rows if r.get("detection_rate") is not None]
            if calibrated and now is not None:
                seen = [{"config": r["config"], "detection_rate": r["live_rate"], "at": r.get("live_at"),
                         "frames_expected": r.get("live_frames_expected")}
                        for r in calibrated if r.get("live_rate") is not None]
                calibrated = list(weigh(calibrated, seen, now=now, settings=live or LiveSettings(), penalty=penalty))

            ranked: Sequence[Mapping[str, Any]] = (
                rank_graph_rows(calibrated, penalty=penalty, tie_rate=tie_rate) if calibrated
                else [r for r in band_rows if r.get("suited")])
            choices: list[Choice] = []
            elsewhere = None
            for r in ranked:
                config = str(r["config"])
                if r.get("in_place") and r.get("deployment") and all(c.config != config for c in choices):
                    if config not in parsed:
                        parsed[config] = parse(config, str(r["config_json"]), r.get("dictionary"))
                    blur = r.get("blur_rate")
                    choices.append(Choice(config, str(r["deployment"]),
                                          float(r["ms_per_frame"]) if r.get("ms_per_frame") is not None else None,
                                          parsed[config],
                                          score_of(float(blur), r.get("blur_false_per_frame"), penalty)
                                          if isinstance(blur, (int, float)) else None))
                elif not choices and elsewhere is None:
                    elsewhere = config
            band, margin = bands[name]
            # Under blur by the same rule (score, then speed beyond noise, then name): no robustness step, since
            # the blur figure is the condition itself.
            blur_order = rank_rows([c for c in choices if c.blur_score is not None],
                                   score=lambda c: float(c.blur_score),
                                   ms=lambda c: c.ms_per_frame if c.ms_per_frame is not None else math.inf,
                                   name=lambda c: c.config, tie_rate=tie_rate)
            entries.append(BandEntry(band, margin, tuple(choices), elsewhere, tuple(blur_order)))
        entries.sort(key=lambda e: e.band.min_level)
        return cls(tuple(entries), budget)

    def entry(self, name: str | None) -> BandEntry | None:
        return next((e for e in self.entries if e.band.name == name), None)

    def band_of(self, level: float) -> BandEntry:
        """The band holding ``level``; outside every band, the nearest."""
        if not self.entries:
            raise ConfigError("the reflex table has no band")
        for e in self.entries:
            if e.band.contains(level):
                return e
        return min(self.entries, key=lambda e: min(abs(level - e.band.min_level), abs(level - e.band.max_level)))

    def band_for_config(self, config: str) -> BandEntry | None:
        """The band whose best in-place choice ``config`` is (what a detector started with it is configured for)."""
        return next((e for e in self.entries if e.best is not None and e.best.config == config), None)

    def neighbours(self, name: str) -> tuple[BandEntry | None, BandEntry | None]:
        """The bands below and above ``name``."""
        names = [e.band.name for e in self.entries]
        if name not in names:
            return None, None
        i = names.index(name)
        return (self.entries[i - 1] if i > 0 else None, self.entries[i + 1] if i + 1 < len(names) else None)

    def choices(self) -> dict[str, Choice]:
        """Every configuration the table may switch to, by name (to build their detectors beforehand)."""
        return {c.config: c for e in self.entries for c in e.choices}


@dataclass(frozen=True, kw_only=True)
class ReflexSettings:
    """How readily a detector acts on its own evidence."""

    collapse_frames: int = 3  # frames in a row without a marker ...
    memory_s: float = 1.0  # ... after markers were seen this recently
    trial_frames: int = 6  # after a switch: frames the previous configuration runs beside it (within budget)
    confirm_frames: int = 2  # frames in a row a hedge must win before it counts
    # A fall: the mean clean count of the last collapse_frames frames below fall_fraction x the typical (median)
    # count of the frames before them within memory_s, when that typical count is at least fall_min_typical
    # (a fall from one or two markers is the zero rule's). A half: a 7 px motion blur leaves 2-13 % of the
    # shipped photographs' markers to the band's configuration, but 37 % of a real DICT_4X4_50 board's at the
    # dusk band's darkest level (the dark configuration keeps 66 %); a hovering camera's view or a marker
    # leaving it moves the count by less. A try on a fall that was not one costs its trial: the previous
    # configuration runs beside it, or is rechecked after going back. 0 turns the rule off.
    fall_fraction: float = 1 / 2
    fall_min_typical: float = 3.0
    # After a fall's try went back: frames the previous configuration's own count is watched for. A try judged
    # against a count still falling (the previous one could not run beside it) is taken again when the previous
    # one then finds fewer than the try did. 0 turns the recheck off.
    recheck_frames: int = 3
    # A band only another process can take, reached by light still moving (by more than the band's margin
    # since the last frame) towards a band beyond it, is told once the light settles there or after this many
    # frames: a frame exposed while a lamp comes on reads in between (a step from dark to day told dusk first,
    # and the process started for it took the CPU from the day frame after it). 0 tells it at once.
    settle_frames: int = 3

    def __post_init__(self) -> None:
        if self.collapse_frames < 1 or self.trial_frames < 0 or self.confirm_frames < 1 or self.memory_s <= 0:
            raise ConfigError("reflex settings: collapse_frames >= 1, trial_frames >= 0, confirm_frames >= 1, "
                              "memory_s > 0")
        if self.settle_frames < 0:
            raise ConfigError(f"reflex settings: settle_frames >= 0, not {self.settle_frames}")
        if not 0 <= self.fall_fraction < 1 or self.fall_min_typical < 1 or self.recheck_frames < 0:
            raise ConfigError("reflex settings: 0 <= fall_fraction < 1, fall_min_typical >= 1, recheck_frames >= 0")


@dataclass(frozen=True)
class Swap:
    """A reflex: run ``config`` from now on (None: nothing here may run band ``band``; the manager must)."""

    config: str | None
    previous: str
    band: str
    from_band: str | None
    evidence: ReflexEvidence
    level: float | None
    deployment: str | None = None
    elsewhere: str | None = None  # with config None: the band's best, which needs another process


@dataclass
class FallTrial:
    """A try after a fall of the count: what each configuration found on the trial's frames."""

    fallen: float  # the mean count of the frames that fell (what the previous one found, for frames it did not run)
    new: int = 0  # markers the new configuration found
    old: float = 0.0  # markers the previous one found beside it (or ``fallen`` where it did not run)
    frames: int = 0  # frames of the trial so far
    beside: int = 0  # of those, frames the previous one ran beside it


@dataclass
class Recheck:
    """After a fall's try went back: the previous configuration's own count against what the try found."""

    tried: str  # the configuration tried
    per_frame: float  # markers a frame the try found on its trial (what it stands for where it does not run beside)
    left: int  # frames still to watch
    mine: int = 0  # markers the previous (running again) configuration found
    theirs: float = 0.0  # markers the try found beside it (or ``per_frame`` where it did not run)


@dataclass
class Reflex:
    """The per-frame reflex of one detector. ``on_light`` before detecting a frame, ``hedge_for`` to know
    what to run beside it, ``on_result`` with what both found."""

    table: ReflexTable
    running: str  # the configuration the detector runs
    settings: ReflexSettings = field(default_factory=ReflexSettings)
    band: str | None = None  # the band the reflex believes the light is in
    last_seen: float | None = None  # when the running configuration last found a marker
    misses: int = 0
    muted: bool = False  # a collapse was tried: none again until markers are seen
    trial: tuple[str, int] | None = None  # (previous configuration, frames left to run it beside)
    trying: str | None = None  # after a collapse: the previous configuration, to go back to if the try finds nothing
    wins: int = 0  # frames in a row the hedge found markers and the running one did not
    swaps: int = 0
    told: bool = False  # the last band change was only told (nothing here could take it in place)
    seen_level: float | None = None  # the light when the running configuration last found a marker
    counts: deque[tuple[float, int]] = field(default_factory=deque)  # (time, clean count) within memory_s
    fall: FallTrial | None = None  # a try after a fall of the count, being judged
    recheck: Recheck | None = None  # after that try went back: the previous configuration's count, watched
    # The running configuration is the manager's choice, made before this table came (a change taken right
    # after the start): its band is the light's on the first frame, not the configuration's, or the reflex
    # would undo the change as if it were a start's stale configuration.
    follow_light: bool = False
    last_level: float | None = None  # the light of the previous frame that had an estimate
    settling: int = 0  # frames a told band has waited for the light to settle (settle_frames)

    @property
    def comparing(self) -> bool:
        """A try after a fall is being judged, or the configuration it went back to is: the other one runs
        beside it on every frame (the detector asks :meth:`hedge_for` on frames the running one found markers
        on too)."""
        return self.fall is not None or self.recheck is not None

    def on_light(self, level: float | None) -> Swap | None:
        """This frame's light; a Swap when it is past an edge of the band by more than the margin."""
        if level is None or not math.isfinite(level) or not self.table.entries:
            return None
        previous, self.last_level = self.last_level, level
        current = self.table.entry(self.band)
        if current is None:
            # Just started: the band it was configured for (a step while it started counts), else the light's.
            current = (None if self.follow_light else self.table.band_for_config(self.running)) or \
                self.table.band_of(level)
            self.band = current.band.name
        if current.band.contains(level, current.margin):
            self.settling = 0
            return None
        new = self.table.band_of(level)
        if new.band.name == current.band.name:
            self.settling = 0
            return None
        best = new.best
        if best is None and self._passing(new, level, previous):
            return None  # the band stays; the next frame says where the light went
        self.settling = 0
        self.band = new.band.name
        if best is None:  # nothing of that band runs here in place: tell, keep detecting with what runs
            self.told = True
            return Swap(None, self.running, new.band.name, current.band.name, ReflexEvidence.LIGHT, level,
                        elsewhere=new.best_elsewhere)
        if best.config == self.running:
            if self.told:  # the manager was told of another band: tell it the light is back in this one
                self.told = False
                return Swap(None, self.running, new.band.name, current.band.name, ReflexEvidence.LIGHT, level)
            return None
        return self._swap(best, ReflexEvidence.LIGHT, level, from_band=current.band.name)

    def _passing(self, new: BandEntry, level: float, previous: float | None) -> bool:
        """The light is on its way through band ``new`` (see ``ReflexSettings.settle_frames``): it moved by more
        than the band's margin since the last frame, towards a band beyond it, and has not waited long."""
        if previous is None or self.settling >= self.settings.settle_frames:
            return False
        moved = level - previous
        if abs(moved) <= new.margin:
            return False  # settled (or drifting, as at dusk outdoors): tell now
        below, above = self.table.neighbours(new.band.name)
        if (above if moved > 0 else below) is None:
            return False  # the last band that way: nowhere further to go
        self.settling += 1
        return True

    def hedge_for(self, level: float | None) -> str | None:
        """The configuration to run beside the running one on this frame, if any: the previous one
        during a trial, else near an edge (within the band's margin) the neighbouring band's best."""
        if self.trial is not None:
            return self.trial[0]
        if self.recheck is not None:
            return self.recheck.tried
        current = self.table.entry(self.band)
        if current is None or level is None or not math.isfinite(level):
            return None
        if current.band.contains(level, -current.margin):
            return None  # well inside the band
        below, above = self.table.neighbours(current.band.name)
        middle = (current.band.min_level + current.band.max_level) / 2
        side = below if level < middle else above
        best = side.best if side is not None else None
        return best.config if best is not None and best.config != self.running else None

    def on_result(self, found: int, now: float, *, hedge: str | None = None, hedge_found: int = 0,
                  level: float | None = None) -> Swap | None:
        """What the running configuration (and the hedge, if one ran) found on this frame; a Swap when
        the evidence says to change."""
        expired = False
        if self.trial is not None:
            previous, left = self.trial
            self.trial = (previous, left - 1) if left > 1 else None
            expired = self.trial is None
        if self.fall is not None:
            return self._judge_fall(found, now, hedge, hedge_found, expired, level)
        if self.recheck is not None:
            again = self._recheck(found, hedge, hedge_found, level)
            if again is not None:
                return again
        self._count(found, now)
        if found > 0:
            self._saw(now, level)
            self.misses, self.muted, self.wins, self.trying = 0, False, 0, None
            if self.trial is not None and hedge == self.trial[0]:
                self.trial = None  # the new one finds the markers: it stays
            fallen = self._fallen() if self.trial is None else None
            if fallen is not None:
                return self._collapse(level, fallen=fallen)
            return None
        if hedge is not None and hedge_found > 0:
            self.wins += 1
            if self.wins >= self.settings.confirm_frames:
                choice = self.table.choices().get(hedge)
                if choice is not None:
                    reverting = self.trial is not None and hedge == self.trial[0]
                    self.trial, self.trying = None, None
                    self.last_seen, self.misses = now, 0
                    return self._swap(choice, ReflexEvidence.REVERT if reverting else ReflexEvidence.HEDGE, level,
                                      trial=False)
            return None
        self.wins = 0
        if expired and self.trying is not None:
            # The try after a collapse found nothing either: back to the band's own choice, no cascade.
            back = self.table.choices().get(self.trying)
            self.trying = None
            if back is not None:
                return self._swap(back, ReflexEvidence.REVERT, level, trial=False)
        if self.muted or self.last_seen is None or now - self.last_seen > self.settings.memory_s:
            return None
        self.misses += 1
        if self.misses < self.settings.collapse_frames:
            return None
        self.misses = 0
        self.muted = True  # one try per collapse: no cascade down the table
        return self._collapse(level)

    def _saw(self, now: float, level: float | None) -> None:
        """The running configuration found markers: when, and in what light."""
        self.last_seen = now
        if level is not None and math.isfinite(level):
            self.seen_level = level

    def _count(self, found: int, now: float) -> None:
        self.counts.append((now, found))
        while self.counts and now - self.counts[0][0] > self.settings.memory_s:
            self.counts.popleft()

    def _fallen(self) -> float | None:
        """When the last ``collapse_frames`` frames found on average less than ``fall_fraction`` of the typical
        (median) count of the frames before them within ``memory_s``: the mean count of the frames of those
        below it (None: no fall). Only those: a frame still before the fall is no figure for the trial's."""
        s = self.settings
        if s.fall_fraction <= 0 or s.trial_frames < 1:  # a fall try is judged over a trial
            return None
        counts = [c for _t, c in self.counts]
        if len(counts) < 2 * s.collapse_frames:
            return None
        window, before = counts[-s.collapse_frames:], counts[:-s.collapse_frames]
        typical = statistics.median(before)
        threshold = s.fall_fraction * typical
        if typical < s.fall_min_typical or statistics.fmean(window) >= threshold:
            return None
        return statistics.fmean(c for c in window if c < threshold)  # the mean is below it: a frame is

    def _collapse(self, level: float | None, *, fallen: float | None = None) -> Swap | None:
        nxt = self._next_candidate(level, fall=fallen is not None)
        if nxt is None:
            return None
        self.trying = self.running
        swap = self._swap(nxt, ReflexEvidence.COLLAPSE, level)
        if fallen is not None:
            self.fall = FallTrial(fallen)
        return swap

    def _judge_fall(self, found: int, now: float, hedge: str | None, hedge_found: int, expired: bool,
                    level: float | None) -> Swap | None:
        """A frame of the trial after a fall: the new configuration stays only when it found more markers
        than the previous one on the trial's frames (where the previous did not run beside it, the count
        that fell stands for it)."""
        fall = self.fall
        assert fall is not None
        if found > 0:
            self._saw(now, level)
        beside = hedge is not None and hedge == self.trying
        fall.new += found
        fall.old += hedge_found if beside else fall.fallen
        fall.frames += 1
        fall.beside += beside
        if not expired:
            return None
        previous, self.fall, self.trying = self.trying, None, None
        if fall.new > fall.old:
            return None  # more markers on the same frames: it stays
        back = self.table.choices().get(previous) if previous is not None else None
        if back is None:
            return None
        tried = self.running
        swap = self._swap(back, ReflexEvidence.REVERT, level, trial=False)
        if fall.beside < fall.frames and self.settings.recheck_frames > 0:
            # Judged, at least in part, against the count that fell: see what the previous one finds now.
            self.recheck = Recheck(tried, fall.new / fall.frames, self.settings.recheck_frames)
        return swap

    def _recheck(self, found: int, hedge: str | None, hedge_found: int, level: float | None) -> Swap | None:
        """A frame after a fall's try went back: the try again, kept, when the previous configuration finds
        fewer markers than the try did (beside it on the same frames, else on its trial)."""
        check = self.recheck
        assert check is not None
        check.mine += found
        check.theirs += hedge_found if hedge is not None and hedge == check.tried else check.per_frame
        check.left -= 1
        if check.left > 0:
            return None
        self.recheck = None
        if check.mine >= check.theirs:
            return None  # the previous one finds as many: it was right to go back
        tried = self.table.choices().get(check.tried)
        if tried is None:
            return None
        # A collapse's try, kept on evidence: the manager lets it stand (adaptation_policy.reflex_stands). It runs
        # with the usual trial (back only when the previous one finds markers and it does not).
        return self._swap(tried, ReflexEvidence.COLLAPSE, level)

    def _steady(self, current: BandEntry, level: float | None) -> bool:
        """The light is within the band's margin of where markers were last seen: it did not cause the loss."""
        return (level is not None and math.isfinite(level) and self.seen_level is not None
                and abs(level - self.seen_level) <= current.margin)

    def _next_candidate(self, level: float | None, *, fall: bool = False) -> Choice | None:
        """After a collapse in steady light: the band's choice best under motion blur, when it is ranked above
        the running one there; after a fall (markers still found) none when the running one holds best under
        blur already (a blur's fall is no reason to try what holds worse under it). Otherwise the band's other
        choices, then the neighbouring bands' best, nearest first."""
        current = self.table.entry(self.band)
        if current is None:
            return None
        if self._steady(current, level):
            mine = next((c.blur_score for c in current.choices if c.config == self.running), None)
            for c in current.blur_order:
                if c.config == self.running:
                    if fall:
                        return None
                    break  # it holds best under blur already
                if mine is None or (c.blur_score is not None and c.blur_score > mine + TIE_RATE):
                    return c
        for c in current.choices:
            if c.config != self.running:
                return c
        below, above = self.table.neighbours(current.band.name)
        sides = [e for e in (below, above) if e is not None]
        if level is not None and math.isfinite(level):
            sides.sort(key=lambda e: min(abs(level - e.band.min_level), abs(level - e.band.max_level)))
        for e in sides:
            for c in e.choices:
                if c.config != self.running:
                    return c
        return None

    def _swap(self, choice: Choice, evidence: ReflexEvidence, level: float | None, *, from_band: str | None = None,
              trial: bool = True) -> Swap:
        self.told = False
        self.fall, self.recheck = None, None
        self.counts.clear()  # another configuration's counts are no typical for this one
        previous, self.running = self.running, choice.config
        self.trial = (previous, self.settings.trial_frames) if trial and self.settings.trial_frames else None
        self.wins = 0
        self.swaps += 1
        return Swap(choice.config, previous, self.band or "", from_band if from_band is not None else self.band,
                    evidence, level, deployment=choice.deployment)

    def taken(self, config: str, level: float | None = None) -> None:
        """The detector was told to run ``config`` (an in-place change from the manager): follow it."""
        self.running = config
        self.trial, self.trying, self.wins, self.misses, self.fall, self.recheck = None, None, 0, 0, None, None
        self.counts.clear()
        if self.band is None:  # before its first frame: the light's band, not the configuration's
            self.follow_light = True
        if level is not None and math.isfinite(level) and self.table.entries:
            self.band = self.table.band_of(level).band.name
