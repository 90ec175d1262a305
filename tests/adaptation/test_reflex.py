"""The detector's reflexes end to end: real service (FalkorDB), agents, camera process, detectors, Zenoh.

A sudden day -> dark step is answered by the running detector itself, within
five of the frames it processes, while the adaptation manager's process is
stopped (SIGSTOP); once resumed, the manager records the change as a
``reflex`` decision and ``why`` shows it. A steady scene makes no reflex, and
the change loses no frame.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kgadapt.operator.cluster import ClusterSettings, WatchedRobot, write_profile
from kgadapt.shared import keys, messages
from kgadapt.shared.proc_stat import state_of

pytestmark = pytest.mark.slow

STEP_S = 30.0  # scenario second of the step day -> dark: after the robot's start, also on a loaded machine
STEP_RAMP_S = 1e-6  # a step: a ramp of 1 ms let one frame in 33 (at 30 fps) fall inside it and read dusk


class Run(WatchedRobot):
    def __init__(self, tmp_path: Path, points: list[list[float]], **settings) -> None:
        settings.setdefault("calibrate", False)
        super().__init__(ClusterSettings(workdir=tmp_path / "run", profile=write_profile(tmp_path / "profile.json", points),
                                         log_level="INFO", camera_process=True, fake_fc=False, **settings))
        self.reflexes: list[dict] = []

    def __enter__(self) -> "Run":
        super().__enter__()
        self.session.declare_subscriber(keys.detector_reflex(self.cluster.settings.robot), self._on_reflex)
        return self

    def _on_reflex(self, sample) -> None:
        m = messages.decode(sample.payload.to_bytes(), "reflex")
        if not m.get("again"):  # each reflex once; its repeats (for receivers that lost it) left out
            self.reflexes.append(m)

    def wait_for(self, predicate, timeout: float, what: str):
        value = self.wait(predicate, timeout, interval=0.05)
        if value:
            return value
        logs = {n: c.tail(12) for n, c in self.cluster.children.items()}
        raise AssertionError(f"timed out waiting for {what}; decisions {self.recorder.decisions}; logs {logs}")


def first_frame_of(run: Run, predicate) -> int | None:
    with run.recorder._lock:  # noqa: SLF001 - the test reads the recorder's own record
        frames = sorted(run.recorder.frames.items())
    return next((seq for seq, (_, level, _) in frames if level is not None and predicate(level)), None)


def answered_after(run: Run, step_seq: int) -> list[tuple[int, bool]]:
    """(seq, found a marker the frame shows) of every frame the detector processed from ``step_seq`` on."""
    with run.recorder._lock:  # noqa: SLF001
        processed = sorted({seq for _, _, _, _, seq, _ in run.recorder.detections if seq >= step_seq})
        found = {seq: ids for seq, _, ids in run.recorder.found}
        truth = {seq: ids for seq, (_, _, ids) in run.recorder.frames.items()}
    return [(seq, bool(found.get(seq, frozenset()) & truth.get(seq, frozenset()))) for seq in processed]


def test_a_sudden_step_is_answered_by_the_detector_within_five_frames_while_the_manager_is_stopped(tmp_path):
    points = [[0, 120], [STEP_S, 120], [STEP_S + STEP_RAMP_S, 5], [120, 5]]
    with Run(tmp_path, points) as run:
        startup = run.wait_for(lambda: next((d for d in run.recorder.decisions if d.kind == "startup"), None), 30,
                               "the first detector")
        assert startup.config == "marker_detection_day"
        # Markers seen in the day before the step; then the manager's process is stopped.
        run.wait_for(lambda: len(run.recorder.found) > 30, 15, "detections in the day")
        onboard = run.cluster.children["onboard"]
        assert first_frame_of(run, lambda level: level < 60) is None, "the step came before the manager was stopped"
        os.kill(onboard.pid, signal.SIGSTOP)  # the agent only: its detector runs on as a process of its own
        stopped_at = time.time()
        try:
            step = run.wait_for(lambda: first_frame_of(run, lambda level: level < 60), STEP_S + 30, "the step")
            answers = run.wait_for(lambda: (a := answered_after(run, step)) and len(a) >= 8 and a, 20,
                                   "eight frames processed after the step")
            still_stopped = onboard.process.poll() is None and state_of(onboard.pid) == "T"
        finally:
            os.kill(onboard.pid, signal.SIGCONT)
        resumed_at = time.time()
        assert still_stopped, "the manager's process was not stopped during the step"
        first_hit = next((i for i, (_, hit) in enumerate(answers) if hit), None)
        assert first_hit is not None and first_hit < 5, (
            f"the detector found the markers first on its {first_hit}th frame after the step; answers {answers[:12]}; "
            f"reflexes {run.reflexes}")
        assert [r["evidence"] for r in run.reflexes] == ["light"], run.reflexes
        reflex = run.reflexes[0]
        assert (reflex["previous"], reflex["config"], reflex["band"]) == (
            "marker_detection_day", "marker_detection_dark", "dark")
        assert stopped_at < reflex["time"] < resumed_at

        # (b) Resumed, the manager records what the detector did, with its inputs, and does not fight it.
        decision = run.wait_for(lambda: next((d for d in run.recorder.decisions if d.kind == "reflex"), None), 20,
                                "the manager's reflex decision")
        assert (decision.config, decision.host, decision.change) == ("marker_detection_dark", "onboard", "reflex")
        assert decision.outcome.startswith("reconfigured by reflex"), decision
        assert decision.instance == startup.instance
        time.sleep(3.0)  # past the smoothed light's hold: the manager's own band decision would come now
        why = subprocess.run([sys.executable, "-m", "kgadapt", "why", "--json", "--connect", run.cluster.endpoint],
                             capture_output=True, text=True, timeout=30)
        configs = {c for t, _, c, _, _, _ in run.recorder.detections if t > time.time() - 1.0}
    assert why.returncode == 0, why.stderr
    explained = json.loads(why.stdout)
    assert explained["running"]["config"] == "marker_detection_dark"
    # The reflex message, or (when the stopped manager's link was dropped with it) the count of
    # reflexes the detections carry, told the manager.
    assert explained["decision"]["trigger"].startswith("reflex(evidence="), explained["decision"]
    assert explained["decision"]["inputs"]["change"] == "reflex"
    assert explained["decision"]["inputs"]["trigger"]["from_band"] == "day"
    assert explained["decision"]["inputs"]["trigger"]["band"] == "dark"
    # Only the reflex changed anything: the manager's own loop agreed rather than changing it again. (Stopped
    # for seconds, the manager may find the remote host's token gone and back: nothing moves for that.)
    changes = [d for d in run.recorder.decisions if d.kind not in ("host_lost", "host_back")]
    assert [d.kind for d in changes] == ["startup", "reflex"], run.recorder.decisions
    assert all(d.outcome.startswith("kept") for d in run.recorder.decisions if d not in changes)
    assert configs == {"marker_detection_dark"}

    # (d) No frame falls between the two configurations: the frame that showed the step is the
    # first one detected with the new configuration.
    run.recorder.attribute_losses()
    assert decision.frames_lost is not None and decision.frames_lost - (decision.frames_lost_busy or 0) == 0, (
        decision.frames_lost, decision.frames_lost_busy)


def test_a_steady_scene_makes_no_reflex(tmp_path):
    # Light at the day level, and at the dusk/day edge (40 +- 3 at 0.7 Hz, inside the band's margin).
    points = [[0, 40, 0.075, 0.7], [120, 40, 0.075, 0.7]]
    with Run(tmp_path, points) as run:
        run.wait_for(lambda: next((d for d in run.recorder.decisions if d.kind == "startup"), None), 30,
                     "the first detector")
        started = time.time()
        run.wait_for(lambda: time.time() - started > 10, 12, "ten seconds of steady light")
        levels = [v for t, v, _ in run.recorder.light if t >= started]
        processed = sum(1 for t, *_ in run.recorder.detections if t >= started)
    assert max(levels) > 40 > min(levels), "the light did not cross the edge; the test proves nothing"
    assert processed > 50  # frames the detector read the light of (fewer than 300 on a loaded machine)
    assert run.reflexes == [], run.reflexes
    assert [d.kind for d in run.recorder.decisions] == ["startup"], run.recorder.decisions
