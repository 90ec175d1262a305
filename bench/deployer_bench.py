"""``kgadapt bench deployer``: process start/stop latency and the output gap of a planned migration.

Three measurements, all on this machine with real processes:

1. **Supervisor** (no Zenoh): start-to-ready and stop latency of
   - a trivial C program, compiled here with ``cc`` (prints the readiness line, waits for a signal),
   - a bare Python child, ``python -c``,
   - the echo detector (Python + a Zenoh session + a subscription),
   - the real marker detector ``kgadapt.onboard.perception.detector`` (OpenCV, Zenoh, its configuration asked of
     the knowledge service),
   side by side with the paper's figures (1.6 ms start, 0.07 ms stop). *spawn* is fork+exec
   until ``Popen`` returns; *ready* is until the readiness line is read; *stop* is SIGINT until
   the exit is reaped. The two detectors again forked by the host's launcher
   (deploy/launcher.py; *spawn* is then the fork request's round trip).
2. **Deployer over Zenoh**: a ``start`` request (knowledge lookup, spawn, readiness) and a
   ``stop`` request, as the adaptation manager or ``kgadapt deploy`` sends them: on the host
   ``onboard`` with its launcher, on ``remote`` without (``--no-launcher``); beside each real
   detector's start, the time it says it took after ready to arm its reflex table (fetched and
   every candidate built, off the frame path).
3. **Planned migration** between two deployers with frames at 30 fps: frames that got no
   detections from any instance while the migration ran (target: 0), beside the same count
   over a quiet window of the same length (the baseline of frames a detector drops anyway).

With ``--onboard-cpu 0.5`` everything is measured again with this process (and so every
process it starts) in a cgroup limited to half a core (a Pi-class companion computer).

Results: ``bench/results/deployer.json`` (records as bench/stats.py writes them).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from kgadapt.bench.stats import format_table, machine_info, make_record, summarize, write_records
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.readiness import READY_TOKEN
from kgadapt.shared.resources import results_dir

log = logging.getLogger(__name__)

ROBOT = "benchbot"
DEFAULT_OUT = results_dir() / "deployer.json"
PAPER = {"start_ms": 1.6, "stop_ms": 0.07}

C_PROGRAM = r"""
#include <stdio.h>
#include <unistd.h>
/* Ready at once (the bare readiness token), then wait; SIGINT's default action ends it. */
int main(void) {
    fputs("@TOKEN@\n", stdout);
    fflush(stdout);
    for (;;) pause();
}
""".replace("@TOKEN@", READY_TOKEN)
ECHO_ARGS = ["-m", "kgadapt.sim.echo_detector", "--robot", "{robot}", "--host", "{host}", "--instance", "{instance}",
             "--config", "{config}", "--connect", "{connect}"]


def register(bench_sub: argparse._SubParsersAction) -> None:
    """Add ``kgadapt bench deployer``."""
    p = bench_sub.add_parser(
        "deployer",
        help="process start/stop latency (C, Python, detectors) and the frames lost in a planned migration",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    p.add_argument("--reps", type=int, default=30, help="starts and stops per program (default 30)")
    p.add_argument("--detector-reps", type=int, default=20,  # issue 32's targets are p50s of >= 20 trials
                   help="starts and stops of the real detector, which takes ~0.2 s each (default 20)")
    p.add_argument("--migrations", type=int, default=6, help="planned migrations per detector (default 6)")
    p.add_argument("--fps", type=float, default=30.0, help="camera frame rate during migrations (default 30)")
    p.add_argument("--skip-real-detector", action="store_true", help="only the echo detector (no OpenCV, no models)")
    p.add_argument("--onboard-cpu", type=float, metavar="CORES",
                   help="measure again inside a cgroup limited to this share of a core (cpu.cfs_quota_us, root), "
                        "e.g. 0.5")
    p.add_argument("--inside-cgroup", type=float, help=argparse.SUPPRESS)  # the limited run's own process
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"records as JSON (default {DEFAULT_OUT})")
    p.add_argument("--markdown", action="store_true", help="print the tables as Markdown (for docs/deploy.md)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.reps < 1 or args.detector_reps < 1 or args.migrations < 1:
        raise ConfigError("--reps, --detector-reps and --migrations must be at least 1")
    from kgadapt.bench.footprint import HalfCore

    if args.onboard_cpu and HalfCore.unavailable_reason():
        raise ConfigError(f"kgadapt bench deployer: --onboard-cpu: {HalfCore.unavailable_reason()}")
    with _Rig(real_detector=not args.skip_real_detector) as rig:
        records = supervisor_latencies(rig, args)
        records += deployer_latencies(rig, args)
        records += migration_gaps(rig, args)
    onboard = f"{args.inside_cgroup:g} core" if args.inside_cgroup else "unlimited"
    for record in records:
        record["onboard"] = onboard
        if args.inside_cgroup:
            record["program"] = f"{record['program']}, {onboard}"
    if args.onboard_cpu:
        # Again in a new process born inside the limited group, so are all the processes it starts
        # (moving a running process with Zenoh's threads in was refused with EINVAL here).
        with HalfCore(args.onboard_cpu) as limit, tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "limited.json"
            argv = [sys.executable, "-m", "kgadapt.bench.deployer_bench", "--reps", str(args.reps), "--detector-reps",
                    str(args.detector_reps), "--migrations", str(args.migrations), "--fps", str(args.fps),
                    "--out", str(out), "--inside-cgroup", str(args.onboard_cpu)]
            if args.skip_real_detector:
                argv.append("--skip-real-detector")
            done = subprocess.run(limit.wrap(argv), cwd=Path(__file__).resolve().parent.parent)
            if done.returncode:
                raise ConfigError(f"the run limited to {args.onboard_cpu:g} core failed (status {done.returncode})")
            records += json.loads(out.read_text())
    for record in records:
        record["machine"] = machine_info()
        record["load_average"] = round(os.getloadavg()[0], 2)
    path = write_records(args.out, records)
    print(render(records, markdown=args.markdown))
    print(f"\nresults: {path}")
    return 0


# -- the rig: knowledge service, two deployers, programs -----------------------------------


class _Rig:
    """A router with the knowledge service (shipped models + echo deployments) and two deployers."""

    def __init__(self, *, real_detector: bool) -> None:
        self.real_detector = real_detector
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> "_Rig":
        from kgadapt.deploy.client import DeployerClient
        from kgadapt.deploy.deployer import Deployer, DeployerSettings
        from kgadapt.deploy.supervisor import RestartPolicy, Supervisor, SupervisorSettings
        from kgadapt.knowledge.loader import load_models
        from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
        from kgadapt.knowledge.store import open_store
        from kgadapt.shared.resources import models
        from kgadapt.shared.session import ZenohSettings, open_session

        stack = self._stack
        self.tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="kgadapt-bench-deployer-")))
        self.c_program = compile_c_program(self.tmp)
        store = open_store(f"embedded:{self.tmp / 'store'}")
        store.setup()
        stack.callback(store.shutdown)
        if self.real_detector:
            load_models(store, [models()])
        _add_echo_deployment(store)
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        fast = {"scouting/delay": 0}
        router = open_session(ZenohSettings(mode="router", listen=(self.endpoint,), extra=fast))
        stack.callback(router.close)
        service = KnowledgeService(store, ServiceSettings(robot=ROBOT))
        service.setup(router)
        stack.callback(service.shutdown)
        self.session = open_session(ZenohSettings(mode="peer", connect=(self.endpoint,), extra=fast))
        stack.callback(self.session.close)
        self.deployers = {}
        for host in ("onboard", "remote"):
            session = open_session(ZenohSettings(mode="peer", connect=(self.endpoint,), extra=fast))
            stack.callback(session.close)
            deployer = Deployer(DeployerSettings(robot=ROBOT, host=host, connect=self.endpoint, ready_timeout=30.0,
                                                 restart=RestartPolicy(max_restarts=0), launcher=host == "onboard"))
            deployer.setup(session)
            stack.callback(deployer.shutdown)
            self.deployers[host] = deployer
        self.supervisor = Supervisor()
        self.supervisor.setup()
        stack.callback(self.supervisor.shutdown)
        self.supervisor_setpriv = None
        if shutil.which("setpriv"):
            self.supervisor_setpriv = Supervisor(SupervisorSettings(death_signal_via="setpriv"))
            self.supervisor_setpriv.setup()
            stack.callback(self.supervisor_setpriv.shutdown)
        self.supervisor_launcher = Supervisor(SupervisorSettings(launcher=True))
        self.supervisor_launcher.setup()
        stack.callback(self.supervisor_launcher.shutdown)
        for supervisor in (self.supervisor_launcher, self.deployers["onboard"].supervisor):
            if supervisor.launcher is None or not supervisor.launcher.wait_ready(120.0):
                raise ConfigError("the launcher did not get ready within 120 s")
        DeployerClient(self.session, ROBOT).wait_for(list(self.deployers))
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()


def compile_c_program(directory: Path) -> Path:
    """Compile the trivial C program with ``cc``; ConfigError if there is no compiler."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if not cc:
        raise ConfigError("no C compiler (cc) found; the benchmark compiles a trivial C program")
    source = directory / "ready.c"
    source.write_text(C_PROGRAM)
    binary = directory / "ready"
    done = subprocess.run([cc, "-O2", "-o", str(binary), str(source)], capture_output=True, text=True)
    if done.returncode:
        raise ConfigError(f"cc failed on the trivial C program: {done.stderr.strip()}")
    return binary


