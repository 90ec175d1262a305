"""What happened during a run, as seen on the Zenoh network: the demo's timeline.

:class:`Recorder` subscribes (callbacks only append under a lock) to
illumination, host status, the adaptation manager's decisions, every
detector's detections and reflexes, and can print decisions and reflexes live. Afterwards it answers:
detection rate over time, frames that no detector processed around each
planned migration, the summary table, and a PNG timeline.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TypeVar

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import MessageError
from kgadapt.shared.states import Change, TriggerKind

M = TypeVar("M", bound=messages.Message)


@dataclass
class Decision:
    time: float
    trigger: str
    kind: str  # a TriggerKind value, "" when the event names none
    config: str | None
    host: str | None
    outcome: str
    latency_ms: float | None
    frames_lost: int | None = None  # frames between the old detector's last answer and the new one's first
    frames_dropped: int | None = None  # frames no detector answered around the migration (busy detectors)
    # Of frames_lost in an in-place change: those the detector says it replaced in its one-frame slot
    # while busy (its "dropped" count rose across the gap), as it does whenever the CPU falls behind.
    frames_lost_busy: int | None = None
    instance: str | None = None
    previous_instance: str | None = None
    trigger_time: float | None = None  # when the manager observed the trigger (the band decided, after the dwell)
    change: str | None = None  # a kgadapt.shared.states.Change value


@dataclass
class LightStep:
    """A step of the scenario's light and how long the robot was blind after it."""

    kind: str  # e.g. "day->dark"
    frame_seq: int  # the first frame of the new light
    frame_time: float  # its capture time
    seen_seq: int | None  # the first frame of the new light whose detections contain a marker it shows
    blind_ms: float | None  # capture of the first new-light frame -> publication of those detections
    band_ms: float | None  # capture of the first new-light frame -> the band change decided (EMA, hysteresis, dwell)
    change: str | None = None  # what the decision after the step did (reconfigure / migrate / kept)
    # The frame just before it was exposed during the step (its level is between the two, which classify
    # names None): the camera's frames kept the phase of a step period that is a whole number of frames.
    between: bool = False
    bands_between: int = 0  # the detectors' reflexes to a band neither side of the step, in the step's time


@dataclass
class ReflexSeen:
    """A detector's own switch (or report) as it put it on its ``reflex`` key."""

    time: float  # when the detector put it
    instance: str
    previous: str
    config: str | None  # None: nothing it may take in place is for the band
    band: str
    evidence: str
    level: float | None
    seq: int
    frame_time: float


