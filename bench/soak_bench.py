"""``kgadapt bench soak --minutes M``: the whole robot under random faults, invariants checked every second.

The robot runs across network namespaces (``onboard``: knowledge service,
onboard agent, fake flight controller hovering; ``remote``: the remote agent;
``robot2``: the observer, :func:`kgadapt.bench.reliability_bench.probe_main`), every
message through the service's router. The scenario camera loops through the
bands (day, dusk, dark, flicker: a light step every ``band_s`` seconds), so
band changes and migrations happen all along.

A fault injector (seeded: ``--seed``; every fault logged with its start and
end) waits ``gap`` seconds (uniform in ``--gap``), then does one of:

``store_kill``      kill -9 of the embedded FalkorDB server (the service's store restarts it)
``remote_kill``     kill -9 of the remote agent (and its detectors), restarted 1 s later as systemd would
``onboard_kill``    kill -9 of the onboard agent (and its detectors), restarted 1 s later
``detector_kill``   kill -9 of a running detector process
``link_cut``        the remote host's link down for 1-10 s
``squeeze``         the onboard host's monitor reserves memory for 10-25 s (the detector must move off and back)
``forged_status``   forged host statuses on this robot's own keys: remote roomy, onboard full, a stale replay

Every second the bench checks (``violations`` in the report, each with its time):

``two_detectors``   more than one detector's detections reach the observer for longer than ``--handover`` s
``no_detections``   no detections for longer than ``--gap-bound`` s outside a fault's explained window
``graph_disagrees`` open detector ProcessProfiles and running detector processes differ for longer than ``--graph-bound`` s
``acked_lost``      an acknowledged knowledge write (one a second, through this robot's write API) is missing
``forged_move``     a decision places the detector on the remote host while no squeeze explains it
and records RSS and threads of the long-running processes (service, agents, fake FC, store) every 5 s:
growth after the warm-up is in ``memory``. Results: ``bench/results/soak.json`` and ``soak.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from kgadapt.shared.errors import ConfigError, KgadaptError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.resources import results_dir

RESULTS = results_dir()
ROBOT = DEFAULT_ROBOT
FAULTS = ("store_kill", "remote_kill", "onboard_kill", "detector_kill", "link_cut", "squeeze", "forged_status")
# After a fault ends, detections may stay away this long and still be explained by it (agent restarts
# with a new detector, failover after a cut): measured bounds, reported beside the figures.
EXPLAINS_S = {"store_kill": 10.0, "remote_kill": 20.0, "onboard_kill": 30.0, "detector_kill": 20.0,
              "link_cut": 20.0, "squeeze": 15.0, "forged_status": 0.0}
LONG_RUNNING = ("service", "remote", "fake-fc", "onboard")
LIFE_WARMUP_S = 60.0  # a restarted process's start-up, left out of its memory growth


@dataclass(frozen=True, kw_only=True)
class SoakSettings:
    minutes: float
    seed: int = 0
    gap: tuple[float, float] = (5.0, 15.0)
    band_s: float = 40.0
    handover_s: float = 5.0  # two detectors may both detect this long during a make-before-break change
    gap_bound_s: float = 3.0  # detections may pause this long outside faults (a migration's own gap)
    graph_bound_s: float = 20.0  # profiles and processes may disagree this long (writes retried after a store kill)
    warmup_s: float = 300.0
    subnet: str = "10.213.9"
    standby: bool = False  # the onboard agent keeps a warm standby (an idle second detector process)

    def __post_init__(self) -> None:
        if not self.minutes > 0:
            raise ConfigError(f"--minutes {self.minutes!r}: use a positive number")
        low, high = self.gap
        if not 0 < low <= high:
            raise ConfigError(f"--gap {self.gap!r}: use 0 < low <= high")


def scenario(band_s: float) -> dict[str, Any]:
    """Light looping through day, dusk, dark and flicker, a step every ``band_s`` seconds (2 s ramps)."""
    levels = [(120.0, 0.0, 0.0), (16.0, 0.0, 0.0), (5.0, 0.0, 0.0), (60.0, 0.6, 7.0)]
    points, t = [], 0.0
    for level, depth, hz in levels:
        points += [[t, level, depth, hz], [t + band_s - 2.0, level, depth, hz]]
        t += band_s
    points.append([t, *levels[0]])
    return {"points": points, "noise": 2.0, "gradient": 0.2, "loop": True}


class Soak:
    """The robot, the fault injector and the invariant checker; ``run()`` returns the report."""

    def __init__(self, settings: SoakSettings, workdir: Path, say: Callable[[str], None]) -> None:
        self.settings = settings
        self.workdir = workdir
        self.say = say
        self.rng = random.Random(settings.seed)
        self.faults: list[dict[str, Any]] = []
        self.violations: list[dict[str, Any]] = []
        self.samples: list[dict[str, Any]] = []
        self.memory: list[dict[str, Any]] = []
        self.acked: list[str] = []
        self.write_failures = 0
        self.handovers: list[float] = []
        self.squeezed_until = 0.0
        self.forged_until = 0.0
        self._stop = threading.Event()
        self.robot: Any = None

    # -- the robot ------------------------------------------------------------------

    def start(self) -> None:
        from kgadapt.bench.reliability_bench import RobotOnHosts, RobotSettings

        s = self.settings
        # The reliability bench's robot, with changing light and the fake flight controller.
        self.robot = RobotOnHosts(RobotSettings(workdir=self.workdir, profile=scenario(s.band_s), fps=15.0,
                                                prefer="onboard-first", subnet=s.subnet, fake_fc=True,
                                                standby=s.standby))
        self.network, self.cluster = self.robot.network, self.robot.cluster
        self.robot.start(timeout=60.0)  # stops what it started when it fails
        self.probe = self.robot.probe

    def stop(self) -> None:
        self.robot.stop()

    def detector_processes(self) -> list[Any]:
        """Detector programs in our namespaces (psutil, not the agents' word): pid, ppid, host, instance;
        the idle pool members the agents' launchers hold (their deployers name them) are no detectors yet."""
        return self.robot.detector_processes()

    def store_pid(self) -> int | None:
        try:
            return int(json.loads((self.workdir / "store" / "server.json").read_text())["pid"])
        except (OSError, ValueError, KeyError):
            return None

    # -- faults ---------------------------------------------------------------------

    def inject(self) -> None:
        s = self.settings
        while not self._stop.wait(self.rng.uniform(*s.gap)):
            kind = self.rng.choice(FAULTS)
            record: dict[str, Any] = {"kind": kind, "start": time.time()}
            self._current_fault_start = record["start"]
            try:
                record.update(getattr(self, f"_fault_{kind}")() or {})
            except Exception as exc:  # a fault that could not be injected is logged, not the end of the soak
                record["error"] = f"{type(exc).__name__}: {exc}"[:300]
            record["end"] = time.time()
            self.faults.append(record)
            self._current_fault_start = None
            details = json.dumps({k: v for k, v in record.items() if k not in ("kind", "start", "end")})
            self.say(f"fault {len(self.faults)} {kind} {details[:160]}")

    def _fault_store_kill(self) -> dict[str, Any]:
        pid = self.store_pid()
        if pid is None:
            raise KgadaptError("no store server pid")
        os.kill(pid, signal.SIGKILL)
        return {"pid": pid}

    def _restart(self, name: str) -> dict[str, Any]:
        self.cluster.kill(name, signal.SIGKILL)
        time.sleep(1.0)  # RestartSec=1 of the units
        started = time.time()
        self.cluster.respawn(name)
        return {"restart_s": round(time.time() - started, 2)}

    def _fault_remote_kill(self) -> dict[str, Any]:
        return self._restart("remote")

    def _fault_onboard_kill(self) -> dict[str, Any]:
        return self._restart("onboard")

    def _fault_detector_kill(self) -> dict[str, Any]:
        procs = self.detector_processes()
        if not procs:
            raise KgadaptError("no detector process to kill")
        victim = self.rng.choice(procs)
        pid, host, instance = victim.pid, victim.host, victim.instance
        os.kill(pid, signal.SIGKILL)
        return {"pid": pid, "host": host, "instance": instance}

    def _fault_link_cut(self) -> dict[str, Any]:
        cut = round(self.rng.uniform(1.0, 10.0), 1)
        self.network.cut("remote")
        try:
            self._stop.wait(cut)
        finally:
            self.network.heal("remote")
        return {"cut_s": cut}

    def _fault_squeeze(self) -> dict[str, Any]:
        hold = round(self.rng.uniform(10.0, 25.0), 1)
        self.squeezed_until = time.time() + hold + 60.0  # until lifted (set below)
        status = self.probe.request("squeeze", host="onboard", reserve_mb=650.0, wait=10)
        try:
            self._stop.wait(hold)
        finally:
            self.probe.request("squeeze", host="onboard", reserve_mb=0.0, wait=10)
            self.squeezed_until = time.time()
        return {"hold_s": hold, "free_mb": status.get("memory_free_mb")}

    def _fault_forged_status(self) -> dict[str, Any]:
        now = time.time()
        forged = [
            {"host": "remote", "time": now, "memory_total_mb": 60000.0, "memory_free_mb": 60000.0, "cpu_load": 0.0},
            {"host": "onboard", "time": now, "memory_total_mb": 700.0, "memory_free_mb": 0.0, "cpu_load": 0.0},
            {"host": "onboard", "time": now - 120.0, "memory_total_mb": 700.0, "memory_free_mb": 0.0,
             "cpu_load": 0.0},
        ]
        self.forged_until = now + 10.0
        sent = 0
        for _ in range(3):
            sent += self.probe.request("forge", statuses=forged, wait=10)
            self._stop.wait(0.7)
        return {"sent": sent}

    # -- invariants -----------------------------------------------------------------

    def explained(self, t: float) -> bool:
        """Is a missing detection at time ``t`` explained by a fault (running, or just ended)?"""
        for f in reversed(self.faults):
            if f["start"] - 1.0 <= t <= f["end"] + EXPLAINS_S[f["kind"]]:
                return True
        current = getattr(self, "_current_fault_start", None)
        return current is not None and t >= current - 1.0

    def violate(self, kind: str, t: float, **detail: Any) -> None:
        self.violations.append({"kind": kind, "t": t, **detail})
        self.say(f"VIOLATION {kind} at +{t - self.t0:.0f} s: {json.dumps(detail, default=str)[:200]}")

    def check(self) -> None:
        s = self.settings
        now = time.time()
        sample: dict[str, Any] = {"t": now}
        try:
            active = self.probe.request("active", window=1.0, wait=5)
        except KgadaptError as exc:
            sample["error"] = str(exc)[:200]
            self.samples.append(sample)
            return
        procs = self.detector_processes()
        sample.update(detecting=sorted(active), processes=sorted(p.instance for p in procs),
                      hosts=sorted({v["host"] for v in active.values()}))
        # One detector counts, outside a bounded handover.
        if len(active) > 1:
            self._two_since = getattr(self, "_two_since", None) or now
        elif getattr(self, "_two_since", None):
            self.handovers.append(now - self._two_since)
            if now - self._two_since > s.handover_s:
                self.violate("two_detectors", self._two_since, seconds=round(now - self._two_since, 1))
            self._two_since = None
        # Detections flow unless a fault explains their absence.
        if not active:
            self._dark_since = getattr(self, "_dark_since", None) or now
        else:
            dark = getattr(self, "_dark_since", None)
            if dark is not None and now - dark > s.gap_bound_s and not (self.explained(dark) or self.explained(now)):
                self.violate("no_detections", dark, seconds=round(now - dark, 1))
            self._dark_since = None
        # Graph against processes (every 5 s: a query through the router).
        if now - getattr(self, "_graph_checked", 0.0) >= 5.0:
            self._graph_checked = now
            try:
                rows = self.probe.request("cypher", wait=10, cypher=(
                    "MATCH (r:ProcessProfile) WHERE r.end_time IS NULL AND r.config STARTS WITH 'marker_detection' "
                    "RETURN r.instance AS instance, r.host AS host"), params={})
                open_profiles = {r["instance"] for r in rows}
                running = {p.instance for p in self.detector_processes()}
                differ = sorted(open_profiles ^ running)
                sample["graph_differs"] = differ
                if differ:
                    self._differ_since = getattr(self, "_differ_since", None) or now
                    if now - self._differ_since > s.graph_bound_s and not getattr(self, "_differ_reported", False):
                        self._differ_reported = True
                        self.violate("graph_disagrees", self._differ_since, open_not_running=sorted(open_profiles - running),
                                     running_not_open=sorted(running - open_profiles))
                else:
                    self._differ_since, self._differ_reported = None, False
            except KgadaptError as exc:
                sample["graph_error"] = str(exc)[:120]
        self.samples.append(sample)

    def writer(self) -> None:
        """One acknowledged write a second: a decision node named soak-ack-N."""
        n = 0
        while not self._stop.wait(1.0):
            name = f"soak-ack-{n}"
            n += 1
            try:
                self.probe.request("write", verb="decision", wait=10, params={
                    "name": name, "time": time.time(), "trigger": "soak acknowledged write"})
                self.acked.append(name)
            except KgadaptError:
                self.write_failures += 1  # not acknowledged: may or may not be there

    def lost_writes(self) -> list[str]:
        found: set[str] = set()
        for i in range(0, len(self.acked), 500):  # another robot's answers are capped at 1000 rows
            for attempt in range(3):
                # The final check must not throw the whole run away: a loaded machine (load 20) once took
                # more than the client's default 2 s to answer it.
                try:
                    rows = self.probe.request("cypher", wait=40, timeout=10.0, cypher=(
                        "MATCH (d:AdaptationDecision) WHERE d.name IN $names RETURN d.name AS name"),
                        params={"names": self.acked[i:i + 500]})
                    break
                except KgadaptError as exc:
                    self.say(f"checking acknowledged writes {i}-{i + 499} (attempt {attempt + 1}): {exc}")
                    if attempt == 2:
                        raise
            found |= {r["name"] for r in rows}
        return [n for n in self.acked if n not in found]

    def measure_memory(self) -> None:
        import psutil

        while not self._stop.wait(5.0):
            now = time.time()
            pids = {n: c.process.pid for n, c in list(self.cluster.children.items()) if n in LONG_RUNNING}
            store = self.store_pid()
            if store:
                pids["store"] = store
            for name, pid in pids.items():
                try:
                    p = psutil.Process(pid)
                    self.memory.append({"t": now, "name": name, "pid": pid, "rss_mb": round(p.memory_info().rss / 2**20, 1),
                                        "threads": p.num_threads()})
                except psutil.Error:
                    continue
            try:
                size = sum(f.stat().st_size for f in (self.workdir / "store").rglob("*") if f.is_file())
                self.memory.append({"t": now, "name": "store_files", "bytes": size, "acked": len(self.acked)})
            except OSError:
                pass

    def watch_decisions(self) -> None:
        """A decision placing the detector on the remote host with no squeeze to explain it is a forged move."""
        seen = 0
        while not self._stop.wait(0.5):
            events = self.probe.events[seen:]
            seen += len(events)
            for e in events:
                if e.get("ev") != "decision" or e.get("host") != "remote":
                    continue
                if not str(e.get("outcome", "")).startswith(("migrated", "started")):
                    continue
                squeezed = e["t"] <= self.squeezed_until + 5.0
                if not squeezed:
                    onboard_down = any(f["kind"] in ("onboard_kill",) and f["start"] - 1 <= e["t"] <= f["end"] + 30
                                       for f in self.faults)
                    self.violate("forged_move" if e["t"] <= self.forged_until else "unexplained_remote_placement",
                                 e["t"], trigger=e.get("trigger"), outcome=str(e.get("outcome"))[:120],
                                 onboard_restarting=onboard_down)

    # -- the run ----------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        s = self.settings
        self.start()
        self.t0 = time.time()
        self.say(f"robot up in namespaces {self.network.settings.tag}; soaking {s.minutes:g} min, seed {s.seed}")
        threads = [threading.Thread(target=t, name=t.__name__, daemon=True)
                   for t in (self.inject, self.writer, self.measure_memory, self.watch_decisions)]
        for t in threads:
            t.start()
        end = self.t0 + s.minutes * 60.0
        try:
            while time.time() < end:
                tick = time.time()
                self.check()
                time.sleep(max(0.0, 1.0 - (time.time() - tick)))
            self._stop.set()
            for t in threads:
                t.join(40)
            time.sleep(2.0)
            lost = self.lost_writes()
            for name in lost:
                self.violate("acked_lost", time.time(), name=name)
            processes_alive = {n: c.process.poll() is None for n, c in self.cluster.children.items()}
        finally:
            self._stop.set()
            self.stop()
        return self.report(lost, processes_alive)

    def report(self, lost: list[str], alive: dict[str, bool]) -> dict[str, Any]:
        from kgadapt.bench.stats import machine_info, percentile

        s = self.settings
        counts: dict[str, int] = {}
        for f in self.faults:
            counts[f["kind"]] = counts.get(f["kind"], 0) + 1
        kinds: dict[str, int] = {}
        for v in self.violations:
            kinds[v["kind"]] = kinds.get(v["kind"], 0) + 1
        warm = self.t0 + min(s.warmup_s, s.minutes * 60.0 / 3.0)
        growth = {}
        for name in (*LONG_RUNNING, "store"):
            by_pid: dict[int, list[dict[str, Any]]] = {}
            for m in self.memory:
                if m["name"] == name and m["rss_mb"] > 0:  # 0: a killed process not yet reaped
                    by_pid.setdefault(m["pid"], []).append(m)
            # A process restarted by a fault has its own warm-up: growth counts from LIFE_WARMUP_S after its
            # start (imports, session, its detectors), not from its first sample.
            by_pid = {pid: kept for pid, life in by_pid.items()
                      if (kept := [m for m in life if m["t"] >= max(warm, life[0]["t"] + LIFE_WARMUP_S)])}
            if not by_pid:
                continue
            pid, life = max(by_pid.items(), key=lambda kv: kv[1][-1]["t"] - kv[1][0]["t"])  # its longest life after warm-up
            first, last = life[0], life[-1]
            growth[name] = {"pid": pid, "seconds": round(last["t"] - first["t"]), "rss_mb_first": first["rss_mb"],
                            "rss_mb_last": last["rss_mb"], "rss_mb_max": max(m["rss_mb"] for m in life),
                            "rss_growth_pct": round(100.0 * (last["rss_mb"] / first["rss_mb"] - 1.0), 1),
                            "threads_first": first["threads"], "threads_last": last["threads"],
                            "threads_max": max(m["threads"] for m in life), "lives": len(by_pid)}
        files = [m for m in self.memory if m["name"] == "store_files"]
        return {
            "bench": "soak", "machine": machine_info(), "time": self.t0,
            "settings": {k: v for k, v in s.__dict__.items()},
            "explains_s": EXPLAINS_S,
            "duration_s": round(time.time() - self.t0),
            "faults": {"total": len(self.faults), "by_kind": counts,
                       "failed_to_inject": sum(1 for f in self.faults if "error" in f), "log": self.faults},
            "violations": {"total": len(self.violations), "by_kind": kinds, "log": self.violations},
            "writes": {"acked": len(self.acked), "lost": len(lost), "not_acked": self.write_failures},
            "handover_s": {"count": len(self.handovers),
                           "p50": round(percentile(self.handovers, 50), 2) if self.handovers else None,
                           "max": round(max(self.handovers), 2) if self.handovers else None},
            "memory": growth,
            "store_files": {"first_bytes": files[0]["bytes"] if files else None,
                            "last_bytes": files[-1]["bytes"] if files else None,
                            "acked_writes": len(self.acked)},
            "processes_alive_at_end": alive,
            "samples": self.samples,
            "memory_samples": self.memory,
        }


def plot(report: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = report["time"]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(14, 7), sharex=True)
    colors = dict(zip(FAULTS, plt.cm.tab10.colors))
    for f in report["faults"]["log"]:
        ax1.axvspan((f["start"] - t0) / 60, (f["end"] - t0) / 60 + 0.02, 0.55, 1.0, color=colors[f["kind"]], alpha=0.6)
    xs = [(s["t"] - t0) / 60 for s in report["samples"] if "detecting" in s]
    ax1.step(xs, [len(s["detecting"]) for s in report["samples"] if "detecting" in s], where="post", color="k",
             lw=0.8, label="detectors detecting")
    for v in report["violations"]["log"]:
        ax1.axvline((v["t"] - t0) / 60, color="red", lw=1.2)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colors[k], alpha=0.6) for k in FAULTS]
    ax1.legend(handles + [plt.Line2D([], [], color="k"), plt.Line2D([], [], color="red")],
               [*FAULTS, "detectors detecting", "violation"], loc="upper left", fontsize=7, ncol=5)
    ax1.set_ylim(0, 3.5)
    ax1.set_ylabel("faults / detectors")
    ax1.set_title(f"soak: {report['duration_s'] / 60:.0f} min, {report['faults']['total']} faults, "
                  f"{report['violations']['total']} violations, {report['writes']['acked']} acknowledged writes "
                  f"({report['writes']['lost']} lost)")
    for name in (*LONG_RUNNING, "store"):
        rows = [m for m in report["memory_samples"] if m["name"] == name]
        if rows:
            ax2.plot([(m["t"] - t0) / 60 for m in rows], [m["rss_mb"] for m in rows], ".", ms=2, label=name)
    ax2.set_ylabel("RSS (MiB)")
    ax2.set_xlabel("minutes")
    ax2.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def register(bench_subparsers: Any) -> None:
    parser = bench_subparsers.add_parser(
        "soak", help="the whole robot under random seeded faults for M minutes, invariants checked every second",
        description="Run the robot across network namespaces with a seeded fault injector (kill -9 of the store, "
        "agents and detectors, link cuts, memory squeezes, forged statuses) and check invariants every second. "
        "Writes bench/results/soak.json and soak.png (or --out).")
    parser.add_argument("--minutes", type=float, default=3.0, help="how long (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault injector (default 0)")
    parser.add_argument("--gap", type=float, nargs=2, default=(5.0, 15.0), metavar=("LOW", "HIGH"),
                        help="seconds between faults, uniform (default 5 15)")
    parser.add_argument("--band", type=float, default=40.0, metavar="S", help="seconds per light band (default 40)")
    parser.add_argument("--out", default=str(RESULTS / "soak.json"), help="report file (the PNG goes beside it)")
    parser.add_argument("--workdir", default=None, help="logs and store (default: a temporary directory)")
    parser.add_argument("--standby", action="store_true",
                        help="the onboard agent keeps a warm standby (an idle detector process for the next band)")
    parser.add_argument("--quiet", action="store_true")
    parser.set_defaults(func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    from kgadapt.operator.cluster import HostNetwork

    reason = HostNetwork.unavailable_reason()
    if reason:
        raise ConfigError(f"the soak needs network namespaces: {reason}")
    settings = SoakSettings(minutes=args.minutes, seed=args.seed, gap=tuple(args.gap), band_s=args.band,
                            standby=args.standby)
    keep = args.workdir is not None
    workdir = Path(args.workdir) if keep else Path(tempfile.mkdtemp(prefix="kgadapt-soak-"))

    def say(line: str) -> None:
        if not args.quiet:
            print(line, flush=True)

    try:
        report = Soak(settings, workdir, say).run()
    finally:
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=str))
    plot(report, out.with_suffix(".png"))
    print(f"soak {report['duration_s']} s: {report['faults']['total']} faults {report['faults']['by_kind']}, "
          f"{report['violations']['total']} violations {report['violations']['by_kind']}, "
          f"{report['writes']['acked']} acknowledged writes, {report['writes']['lost']} lost; wrote {out}")
    return 0
