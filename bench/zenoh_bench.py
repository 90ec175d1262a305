"""``kgadapt bench zenoh``: what the Zenoh fabric costs on top of the store.

One run, real processes on loopback:

1. A knowledge service (``kgadapt knowledge serve``, its own embedded
   FalkorDB with the shipped models) and an echo process. From this process,
   interleaved round by round so every operation sees the same machine:

   ``zenoh_bare``      a get answered by an echo queryable replying in its callback
                       (Zenoh's floor; our code never replies there); the echo is a
                       process of its own, one hop away as the service is
   ``zenoh_queued``    the same echo handed to a worker thread through a queue
                       (the pattern every queryable of ours follows)
   ``rpc_queued``      the same queued echo asked with ``kgadapt.shared.rpc.call`` (how every
                       client of ours asks; its cost over ``zenoh_queued``)
   ``store_trivial``   ``RETURN 1`` on the store directly
   ``zenoh_trivial``   ``RETURN 1`` as read-only Cypher through the service
   ``store_named``     the placement query, ``run_named`` on the store directly
   ``zenoh_named``     the same named query through the service (KnowledgeClient)

2. Status fan-in: ``--hosts`` simulated hosts publish ``host_status`` at
   ``--rate`` Hz each for ``--duration`` seconds. Reported: the service's and
   its store's CPU (percent of one core, from psutil, beside an idle baseline)
   and the lag from a status being published to the graph showing it
   (``status_lag``: a probe thread owns some of the hosts; after each of their
   statuses it reads the graph until the new figure is there, ~0.3 ms a read).

Records go to ``bench/results/zenoh.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from kgadapt.bench.stats import format_table, gc_paused, machine_info, make_record, time_once, write_records
from kgadapt.shared import rpc
from kgadapt.shared.children import ChildProcess
from kgadapt.shared.errors import ConfigError, TransportError
from kgadapt.shared.resources import models, results_dir

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = results_dir() / "zenoh.json"
ROBOT = "bench"
CONFIG = "marker_detection_day"
QUERY_PARAMS = {"feature": "MarkerDetection", "config": CONFIG}

_ECHO = r"""
import queue, sys, threading
from kgadapt.shared.readiness import announce_ready
from kgadapt.shared.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode="peer", listen=(sys.argv[1],)))
work = queue.Queue()
def worker():
    while True:
        q = work.get()
        with q:
            q.reply(q.key_expr, b"pong")
threading.Thread(target=worker, daemon=True).start()
def direct(q):
    q.reply(q.key_expr, b"pong")  # baseline only: replying inside the callback
    q.drop()
session.declare_queryable("bench/echo/direct", direct)
session.declare_queryable("bench/echo/queued", lambda q: work.put(q))
announce_ready(role="echo")
try:
    sys.stdin.read()
except KeyboardInterrupt:  # the bench stops its children with SIGINT first
    pass