@dataclass
class Recorder:
    """Records one robot's run. ``setup(session)`` subscribes; ``shutdown()`` stops."""

    robot: str
    camera: str = "cam0"
    on_decision: Callable[[Decision], None] | None = None
    on_reflex: Callable[[ReflexSeen], None] | None = None
    t0: float = field(default_factory=time.time)
    light: list[tuple[float, float, int]] = field(default_factory=list)  # (time, smoothed level, frame seq)
    memory: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # host -> (time, free MiB)
    detections: list[tuple[float, str, str, str, int, int]] = field(default_factory=list)
    decisions: list[Decision] = field(default_factory=list)
    marks: list[tuple[float, str]] = field(default_factory=list)  # scripted actions (squeeze, kill)
    # per frame: seq -> (capture time, the scenario's light level, marker ids it shows)
    frames: dict[int, tuple[float, float | None, frozenset[int]]] = field(default_factory=dict)
    found: list[tuple[int, float, frozenset[int]]] = field(default_factory=list)  # (seq, published, ids)
    reflexes: list[ReflexSeen] = field(default_factory=list)  # each reflex once (not its repeats)
    # per detector instance: its hedging so far (frames, frames hedged, ms), from its reflex messages
    hedges: dict[str, tuple[int, int, float]] = field(default_factory=dict)
    detect_ms: list[float] = field(default_factory=list)  # processing ms of every detection

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._stack = contextlib.ExitStack()
        self._detected_seqs: set[int] = set()
        self._dropped: dict[tuple[str, int], int] = {}  # (instance, seq answered) -> the detector's dropped count

    def setup(self, session: Any) -> None:
        r = self.robot
        with contextlib.ExitStack() as stack:
            for key, callback in ((keys.camera_illumination(r, self.camera), self._on_light),
                                  (keys.host_status(r), self._on_status),
                                  (keys.adaptation_events(r), self._on_event),
                                  (keys.detector_markers(r), self._on_detections),
                                  (keys.detector_reflex(r), self._on_reflex),
                                  (keys.camera_frame(r, self.camera), self._on_frame)):
                rpc.declared(stack, session.declare_subscriber(key, callback))
            self._stack = stack.pop_all()

    def shutdown(self) -> None:
        self._stack.close()

    def mark(self, text: str) -> None:
        with self._lock:
            self.marks.append((time.time(), text))

    # -- callbacks: decode and append, nothing else ------------------------

    def _decode(self, sample: Any, kind: type[M]) -> M | None:
        try:
            return messages.decode_as(sample.payload.to_bytes(), kind)
        except MessageError:
            return None

    def _on_light(self, sample: Any) -> None:
        m = self._decode(sample, messages.Illumination)
        if m:
            with self._lock:
                self.light.append((time.time(), float(m.smoothed), int(m.seq)))

    def _on_status(self, sample: Any) -> None:
        m = self._decode(sample, messages.HostStatus)
        if m:
            with self._lock:
                self.memory.setdefault(str(m.host), []).append((time.time(), float(m.memory_free_mb)))

    def _on_detections(self, sample: Any) -> None:
        m = self._decode(sample, messages.Detections)
        if m:
            with self._lock:
                self.detections.append((time.time(), str(m.instance), str(m.config), str(m.host),
                                        int(m.seq), len(m.ids)))
                self._detected_seqs.add(int(m.seq))
                self._dropped[(str(m.instance), int(m.seq))] = int(m.dropped or 0)
                self.detect_ms.append(float(m.processing_ms))
                if m.ids:
                    self.found.append((int(m.seq), float(m.time), frozenset(int(i) for i in m.ids)))

    def _on_reflex(self, sample: Any) -> None:
        m = self._decode(sample, messages.Reflex)
        if not m:
            return
        seen = ReflexSeen(time=float(m.time), instance=str(m.instance), previous=str(m.previous),
                          config=m.config, band=str(m.band), evidence=str(m.evidence),
                          level=m.level, seq=int(m.seq), frame_time=float(m.frame_time))
        with self._lock:
            if m.frames is not None:
                self.hedges[seen.instance] = (int(m.frames), int(m.hedged or 0), float(m.hedge_ms or 0))
            new = not any(r.instance == seen.instance and r.seq == seen.seq for r in self.reflexes[-8:])
            if new:
                self.reflexes.append(seen)
        if new and self.on_reflex:
            self.on_reflex(seen)

    def hedging(self) -> dict[str, Any]:
        """What hedging cost, from the detectors' reflex messages (their last figures): ms per processed
        frame on average, the share of frames hedged, and ms per hedged frame."""
        with self._lock:
            figures = list(self.hedges.values())
            detect = list(self.detect_ms)
        frames = sum(f for f, _, _ in figures)
        hedged = sum(h for _, h, _ in figures)
        ms = sum(t for _, _, t in figures)
        if not frames:
            return {"frames": 0}
        return {"frames": frames, "hedged_share": round(hedged / frames, 4),
                "hedge_ms_per_frame": round(ms / frames, 3),
                "hedge_ms_when_hedged": round(ms / hedged, 3) if hedged else None,
                "detect_ms_per_frame": round(sum(detect) / len(detect), 3) if detect else None}

    def _on_frame(self, sample: Any) -> None:
        m = self._decode(sample, messages.Frame)
        if m:
            ids = frozenset(int(t["id"]) for t in m.truth or [] if isinstance(t, dict) and "id" in t)
            level = m.level
            with self._lock:
                self.frames[int(m.seq)] = (float(m.time), None if level is None else float(level), ids)

    def _on_event(self, sample: Any) -> None:
        m = self._decode(sample, messages.AdaptationEvent)
        if not m:
            return
        d = m.decision
        trigger, outcome = str(m.trigger), str(m.outcome or "")
        # A kind newer than the event's contract is left out of trigger_kind: the trigger's text names it.
        kind = str(d.trigger_kind if d and d.trigger_kind else (trigger.split("(", 1)[0] if d else ""))
        change = (d.change if d else None) or (Change.REFLEX if outcome.startswith("reconfigured by reflex") else None)
        d = d or messages.Decision()
        decision = Decision(time=float(m.time), trigger=trigger, kind=kind,
                            config=d.config, host=d.host, outcome=outcome,
                            latency_ms=d.latency_ms, instance=d.instance,
                            previous_instance=d.previous_instance, trigger_time=d.trigger_time,
                            change=change)
        with self._lock:
            self.decisions.append(decision)
        if self.on_decision:
            self.on_decision(decision)

    # -- analysis ----------------------------------------------------------

    def latest(self) -> dict[str, Any]:
        """The newest figures, for a status line."""
        with self._lock:
            light = self.light[-1][1] if self.light else None
            free = {h: v[-1][1] for h, v in self.memory.items() if v}
            last = self.detections[-1] if self.detections else None
        return {"light": light, "free": free, "running": None if last is None else f"{last[2]}@{last[3]}",
                "rate": self.detection_rate(time.time() - 1.0, time.time())}

    def detection_rate(self, start: float, end: float) -> float | None:
        """Share of frames in [start, end) on which some detector found a marker."""
        with self._lock:
            frames = [seq for t, _, seq in self.light if start <= t < end]
            hits = {seq for t, _, _, _, seq, n in self.detections if n > 0}
        if not frames:
            return None
        return sum(1 for seq in frames if seq in hits) / len(frames)

    def frames_unprocessed(self, start: float, end: float) -> int:
        """Frames captured in [start, end) that no detector answered (with or without markers)."""
        with self._lock:
            frames = [seq for t, _, seq in self.light if start <= t < end]
            done = set(self._detected_seqs)
        return sum(1 for seq in frames if seq not in done)

    def attribute_losses(self, margin_s: float = 0.5) -> None:
        """Per planned change (migration, in-place reconfiguration, switch to a standby): the coverage gap (frames lost)
        and busy drops around it.

        A planned migration loses a frame when no detector covers it: captured
        after the old instance's last answered frame and before the new one's
        first. With make-before-break the new one answers first, so the gap is 0.
        Separately, ``frames_dropped`` counts frames nobody answered in the window
        around the migration: detectors drop stale frames when the CPU is busy.
        """
        with self._lock:
            frames = [seq for _, _, seq in self.light]
            answered: dict[str, list[int]] = {}
            by_config: dict[tuple[str, str], list[int]] = {}
            for _, instance, config, _, seq, _ in self.detections:
                answered.setdefault(instance, []).append(seq)
                by_config.setdefault((instance, config), []).append(seq)
        for d in self.decisions:
            if not (d.outcome.startswith(("migrated", "reconfigured", "switched")) and d.latency_ms is not None):
                continue
            start = d.time - d.latency_ms / 1000.0 - margin_s
            d.frames_dropped = self.frames_unprocessed(start, d.time + margin_s)
            if d.outcome.startswith("reconfigured"):
                # One process: the gap is between its last answer with another configuration and
                # its first with the new one.
                new = by_config.get((d.instance or "", d.config or ""), [])
                old = [seq for (inst, cfg), seqs in by_config.items() if inst == d.instance and cfg != d.config
                       for seq in seqs if not new or seq < min(new)]
            else:
                old = answered.get(d.previous_instance or "", [])
                new = answered.get(d.instance or "", [])
            if not old or not new:
                d.frames_lost = None  # not observed (e.g. the recorder joined late)
                continue
            old_last, new_first = max(old), min(new)
            d.frames_lost = sum(1 for seq in frames if old_last < seq < new_first)
            if d.outcome.startswith("reconfigured"):
                with self._lock:
                    rose = (self._dropped.get((d.instance or "", new_first), 0)
                            - self._dropped.get((d.instance or "", old_last), 0))
                d.frames_lost_busy = min(d.frames_lost, max(0, rose))

    def light_steps(self, classify: Callable[[float], str | None],
                    band_of: Callable[[str], str] = lambda kind: kind) -> list[LightStep]:
        """Every step of the scenario's light between the classes ``classify`` gives levels
        (None: a level in between, e.g. a ramp), with the blind time after it.

        Blind time: from the capture of the first frame of the new light to the
        publication of the first detections, of a frame of the new light, that
        contain a marker that frame shows (the camera's ground truth). It is
        what a pilot waiting for a position fix feels; ``band_ms`` is the part
        the light monitor and the band's dwell take before anything is decided.
        ``band_of`` names the band of a class of light (for ``bands_between``).
        """
        with self._lock:
            frames = sorted(self.frames.items())
            found = sorted(self.found)
            decisions = sorted(((d.trigger_time, d) for d in self.decisions if d.trigger_time is not None),
                               key=lambda timed: timed[0])
            reflexes = list(self.reflexes)
        steps: list[LightStep] = []
        previous: str | None = None
        between = False
        for seq, (t, level, _) in frames:
            kind = classify(level) if level is not None else None
            if kind is None:
                between = level is not None
                continue
            if previous is not None and kind != previous:
                steps.append(LightStep(kind=f"{previous}->{kind}", frame_seq=seq, frame_time=t,
                                       seen_seq=None, blind_ms=None, band_ms=None, between=between))
            previous, between = kind, False
        truth = {seq: ids for seq, (_, _, ids) in frames}
        for i, step in enumerate(steps):
            end = steps[i + 1].frame_seq if i + 1 < len(steps) else None
            for seq, published, ids in found:
                if seq < step.frame_seq or (end is not None and seq >= end):
                    continue
                if ids & truth.get(seq, frozenset()):
                    step.seen_seq, step.blind_ms = seq, (published - step.frame_time) * 1000.0
                    break
            until = steps[i + 1].frame_time if i + 1 < len(steps) else float("inf")
            sides = {band_of(side) for side in step.kind.split("->")}
            since = step.frame_time - 0.1  # the frame exposed during the step comes a frame before it
            step.bands_between = sum(1 for r in reflexes if since <= r.frame_time < until and r.band not in sides)
            after = next(((t, d) for t, d in decisions if step.frame_time <= t < until
                          and d.kind not in (TriggerKind.STARTUP, TriggerKind.HOST_BACK)), None)
            if after is not None:
                trigger_time, decision = after
                step.band_ms = (trigger_time - step.frame_time) * 1000.0
                step.change = decision.change or decision.outcome.split(":")[0]
        return steps

    def pipeline_ms(self) -> list[float]:
        """Capture -> publication of detections with a marker the frame shows, every such frame: what any
        blind time is bounded by from below (camera, transport, decoding, detection)."""
        with self._lock:
            truth = {seq: (t, ids) for seq, (t, _, ids) in self.frames.items()}
            found = list(self.found)
        return [(published - truth[seq][0]) * 1000.0 for seq, published, ids in found
                if seq in truth and ids & truth[seq][1]]

    def reflex_frames(self, steps: list[LightStep]) -> list[int]:
        """Per step, frames from its first frame to the frame whose evidence made the detector's first reflex
        after it (0: the step's own frame); steps without a reflex are left out."""
        with self._lock:
            seqs = sorted(r.seq for r in self.reflexes)
        out = []
        for i, step in enumerate(steps):
            end = steps[i + 1].frame_seq if i + 1 < len(steps) else None
            first = next((q for q in seqs if q >= step.frame_seq and (end is None or q < end)), None)
            if first is not None:
                out.append(first - step.frame_seq)
        return out

    def baseline_loss(self) -> tuple[int, int]:
        """(frames no detector answered, frames) while a detector ran, outside migrations."""
        with self._lock:
            if not self.detections:
                return 0, 0
            first = self.detections[0][0]
            frames = [(t, seq) for t, _, seq in self.light if t >= first + 1.0]
            done = set(self._detected_seqs)
            windows = [(d.time - (d.latency_ms or 0) / 1000.0 - 1.0, d.time + 1.0) for d in self.decisions]
        steady = [seq for t, seq in frames if not any(a <= t < b for a, b in windows)]
        return sum(1 for seq in steady if seq not in done), len(steady)

    def summary_rows(self) -> list[dict[str, Any]]:
        self.attribute_losses()
        return [{
            "t_s": round(d.time - self.t0, 1), "trigger": d.trigger[:44], "chosen": f"{d.config}@{d.host}",
            "outcome": d.outcome.split(":")[0].split(";")[0], "latency_ms": d.latency_ms, "frames_lost": d.frames_lost,
            "busy_drops": d.frames_dropped,
        } for d in self.decisions]

    def plot(self, path: Path, bands: list[tuple[str, float, float]] | None = None) -> Path:
        """Draw the timeline PNG: illumination, configuration, host, detection rate, free memory."""
        from kgadapt.shared.extras import require

        matplotlib = require("matplotlib", extra="plots", what="the demo's timeline plot")
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        with self._lock:
            light = list(self.light)
            dets = list(self.detections)
            memory = {h: list(v) for h, v in self.memory.items()}
            decisions = list(self.decisions)
            marks = list(self.marks)
            reflexes = list(self.reflexes)
        t0 = self.t0
        fig, axes = plt.subplots(5, 1, figsize=(11, 10), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1, 1, 1.3, 1.5]})
        ax = axes[0]
        ax.plot([t - t0 for t, _, _ in light], [v for _, v, _ in light], color="goldenrod", lw=1.2)
        for name, lo, hi in bands or []:
            ax.axhline(lo, color="grey", lw=0.5, ls=":")
            ax.text(0.2, (lo + min(hi, 130)) / 2, name, fontsize=8, color="grey", va="center")
        ax.set_ylabel("illumination\n(mean level)")
        ax.set_ylim(0, 135)
        configs = sorted({c for _, _, c, _, _, _ in dets})
        hosts = sorted({h for _, _, _, h, _, _ in dets})
        axes[1].scatter([t - t0 for t, *_ in dets], [configs.index(c) for _, _, c, _, _, _ in dets], s=2)
        axes[1].set_yticks(range(len(configs)), [c.replace("marker_detection_", "") for c in configs])
        axes[1].set_ylabel("configuration")
        axes[2].scatter([t - t0 for t, *_ in dets], [hosts.index(h) for _, _, _, h, _, _ in dets], s=2, color="purple")
        axes[2].set_yticks(range(len(hosts)), hosts)
        axes[2].set_ylabel("host")
        times = [t for t, _, _ in light]
        if times:
            end = times[-1]
            step, xs, ys = 0.5, [], []
            t = times[0]
            while t < end:
                rate = self.detection_rate(t, t + 1.0)
                if rate is not None:
                    xs.append(t + 0.5 - t0)
                    ys.append(rate * 100)
                t += step
            axes[3].plot(xs, ys, color="green")
        axes[3].set_ylabel("frames with\nmarkers (%)")
        axes[3].set_ylim(-5, 105)
        # Hosts differ by an order of magnitude: the onboard host on the left axis, the others on the right.
        other = axes[4].twinx()
        for i, (host, values) in enumerate(sorted(memory.items())):
            target = axes[4] if host == "onboard" else other
            target.plot([t - t0 for t, _ in values], [v for _, v in values], label=host, color=f"C{i}")
            target.set_ylabel(f"free MiB\n{host}" if host == "onboard" else f"free MiB, {host}", color=f"C{i}")
        axes[4].set_xlabel("seconds")
        for d in decisions:
            for a in axes:
                a.axvline(d.time - t0, color="red", lw=0.6, alpha=0.6)
        for seen in reflexes:
            for a in axes:
                a.axvline(seen.time - t0, color="blue", lw=0.6, ls=":", alpha=0.8)
            axes[1].text(seen.time - t0, 0, f" reflex: {seen.band}", fontsize=7, color="blue", rotation=90, va="bottom")
        for t, text in marks:
            for a in axes:
                a.axvline(t - t0, color="black", lw=0.8, ls="--", alpha=0.7)
            axes[4].text(t - t0, axes[4].get_ylim()[1] * 0.9, " " + text, fontsize=7)
        fig.suptitle("kgadapt demo: illumination, chosen detector, host, detection rate, free memory "
                     "(red: adaptation decisions; blue dotted: the detector's reflexes)", fontsize=10)
        fig.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=90)
        plt.close(fig)
        return path