def _add_echo_deployment(store: Any) -> None:
    from kgadapt.knowledge import schema as S

    store.execute(
        f"MERGE (d:{S.DEPLOYMENT} {{name: 'echo'}}) SET d.kind = 'DeploymentFile', d.executable = '{{python}}', "
        "d.arguments = $arguments, d.environment = []", {"arguments": ECHO_ARGS})
    for host in ("onboard", "remote"):
        store.execute(f"MATCH (d:{S.DEPLOYMENT} {{name: 'echo'}}) MERGE (p:{S.PLATFORM} {{name: $host}}) "
                      f"MERGE (d)-[:{S.EXECUTABLE_ON}]->(p)", {"host": host})
    store.execute(f"MATCH (d:{S.DEPLOYMENT} {{name: 'echo'}}) MERGE (g:{S.PERCEPTION_GRAPH} {{name: 'echo_config'}}) "
                  f"MERGE (d)-[:{S.DEPLOYS}]->(g)")


def _free_port() -> int:
    import random
    import socket

    for _ in range(200):
        port = random.randrange(20000, 32000)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise ConfigError("no free TCP port on loopback")


# -- 1. supervisor ------------------------------------------------------------------------


def supervisor_latencies(rig: _Rig, args: argparse.Namespace) -> list[dict[str, Any]]:
    from kgadapt.deploy.supervisor import ProcessSpec

    py = sys.executable
    bare = (py, "-c", f"import time; print({READY_TOKEN!r}); time.sleep(600)")
    programs: list[tuple[str, tuple[str, ...], int, Any]] = [
        ("C program (trivial)", (str(rig.c_program),), args.reps, rig.supervisor),
        ("python -c (bare)", bare, args.reps, rig.supervisor),
    ]
    if rig.supervisor_setpriv is not None:
        programs += [
            ("C program (trivial), setpriv launcher", (str(rig.c_program),), args.reps, rig.supervisor_setpriv),
            ("python -c (bare), setpriv launcher", bare, args.reps, rig.supervisor_setpriv),
        ]
    echo = (py, "-m", "kgadapt.sim.echo_detector", "--robot", ROBOT, "--host", "onboard", "--instance", "bench",
            "--config", "echo_config", "--connect", rig.endpoint)
    detector = (py, "-m", "kgadapt.onboard.perception.detector", "--robot", ROBOT, "--host", "onboard", "--instance", "bench",
                "--config", "marker_detection_day", "--connect", rig.endpoint)
    programs += [("echo detector (Python + Zenoh)", echo, args.reps, rig.supervisor)]
    if rig.real_detector:
        programs.append(("kgadapt.onboard.perception.detector (OpenCV + Zenoh + config query)", detector, args.detector_reps,
                         rig.supervisor))
    # The launcher preloads the runtime detector only (deploy/launcher.py RUNNABLE), not the echo stand-in.
    if rig.real_detector:
        programs.append(("kgadapt.onboard.perception.detector, forked by the launcher", detector, args.detector_reps,
                         rig.supervisor_launcher))
    records = []
    for label, argv, reps, supervisor in programs:
        spawn, ready, stop, rss = [], [], [], []
        for i in range(reps + 1):  # the first run warms caches and is not counted
            spec = ProcessSpec(instance=f"bench{i}", argv=argv, ready_timeout=30.0)
            t0 = time.time()
            p0 = time.perf_counter()
            info = supervisor.start(spec)
            ready_ms = (time.perf_counter() - p0) * 1000.0
            if supervisor is rig.supervisor_launcher and info.via != "launcher":
                raise ConfigError(f"{label}: started the plain way, not by the launcher")
            rss_mb = _rss_mb(info.pid)
            p1 = time.perf_counter()
            final = supervisor.stop(spec.instance)
            stop_ms = (time.perf_counter() - p1) * 1000.0
            if final.returncode is None:
                raise ConfigError(f"{label}: no exit status after stop")
            if i:
                spawn.append((info.started_at - t0) * 1000.0)
                ready.append(ready_ms)
                stop.append(stop_ms)
                rss.append(rss_mb)
        common = {"store": "supervisor", "n": None, "program": label, "rss_mb_at_ready": round(max(rss), 1)}
        records.append(make_record(op="spawn", samples_ms=spawn, **common))
        records.append(make_record(op="start_to_ready", samples_ms=ready, paper_ms=PAPER["start_ms"], **common))
        records.append(make_record(op="stop", samples_ms=stop, paper_ms=PAPER["stop_ms"], **common))
        print(f"  supervisor: {label}: ready p50 {summarize(ready).p50_ms:.2f} ms, stop p50 {summarize(stop).p50_ms:.2f} ms",
              flush=True)
    return records