session.close()
"""


def register(bench_sub: argparse._SubParsersAction) -> None:
    """Add ``kgadapt bench zenoh``."""
    p = bench_sub.add_parser(
        "zenoh",
        help="named query over Zenoh vs on the store; status fan-in from simulated hosts",
        description="Named query latency over Zenoh beside the same query on the store (p50, p99), "
        "and status fan-in from many simulated hosts (service CPU, status-to-graph lag). "
        "Starts its own knowledge service and store on loopback.",
    )
    p.add_argument("--reps", type=int, default=2000, help="timed requests per operation (default 2000)")
    p.add_argument("--warmup", type=int, default=200, help="untimed requests first (default 200)")
    p.add_argument("--hosts", type=int, default=50, help="simulated hosts for the fan-in (default 50)")
    p.add_argument("--rate", type=float, default=2.0, help="status rate per host, Hz (default 2)")
    p.add_argument("--duration", type=float, default=20.0, help="fan-in duration, seconds (default 20)")
    p.add_argument("--probe-hosts", type=int, default=10, help="hosts whose statuses are timed to the graph (default 10)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"records as JSON (default {DEFAULT_OUT})")
    p.add_argument("--json", action="store_true", help="print the records as JSON instead of a table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.reps < 1 or args.hosts < 1 or args.rate <= 0 or args.duration <= 0:
        raise ConfigError("--reps, --hosts, --rate and --duration must be positive")
    if not 0 < args.probe_hosts <= args.hosts:
        raise ConfigError(f"--probe-hosts {args.probe_hosts}: between 1 and --hosts ({args.hosts})")
    load_before = round(os.getloadavg()[0], 2)
    with tempfile.TemporaryDirectory(prefix="kgadapt-zenoh-bench-") as tmp:
        with _Fabric(Path(tmp)) as fabric:
            records = _request_latency(fabric, reps=args.reps, warmup=args.warmup)
            records.append(_fan_in(fabric, hosts=args.hosts, rate=args.rate, duration=args.duration,
                                   probe_hosts=args.probe_hosts))
    info = machine_info()
    load = [load_before, round(os.getloadavg()[0], 2)]  # 1-minute load before and after the run
    for record in records:
        record["machine"] = info
        record["loadavg_1m"] = load
    write_records(args.out, records)
    if args.json:
        print(json.dumps(records, indent=1))
    else:
        print(summary_table(records))
        print(f"\nwritten to {args.out}")
    return 0


def summary_table(records: list[dict[str, Any]], *, markdown: bool = False) -> str:
    rows = []
    for r in records:
        extra = ""
        if r["op"] == "status_lag":
            extra = (f"{r['hosts']} hosts x {r['rate_hz']} Hz: service CPU {r['service_cpu_pct']:.1f} % "
                     f"(idle {r['service_idle_cpu_pct']:.1f} %), store CPU {r['store_cpu_pct']:.1f} %")
        rows.append([r["op"], r["p50_ms"], r["p99_ms"], r["mean_ms"], r["reps"], extra])
    return format_table(rows, ["op", "p50 ms", "p99 ms", "mean ms", "n", "notes"], markdown=markdown)


class _Fabric:
    """Service and echo child processes, a client session, a direct store handle."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.children: list[ChildProcess] = []

    def __enter__(self) -> "_Fabric":
        from kgadapt.knowledge.client import KnowledgeClient
        from kgadapt.knowledge.loader import load_models
        from kgadapt.knowledge.store import open_store
        from kgadapt.shared.session import ZenohSettings, open_session

        store_dir = self.tmp / "store"
        loader = open_store(f"embedded:{store_dir}")
        loader.setup()
        try:
            load_models(loader, [models()])
        finally:
            loader.shutdown()
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        try:
            self.service = self._start(
                [sys.executable, "-m", "kgadapt", "knowledge", "serve", "--store", f"embedded:{store_dir}",
                 "--robot", ROBOT, "--listen", self.endpoint], "service")
            # The echo gets its own endpoint and session: one hop, like this process to the service.
            echo_endpoint = f"tcp/127.0.0.1:{_free_port()}"
            self.echo = self._start([sys.executable, "-c", _ECHO, echo_endpoint], "echo")
            self.echo_session = open_session(ZenohSettings(mode="client", connect=(echo_endpoint,)))
            self.session = open_session(ZenohSettings(mode="client", connect=(self.endpoint,)))
            self.client = KnowledgeClient(self.session, ROBOT, timeout=5)
            self.store = open_store(f"embedded:{store_dir}")  # finds the service's running server
            self.store.setup()
            self.store_pid = json.loads((store_dir / "server.json").read_text())["pid"]
            now = time.time()
            for platform in ("onboard", "remote"):  # as the agents would: online, with room
                self.client.write("platform", {"name": platform, "time": now, "memory_free_mb": 900.0, "online": True})
            if not self.client.query("placement", QUERY_PARAMS):
                raise ConfigError("benchmark setup: the placement query found no platform")
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start(self, argv: list[str], name: str) -> ChildProcess:
        # stdin stays open (a pipe): the echo runs until it closes
        child = ChildProcess(argv, name=name, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdin=subprocess.PIPE)
        self.children.append(child)
        child.wait_ready(30.0)
        return child

    def __exit__(self, *exc: object) -> None:
        if getattr(self, "store", None) is not None:
            self.store.shutdown()
        for name in ("session", "echo_session"):
            if getattr(self, name, None) is not None:
                getattr(self, name).close()
        for child in reversed(self.children):
            child.stop()


def _request_latency(fabric: _Fabric, *, reps: int, warmup: int) -> list[dict[str, Any]]:
    from kgadapt.knowledge.queries import run_named

    client, store, echo_session = fabric.client, fabric.store, fabric.echo_session

    def echo(key: str) -> Callable[[], Any]:
        def call() -> None:
            replies = list(echo_session.get(key, payload=b"ping", timeout=5))
            if not replies or replies[0].ok is None:
                raise TransportError(f"no echo on {key}")
        return call

    ops: dict[str, Callable[[], Any]] = {
        "zenoh_bare": echo("bench/echo/direct"),
        "zenoh_queued": echo("bench/echo/queued"),
        # the same echo asked through shared/rpc.py, as every client of ours asks: the layer's own cost
        "rpc_queued": lambda: rpc.call(echo_session, "bench/echo/queued", b"ping", bytes, timeout=5),
        "store_trivial": lambda: store.execute("RETURN 1 AS one", read_only=True),
        "zenoh_trivial": lambda: client.cypher("RETURN 1 AS one"),
        "store_named": lambda: run_named(store, "placement", QUERY_PARAMS),
        "zenoh_named": lambda: client.query("placement", QUERY_PARAMS),
    }
    expected = run_named(store, "placement", QUERY_PARAMS)
    if client.query("placement", QUERY_PARAMS) != expected:
        raise ConfigError("the named query over Zenoh and on the store disagree")
    for fn in ops.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[float]] = {name: [] for name in ops}
    order = list(ops)
    rng = random.Random(1)
    with gc_paused():
        for _ in range(reps):
            rng.shuffle(order)  # interleaved: each round times every op on the same machine state
            for name in order:
                samples[name].append(time_once(ops[name]))
    return [make_record(store="embedded", n=None, op=name, samples_ms=samples[name]) for name in ops]


