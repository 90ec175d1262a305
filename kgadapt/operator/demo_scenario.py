"""The demo scenario: the whole robot on this machine through a minute of changing light.

1. a fresh embedded store under ``var/demo``: the shipped models loaded, every
   detector configuration calibrated on the synthetic scenario;
2. knowledge service, remote agent, fake flight controller and the onboard
   agent (synthetic camera, adaptation manager) as real processes;
3. a live timeline of what changed, what was decided and how long it took,
   with a scripted memory squeeze on the onboard host during the dark phase;
4. a summary table (decisions, latencies, frames lost) and a PNG timeline.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

from kgadapt.operator.cluster import ClusterSettings, LocalCluster, WatchedRobot
from kgadapt.operator.timeline import Decision, ReflexSeen

# (scenario second, action, argument): the demo profile is dark from 26 s to 36 s.
SCRIPT = (
    (30.0, "squeeze", "onboard"),
    (47.0, "release", "onboard"),
)


def run_scenario(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.store import rows_as_table
    from kgadapt.shared.hostmonitor import parse_size_mb, squeeze

    workdir = Path(args.workdir).resolve()  # relative to where the command runs
    shutil.rmtree(workdir, ignore_errors=True)
    squeeze_mb = parse_size_mb(args.squeeze)
    settings = ClusterSettings(workdir=workdir, scenario_speed=args.speed)
    robot = WatchedRobot(settings)
    recorder, cluster = robot.recorder, robot.cluster
    say = _printer()
    say(f"kgadapt demo: the robot on this machine, {args.duration:.0f} s of day, dusk, dark, flicker, day")
    say(f"  logs, store and plots in {workdir}")

    def on_decision(d: Decision) -> None:
        latency = "" if d.latency_ms is None else f" in {d.latency_ms:.0f} ms"
        say(f"{d.time - recorder.t0:6.1f} s  {d.trigger:<46} -> {d.config}@{d.host}: {d.outcome.split(':')[0]}{latency}")

    def on_reflex(r: ReflexSeen) -> None:
        level = "" if r.level is None else f", light {r.level:.0f}"
        what = (f"{r.previous} -> {r.config} between two frames" if r.config
                else f"nothing it may take in place is for band {r.band}: asks the manager")
        say(f"{r.time - recorder.t0:6.1f} s  detector reflex ({r.evidence}{level}, band {r.band}): {what}, "
            f"{(r.time - r.frame_time) * 1000:.0f} ms after the frame's capture")

    recorder.on_decision = on_decision
    recorder.on_reflex = on_reflex
    with robot:
        session = robot.session
        say(f"  models loaded and every detector configuration calibrated in {robot.timings['prepare']:.1f} s:")
        for line in robot.prepared[-1].splitlines():
            if line.strip() and not line.startswith(("wrote", "recorded")):
                say("    " + line)
        say(f"  knowledge service, remote agent (budget {settings.remote_budget}), fake flight controller and "
            f"onboard agent (budget {settings.onboard_budget}) up in {robot.timings['start']:.1f} s; "
            f"zenoh {cluster.endpoint}")
        say("\n  time    what changed                                    what was decided")
        pending = list(SCRIPT)
        next_status = 5.0
        while (elapsed := time.time() - recorder.t0) < args.duration / args.speed:
            scenario_s = elapsed * args.speed
            while pending and scenario_s >= pending[0][0]:
                _, action, host = pending.pop(0)
                reserve = squeeze_mb if action == "squeeze" else 0.0
                status = squeeze(session, settings.robot, host, reserve)
                text = (f"squeeze {host}: {reserve:.0f} MiB reserved" if reserve
                        else f"release {host}: squeeze lifted")
                recorder.mark(text)
                say(f"{elapsed:6.1f} s  {text}, {status.memory_free_mb:.0f} MiB free now")
            if elapsed >= next_status:
                now = recorder.latest()
                free = ", ".join(f"{h} {v:.0f}" for h, v in sorted(now["free"].items()))
                rate = "-" if now["rate"] is None else f"{now['rate'] * 100:.0f} %"
                light = "-" if now["light"] is None else f"{now['light']:.0f}"
                say(f"{elapsed:6.1f} s    light {light:>3}, running {now['running']}, frames with markers "
                    f"{rate}, free MiB: {free}")
                next_status += 5.0
            time.sleep(0.05)
    codes = robot.exit_codes
    bad = {name: code for name, code in codes.items() if code not in (0, -2, 130)}
    rows = recorder.summary_rows()
    lost, steady = recorder.baseline_loss()
    say("\nSummary of adaptations")
    say(rows_as_table(rows))
    migrations = [r for r in rows if r["outcome"] in ("migrated", "reconfigured", "reconfigured by reflex")]
    in_place = sum(r["outcome"].startswith("reconfigured") for r in migrations)
    reflexes = sum(r["outcome"] == "reconfigured by reflex" for r in migrations)
    latencies = sorted(r["latency_ms"] for r in rows if r["latency_ms"] is not None)
    if latencies:
        say(f"\n{len(rows)} decisions, {len(migrations)} changes ({in_place} in place, {reflexes} of them the "
            f"detector's own reflexes, {len(migrations) - in_place} new processes); latency from trigger to the "
            f"first detection with the "
            f"new configuration: median {latencies[len(latencies) // 2]:.0f} ms, max {latencies[-1]:.0f} ms")
    say(f"frames lost in changes (between the last answer with the old configuration and the first with "
        f"the new one): {sum(r['frames_lost'] or 0 for r in migrations)}; frames dropped by busy detectors around "
        f"them: {sum(r['busy_drops'] or 0 for r in migrations)}, outside them: {lost} of {steady}")
    bands = _bands(cluster)
    steps = recorder.light_steps(_classifier(bands)) if bands else []
    if steps:
        say("\nTotal blind time after each change of the scenario's light band (first frame in the new band -> "
            "first published detections showing a marker of that frame); decided_ms: until the change was decided "
            "(the detector's reflex, or the manager's light EMA, hysteresis and dwell), beyond_ms: the rest:")
        say(rows_as_table([{"t_s": round(st.frame_time - recorder.t0, 1), "step": st.kind,
                            "blind_ms": None if st.blind_ms is None else round(st.blind_ms),
                            "decided_ms": None if st.band_ms is None else round(st.band_ms),
                            "beyond_ms": (None if st.blind_ms is None or st.band_ms is None
                                          else round(max(0.0, st.blind_ms - st.band_ms))),
                            "change": st.change} for st in steps]))
        blind = sorted(st.blind_ms for st in steps if st.blind_ms is not None)
        if blind:
            say(f"total blind time per step: median {blind[len(blind) // 2]:.0f} ms, max {blind[-1]:.0f} ms "
                f"over {len(blind)} steps" + (f" ({len(steps) - len(blind)} never saw a marker)"
                                              if len(blind) < len(steps) else ""))
    png = recorder.plot(workdir / "timeline.png", bands)
    say(f"timeline plot: {png}")
    if bad:
        say(f"processes that did not stop cleanly: {bad}")
    if args.json:
        print(json.dumps({"decisions": rows, "baseline_lost": lost, "baseline_frames": steady, "exit_codes": codes,
                          "light_steps": [vars(st) for st in steps],
                          "reflexes": [vars(r) for r in recorder.reflexes]}))
    return 1 if bad or not rows else 0


def _bands(cluster: LocalCluster) -> list[tuple[str, float, float]]:
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store

    try:
        with open_store(cluster.store_url) as store:
            rows = run_named(store, "detector_configs", {})
    except Exception:  # noqa: BLE001 - any store failure: the plot is still useful without band lines
        return []
    return sorted({(r["band"], float(r["min_level"]), float(r["max_level"])) for r in rows if r.get("band")},
                  key=lambda b: b[1])


def _classifier(bands: list[tuple[str, float, float]]) -> Callable[[float], str | None]:
    """Frame level -> the band it lies in (by the graph's band edges; the scenario's level has no flicker)."""
    def classify(level: float) -> str | None:
        return next((name for name, low, high in bands if low <= level < high), bands[-1][0] if level >= bands[-1][2]
                    else None)
    return classify


def _printer() -> Callable[[str], None]:
    def say(line: str) -> None:
        print(line, flush=True)
        sys.stdout.flush()
    return say