def _rss_mb(pid: int | None) -> float:
    import psutil

    try:
        return psutil.Process(pid).memory_info().rss / (1024 * 1024)
    except (psutil.Error, TypeError):
        return 0.0


# -- 2. deployer over Zenoh -------------------------------------------------------------------


def deployer_latencies(rig: _Rig, args: argparse.Namespace) -> list[dict[str, Any]]:
    from kgadapt.deploy.client import DeployerClient

    client = DeployerClient(rig.session, ROBOT, timeout=10.0)
    cases = [("echo", "echo_config", args.reps)]
    if rig.real_detector:
        cases.append(("detector_day", "marker_detection_day", args.detector_reps))
    records = []
    for (deployment, config, reps), host in [(c, h) for c in cases for h in ("onboard", "remote")]:
        start, stop, armed = [], [], []
        for i in range(reps + 1):
            p0 = time.perf_counter()
            client.start(host, deployment, config, instance=f"zbench{i}")
            start_ms = (time.perf_counter() - p0) * 1000.0
            armed_ms = _armed_after_ready(client, host, f"zbench{i}") if deployment != "echo" else None
            p1 = time.perf_counter()
            client.stop(host, f"zbench{i}")
            stop_ms = (time.perf_counter() - p1) * 1000.0
            if i:
                start.append(start_ms)
                stop.append(stop_ms)
                if armed_ms is not None:
                    armed.append(armed_ms)
        how = "launcher" if host == "onboard" else "no launcher"
        common = {"store": "deployer over Zenoh", "n": None, "program": f"{deployment} ({config}), {how}"}
        records.append(make_record(op="start_request_to_ready", samples_ms=start, **common))
        records.append(make_record(op="stop_request", samples_ms=stop, **common))
        if armed:
            records.append(make_record(
                op="ready_to_reflex_armed", samples_ms=armed, **common,
                what="the detector's own figure: ready -> its reflex table fetched and every candidate built "
                     "(after ready, off the frame path)"))
        print(f"  deployer: {deployment}, {how}: start p50 {summarize(start).p50_ms:.1f} ms, stop p50 "
              f"{summarize(stop).p50_ms:.1f} ms" + (f", reflex armed {summarize(armed).p50_ms:.1f} ms after ready"
                                                    if armed else ""), flush=True)
    if rig.real_detector and _has_pool(rig):
        records += pooled_latencies(rig, args, client)
    return records