def _fan_in(fabric: _Fabric, *, hosts: int, rate: float, duration: float, probe_hosts: int) -> dict[str, Any]:
    import psutil

    from kgadapt.shared import keys, messages

    service = psutil.Process(fabric.service.pid)
    store_proc = psutil.Process(fabric.store_pid)
    names = [f"simhost{i:03d}" for i in range(hosts)]
    from kgadapt.bench.fleet_bench import load_sim_platforms

    load_sim_platforms(fabric.store, names, fabric.tmp / "sim-platforms")  # only the models add hosts
    publishers = {name: fabric.session.declare_publisher(keys.host_status(ROBOT, name)) for name in names}

    # Idle baseline: what the service and its store burn with no status flowing.
    idle_before = (_cpu_seconds(service), _cpu_seconds(store_proc))
    idle_seconds = min(3.0, duration)
    time.sleep(idle_seconds)
    idle_service = 100 * (_cpu_seconds(service) - idle_before[0]) / idle_seconds
    idle_store = 100 * (_cpu_seconds(store_proc) - idle_before[1]) / idle_seconds

    probes = names[:probe_hosts]
    others = names[probe_hosts:]
    period = 1.0 / rate
    stop = threading.Event()
    lags: list[float] = []
    sent = [0]
    failures: list[str] = []

    def status(name: str, free: float) -> bytes:
        return messages.encode("host_status", {
            "host": name, "time": time.time(), "memory_total_mb": 4096.0, "memory_free_mb": free,
            "cpu_load": 10.0, "cpu_cores": 4})

    def probe_loop() -> None:
        seq = 0
        slot = period / len(probes)
        next_at = time.monotonic()
        while not stop.is_set():
            for name in probes:
                seq += 1
                # Unique (the graph shows this exact figure once applied), and 1 GiB from the host's last
                # one: a change the service writes at once, not one within its deadband that waits for
                # the refresh (ServiceSettings.status_deadband_mb, status_refresh_s).
                free = 1000.0 + 1024.0 * (seq // len(probes) % 2) + seq / 1e6
                publishers[name].put(status(name, free))
                sent_at = time.perf_counter()
                while True:
                    rows = fabric.store.execute(
                        "MATCH (p:Platform {name: $name}) RETURN p.memory_free_mb AS free", {"name": name}, read_only=True)
                    if rows and rows[0]["free"] == free:
                        lags.append((time.perf_counter() - sent_at) * 1000)
                        break
                    if time.perf_counter() - sent_at > 5:
                        failures.append(f"{name}: status {seq} not in the graph after 5 s")
                        break
                next_at += slot
                stop.wait(max(0.0, next_at - time.monotonic()))
                if stop.is_set():
                    return

    def publish_loop() -> None:
        if not others:
            return
        slot = period / len(others)
        next_at = time.monotonic()
        i = 0
        while not stop.is_set():
            name = others[i % len(others)]
            publishers[name].put(status(name, 1000.0 + i % 500))
            sent[0] += 1
            i += 1
            next_at += slot
            stop.wait(max(0.0, next_at - time.monotonic()))

    threads = [threading.Thread(target=probe_loop, daemon=True), threading.Thread(target=publish_loop, daemon=True)]

    before = (_cpu_seconds(service), _cpu_seconds(store_proc))
    started = time.monotonic()
    for t in threads:
        t.start()
    time.sleep(duration)
    stop.set()
    for t in threads:
        t.join(10)
    elapsed = time.monotonic() - started
    after = (_cpu_seconds(service), _cpu_seconds(store_proc))
    for pub in publishers.values():
        pub.undeclare()
    if failures:
        raise TransportError(f"fan-in: {len(failures)} statuses never reached the graph, e.g. {failures[0]}")
    if not lags:
        raise TransportError("fan-in: no status was timed")
    return make_record(
        store="embedded", n=hosts, op="status_lag", samples_ms=lags,
        hosts=hosts, rate_hz=rate, duration_s=round(elapsed, 2),
        statuses_sent=sent[0] + len(lags),
        service_cpu_pct=round(100 * (after[0] - before[0]) / elapsed, 2),
        store_cpu_pct=round(100 * (after[1] - before[1]) / elapsed, 2),
        service_idle_cpu_pct=round(idle_service, 2), store_idle_cpu_pct=round(idle_store, 2),
    )


def _cpu_seconds(proc: Any) -> float:
    times = proc.cpu_times()
    return times.user + times.system


def _free_port() -> int:
    from kgadapt.operator.cluster import free_tcp_port

    return free_tcp_port()