def _armed_after_ready(client: Any, host: str, instance: str, timeout: float = 5.0) -> float | None:
    """The ms a started detector says it took, after it was ready, to arm its reflex table (its record line
    ``... armed after ready: N candidate configurations in M ms``); None when it does not say so in time
    (a detector that arms before ready, or has no table)."""
    import re

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in client.status(host, instance).output or []:
            found = re.search(r"armed after ready: \d+ candidate configurations in ([0-9.]+) ms", line)
            if found:
                return float(found.group(1))
            if "reflex table prepared in the launcher's pool" in line or "no reflex table" in line:
                return None
        time.sleep(0.05)
    return None


def _has_pool(rig: _Rig) -> bool:
    return hasattr(rig.deployers["onboard"], "warm")  # main before issue 32 item 2 has no pool


def pooled_latencies(rig: _Rig, args: argparse.Namespace, client: Any) -> list[dict[str, Any]]:
    """Start request -> ready when the launcher's pool has an idle detector (session open) for it.

    Between two starts the pool is left to fill again (an idle member opens its session on its
    own time): the figure is a start that finds one waiting, as the pool is meant to make every start."""
    import dataclasses

    deployer = rig.deployers["onboard"]
    launcher = deployer.supervisor.launcher
    deployer.settings = dataclasses.replace(deployer.settings, pool=1)
    deployer.warm("detector_day", "marker_detection_day")
    start, stop, via = [], [], []
    for i in range(args.detector_reps + 1):
        deadline = time.monotonic() + 30.0
        while sum(launcher.idle.values()) < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(1.0)  # the new member opens its Zenoh session (not observable from here)
        p0 = time.perf_counter()
        info = client.start("onboard", "detector_day", "marker_detection_day", instance=f"pbench{i}")
        start_ms = (time.perf_counter() - p0) * 1000.0
        p1 = time.perf_counter()
        client.stop("onboard", f"pbench{i}")
        stop_ms = (time.perf_counter() - p1) * 1000.0
        if i:
            start.append(start_ms)
            stop.append(stop_ms)
            via.append(info.via)
    deployer.settings = dataclasses.replace(deployer.settings, pool=0)
    common = {"store": "deployer over Zenoh", "n": None,
              "program": "detector_day (marker_detection_day), launcher's pool",
              "pooled": sum(v == "pool" for v in via), "trials": len(via)}
    print(f"  deployer: detector_day, pool: start p50 {summarize(start).p50_ms:.1f} ms "
          f"({common['pooled']}/{len(via)} from the pool)", flush=True)
    return [make_record(op="start_request_to_ready", samples_ms=start, **common),
            make_record(op="stop_request", samples_ms=stop, **common)]


# -- 3. planned migration ---------------------------------------------------------------------


class _Frames:
    """JPEG frames at ``fps`` on camera cam0; remembers when each sequence number went out."""

    def __init__(self, session: Any, fps: float) -> None:
        import cv2
        import numpy as np

        from kgadapt.shared import keys

        image = np.full((480, 640), 128, np.uint8)
        ok, jpeg = cv2.imencode(".jpg", image)
        self.jpeg = jpeg.tobytes()
        self.publisher = session.declare_publisher(keys.camera_frame(ROBOT, "cam0"))
        self.period = 1.0 / fps
        self.seq = 0
        self.sent_at: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-frames", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from kgadapt.shared import messages

        next_at = time.perf_counter()
        while not self._stop.is_set():
            self.seq += 1
            self.sent_at[self.seq] = time.perf_counter()
            self.publisher.put(messages.encode("frame", {
                "camera": "cam0", "seq": self.seq, "time": time.time(), "width": 640, "height": 480, "jpeg": self.jpeg}))
            next_at += self.period
            self._stop.wait(max(0.0, next_at - time.perf_counter()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.publisher.undeclare()


class _Answered:
    """Frame sequence numbers that got a detections message from any detector instance."""

    def __init__(self, session: Any) -> None:
        from kgadapt.shared import keys

        self.seqs: set[int] = set()
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.detector_markers(ROBOT, "*"), self._on)

    def _on(self, sample: Any) -> None:
        from kgadapt.shared import messages
        from kgadapt.shared.errors import MessageError

        try:
            seq = messages.decode(sample.payload.to_bytes(), "detections")["seq"]
        except MessageError:
            return
        with self._lock:
            self.seqs.add(seq)

    def missing(self, first: int, last: int) -> list[int]:
        with self._lock:
            return [s for s in range(first, last + 1) if s not in self.seqs]

    def close(self) -> None:
        self._sub.undeclare()


def migration_gaps(rig: _Rig, args: argparse.Namespace) -> list[dict[str, Any]]:
    from kgadapt.deploy.client import DeployerClient
    from kgadapt.deploy.migration import migrate

    cases = [("echo", "echo_config")]
    if rig.real_detector:
        cases.append(("detector_day", "marker_detection_day"))
    client = DeployerClient(rig.session, ROBOT, timeout=10.0, start_timeout=60.0)
    records = []
    for deployment, config in cases:
        frames = _Frames(rig.session, args.fps)
        answered = _Answered(rig.session)
        try:
            instance, host = f"mig-{deployment}-0", "onboard"
            client.start(host, deployment, config, instance=instance)
            time.sleep(1.0)  # settle: the detector is fed and answering
            durations, lost, baseline, during = [], [], [], []
            for i in range(1, args.migrations + 1):
                target = "remote" if host == "onboard" else "onboard"
                first = frames.seq + 1
                t0 = time.perf_counter()
                report = migrate(rig.session, ROBOT, instance, target, source_host=host,
                                 new_instance=f"mig-{deployment}-{i}", ready_timeout=30.0, client=client)
                took = time.perf_counter() - t0
                last = frames.seq
                time.sleep(0.5)  # in-flight detections arrive
                lost.append(len(answered.missing(first, last)))
                during.append(last - first + 1)
                durations.append(report.source_stopped_ms)
                # Baseline: a quiet window as long as the migration, one detector running.
                quiet_first = frames.seq + 1
                time.sleep(max(took, 0.2))
                quiet_last = frames.seq
                time.sleep(0.5)
                baseline.append(len(answered.missing(quiet_first, quiet_last)))
                instance, host = report.new_instance, target
            client.stop(host, instance)
        finally:
            answered.close()
            frames.close()
        records.append(make_record(
            store="migration", n=None, op="planned_migration", program=f"{deployment} ({config})",
            samples_ms=durations, fps=args.fps, migrations=args.migrations,
            frames_during=sum(during), frames_lost=sum(lost), frames_lost_max=max(lost),
            baseline_frames_lost=sum(baseline), target_frames_lost=0,
        ))
        print(f"  migration: {deployment}: {sum(lost)} frames without detections in {args.migrations} migrations "
              f"({sum(during)} frames), baseline {sum(baseline)}", flush=True)
    return records


# -- output -----------------------------------------------------------------------------------


def render(records: list[dict[str, Any]], *, markdown: bool = False) -> str:
    """The records as three tables: supervisor, deployer over Zenoh, migration."""
    sup = [r for r in records if r["store"] == "supervisor"]
    programs = list(dict.fromkeys(r["program"] for r in sup))
    rows = []
    for program in programs:
        by_op = {r["op"]: r for r in sup if r["program"] == program}
        rows.append([program, by_op["spawn"]["p50_ms"], by_op["start_to_ready"]["p50_ms"],
                     by_op["start_to_ready"]["p99_ms"], by_op["stop"]["p50_ms"], by_op["stop"]["p99_ms"],
                     by_op["spawn"]["rss_mb_at_ready"]])
    rows.append(["paper, Table I (C detector, start / stop, mean)", None, PAPER["start_ms"], None, PAPER["stop_ms"], None, None])
    out = ["Supervisor, ms (p50 unless noted):",
           format_table(rows, ["program", "spawn", "ready", "ready p99", "stop", "stop p99", "RSS MiB"], markdown=markdown)]
    dep = [r for r in records if r["store"] == "deployer over Zenoh"]
    rows = []
    for program in dict.fromkeys(r["program"] for r in dep):
        by_op = {r["op"]: r for r in dep if r["program"] == program}
        armed = by_op.get("ready_to_reflex_armed")
        rows.append([program, by_op["start_request_to_ready"]["p50_ms"], by_op["start_request_to_ready"]["p99_ms"],
                     by_op["stop_request"]["p50_ms"], by_op["stop_request"]["p99_ms"],
                     armed["p50_ms"] if armed else None])
    out += ["", "Deployer requests over Zenoh, ms (reflex armed: ready -> its candidates built, after ready):",
            format_table(rows, ["deployment", "start p50", "start p99", "stop p50", "stop p99", "reflex armed p50"],
                         markdown=markdown)]
    mig = [r for r in records if r["store"] == "migration"]
    rows = [[r["program"], r["migrations"], r["p50_ms"], r["frames_during"], r["frames_lost"], r["frames_lost_max"],
             r["baseline_frames_lost"]] for r in mig]
    out += ["", f"Planned migration at {mig[0]['fps'] if mig else 30:g} fps (target: 0 frames lost):",
            format_table(rows, ["detector", "migrations", "duration p50 ms", "frames", "frames lost",
                                "worst migration", "baseline lost"], markdown=markdown)]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:  # python -m kgadapt.bench.deployer_bench
    parser = argparse.ArgumentParser(prog="python -m kgadapt.bench.deployer_bench")
    register(parser.add_subparsers(dest="bench"))
    args = parser.parse_args(["deployer", *(argv if argv is not None else sys.argv[1:])])
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
