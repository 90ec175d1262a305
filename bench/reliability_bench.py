"""``kgadapt bench reliability``: real faults on real processes, counted and timed.

Trials (each injects one fault and records what happened):

``store_crash``
    The embedded FalkorDB (knowledge/embedded.py) takes a burst of run-time
    writes; ``kill -9`` of its redis-server lands mid-burst; the server is
    started again -- by its owner, or by the store itself on the next write
    (as in the knowledge service) -- and a fresh server counts: every
    acknowledged write must be there.
``remote_death``
    The robot across network namespaces (:class:`RobotOnHosts`), the detector
    on the remote host; ``kill -9`` of the remote agent (its detector dies
    with it, parent-death signal). Failover: kill to the first detections of
    the new detector on the onboard host.
``partition``
    The remote host's cable is pulled (``ip link set ... down``) for a few
    seconds and plugged back in. Failover during the cut; heal: link up to the
    remote twin stopped (exactly one detector again), both platforms online,
    the twin's ProcessProfile ended, nothing restarted.
``onboard_restart``
    The onboard agent gets SIGTERM or ``kill -9`` and is started again: the
    detector it had started is adopted or stopped cleanly, none orphaned.
``store_and_remote_death``
    ``kill -9`` of the knowledge store's server and of the remote agent at
    once: the first failover plan fails; the detector must still come back.
``bad_inputs``
    Another robot (the ``robot2`` namespace) sends hypothesis-generated
    malformed payloads to the knowledge and deployer queryables: error
    replies, refusals, or crashes, counted.

The observer of the namespace trials is a second robot: :func:`probe_main`
(``python -m kgadapt.bench.reliability_bench probe``) runs in the ``robot2``
namespace, a Zenoh client of the robot's router, and reports what it sees
(detections, liveliness, decisions, deployer events) as JSON lines; it also
answers requests (named queries, Cypher, deployer lists, fuzzing) sent to its
stdin. Results: ``bench/results/reliability.json``; ``--markdown`` prints the
table of docs/reliability.md.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from kgadapt.shared.children import ChildProcess, StopPolicy
from kgadapt.shared.errors import ConfigError, KgadaptError, StoreUnavailable, TransportError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.resources import results_dir
from kgadapt.shared.states import ENDED_EVENTS, KEPT_STATES, TriggerKind

RESULTS = results_dir() / "reliability.json"
ROBOT = DEFAULT_ROBOT
DETECTOR_MODULE = "kgadapt.onboard.perception.detector"
# Measured here (Zenoh 1.10): a TCP link that dies with unsent data is closed with SO_LINGER 10 s,
# which blocks one of the RX runtime's 2 threads; two dead links (a host's agent and its detector)
# block both and the router stops routing until the cable is back. More RX threads keep it going.
ZENOH_RUNTIME = "(rx: (worker_threads: 8))"


# -- store crash ---------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class StoreCrashSettings:
    """One trial: ``kill -9`` after ``kill_after`` acknowledgements (drawn from the range).

    ``restart``: ``owner`` -- the writer stops at the first failed write, the server's
    owner notices its death and starts it again (``EmbeddedServer.stop()`` + ``ensure()``);
    ``store`` -- the embedded store finds its server gone on the next write and restarts it
    by itself, as the knowledge service's store does, and the burst goes on until ``tail``
    writes were acknowledged by the restarted server (then the new server is killed too and a fresh one counts).
    """

    kill_after: tuple[int, int] = (50, 400)
    restart: str = "owner"
    tail: int = 50
    start_timeout: float = 15.0
    # A write with no answer this long is not acknowledged (a FalkorDB that stops answering is a fault of its own).
    socket_timeout: float = 10.0

    def __post_init__(self) -> None:
        if self.restart not in ("owner", "store"):
            raise ConfigError(f"store crash restart {self.restart!r}: use owner or store")
        low, high = self.kill_after
        if not 1 <= low <= high:
            raise ConfigError(f"store crash kill_after {self.kill_after!r}: use 1 <= low <= high")


def store_crash_trial(data_dir: Path, *, trial: int = 0, seed: int = 0,
                      settings: StoreCrashSettings = StoreCrashSettings()) -> dict[str, Any]:
    """A burst of acknowledged writes to the embedded store, ``kill -9`` of its server mid-burst, count.

    The writes are ``kgadapt.knowledge.runtime.record_process_sample`` (one MERGE each, as the
    deployers send them), each acknowledged when ``execute`` returns. The kill comes from
    another thread while the writer keeps writing, so it lands mid-write. Writes run on
    this thread: a server the store restarts gets its parent-death signal tied to the
    thread that started it. Returns acknowledged, found and lost counts, and timings.
    """
    from kgadapt.knowledge import runtime
    from kgadapt.knowledge.embedded import EmbeddedServer
    from kgadapt.knowledge.store import open_store

    rng = random.Random(seed * 1000 + trial)
    target = rng.randint(*settings.kill_after)
    prefix = f"burst-{trial}-"
    server = EmbeddedServer(data_dir, start_timeout=settings.start_timeout)
    server.ensure()
    first_pid = server.address.pid
    auto = settings.restart == "store"
    store = open_store(f"embedded:{data_dir}" if auto else f"falkordb+unix://{server.address.unix_socket}",
                       socket_timeout=settings.socket_timeout)
    if auto:
        store.server = server  # the store adopts the server: it restarts it and stops it
    store.setup(timeout=settings.start_timeout)
    acked: list[int] = []
    kill = threading.Event()
    killed_at: list[float] = []

    delay = rng.uniform(0.0, 0.005)  # a few writes later: anywhere in a write's round trip

    def killer() -> None:
        if kill.wait(60):
            time.sleep(delay)
            # Taken before the kill: the writer may find the server gone, have it restarted and write on
            # before this thread runs again (it did under load), and the outage is counted from here.
            at = time.perf_counter()
            os.kill(first_pid, signal.SIGKILL)
            killed_at.append(at)

    thread = threading.Thread(target=killer, name="store-killer", daemon=True)
    thread.start()
    failed: list[str] = []
    back_at: float | None = None
    acked_at_restart: int | None = None  # acknowledged writes before the first one on the restarted server
    i = 0
    try:
        while True:
            try:
                runtime.record_process_sample(store, run_id=f"{prefix}{i}", rss_mb_last=float(i), rss_mb_mean=1.0,
                                              rss_mb_max=float(i), cpu_percent_mean=0.0)
            except KgadaptError as exc:  # not acknowledged
                failed.append(str(exc))
                if not auto or len(failed) > 20:
                    break
                continue
            finally:
                i += 1
            acked.append(i - 1)
            if len(acked) == target:
                kill.set()
            if auto and acked_at_restart is None and store.server.address.pid != first_pid:
                # Only a kill changes the pid; seen by the writer, not by when the killer thread ran again.
                acked_at_restart, back_at = len(acked) - 1, time.perf_counter()
            if acked_at_restart is not None and len(acked) - acked_at_restart >= settings.tail:
                break
            if len(acked) > target + 100_000:
                raise KgadaptError(f"store crash trial {trial}: the kill never took effect")
        kill.set()
        thread.join(5)
        restarted_pid = store.server.address.pid if auto else None
    finally:
        if auto and store.server is not None and store.server.address and store.server.address.pid != first_pid:
            _kill_hard(store.server.address.pid)  # what counts is what reached the disk
        store.shutdown()  # the embedded store's shutdown also reaps and forgets its (dead) server
        server.stop()  # the owner reaps its dead server and forgets it (server.json)
    started = time.perf_counter()
    fresh = EmbeddedServer(data_dir, start_timeout=settings.start_timeout)
    restart_hung = False
    try:
        fresh.ensure()
    except StoreUnavailable:
        # FalkorDB 4.16 once never finished replaying the AOF (no log line after its base file's; the same
        # files then loaded in 0.03 s on 60 starts). ensure() killed it; a second start reads the same files.
        restart_hung = True
        fresh = EmbeddedServer(data_dir, start_timeout=settings.start_timeout)
        fresh.ensure()
    restart_ms = (time.perf_counter() - started) * 1000.0
    try:
        counter = open_store(f"falkordb+unix://{fresh.address.unix_socket}")
        counter.setup()
        try:
            rows = counter.execute("MATCH (r:ProcessProfile) WHERE r.name STARTS WITH $prefix RETURN r.name AS name",
                                   {"prefix": prefix})
        finally:
            counter.shutdown()
    finally:
        fresh.stop()
    found = {int(str(r["name"])[len(prefix):]) for r in rows}
    lost = sorted(set(acked) - found)
    outage_ms = (back_at - killed_at[0]) * 1000.0 if back_at and killed_at else None
    return {
        "trial": trial, "restart": settings.restart, "kill_after": target, "acked": len(acked),
        "acked_after_restart": 0 if acked_at_restart is None else len(acked) - acked_at_restart,
        "found": len(found), "lost": len(lost), "lost_examples": lost[:10],
        "unacked_but_stored": len(found - set(acked)), "failed_writes": len(failed), "first_failure": failed[:1],
        "killed": bool(killed_at), "restarted_by_store": bool(auto and restarted_pid and restarted_pid != first_pid),
        "outage_ms": None if outage_ms is None else round(outage_ms, 1), "restart_ms": round(restart_ms, 1),
        "restart_hung": restart_hung,
    }


def _kill_hard(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        try:
            done, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return
        if done:
            return
        time.sleep(0.005)


# -- the observer: a second robot on the network ------------------------------------------


def probe_main(argv: Sequence[str] | None = None) -> int:
    """``python -m kgadapt.bench.reliability_bench probe``: watch a robot over Zenoh, answer requests on stdin."""
    parser = argparse.ArgumentParser(prog="python -m kgadapt.bench.reliability_bench probe",
                                     description="Watch a robot's detections, hosts, decisions and deployers; "
                                     "print JSON lines; answer JSON requests read from stdin.")
    parser.add_argument("--robot", default=ROBOT, help="the robot watched (default quad1)")
    from kgadapt.shared.session import add_arguments, settings_from_args

    add_arguments(parser)
    args = parser.parse_args(argv)
    from kgadapt.shared.readiness import ready_line
    from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session

    session = open_session(settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT]))
    probe = _Probe(args.robot, session)
    try:
        probe.setup()
        probe.emit_line(ready_line(role="probe", robot=args.robot))  # through the one writer: lines stay whole
        for line in sys.stdin:
            if line.strip():
                probe.handle(line)
    finally:
        probe.shutdown()
        session.close()
    return 0


class _Probe:
    """The probe's insides: callbacks queue lines, one writer prints, the main thread answers requests."""

    def __init__(self, robot: str, session: Any) -> None:
        self.robot = robot
        self.session = session
        self._out: queue.Queue[dict[str, Any] | str | None] = queue.Queue()
        self._lock = threading.Lock()
        self.instances: dict[str, dict[str, Any]] = {}
        self._times: dict[str, collections.deque[float]] = {}  # recent detection times per instance
        self._handles: list[Any] = []
        self._writer = threading.Thread(target=self._write, name="probe-writer", daemon=True)

    def setup(self) -> None:
        from kgadapt.shared import keys

        r = self.robot
        self._writer.start()
        self._handles = [
            self.session.declare_subscriber(keys.detector_markers(r), self._on_detections),
            self.session.declare_subscriber(keys.adaptation_events(r), self._on_decision),
            self.session.declare_subscriber(keys.deployer_events(r), self._on_deploy),
            self.session.liveliness().declare_subscriber(keys.host_alive(r), self._on_alive, history=True),
        ]

    def shutdown(self) -> None:
        from kgadapt.shared import rpc

        for handle in self._handles:
            rpc.undeclare_quietly(handle)
        self._out.put(None)
        self._writer.join(2)

    def emit(self, event: dict[str, Any]) -> None:
        event.setdefault("t", time.time())
        self._out.put(event)

    def emit_line(self, line: str) -> None:
        self._out.put(line)

    def _write(self) -> None:
        while (event := self._out.get()) is not None:
            sys.stdout.write((event if isinstance(event, str) else json.dumps(event, default=str)) + "\n")
            sys.stdout.flush()

    def _decode(self, sample: Any, kind: str) -> dict[str, Any] | None:
        from kgadapt.shared import messages
        from kgadapt.shared.errors import MessageError

        try:
            return messages.decode(sample.payload.to_bytes(), kind)
        except MessageError as exc:
            self.emit({"ev": "dropped", "kind": kind, "why": str(exc)[:200]})
            return None

    def _on_detections(self, sample: Any) -> None:
        now = time.time()
        m = self._decode(sample, "detections")
        if m is None:
            return
        with self._lock:
            seen = self.instances.get(m["instance"])
            if seen is None:
                seen = self.instances[m["instance"]] = {"host": m["host"], "config": m["config"], "first": now,
                                                         "count": 0, "last": now}
            seen["last"] = now
            seen["count"] += 1
            first = seen["count"] == 1
            self._times.setdefault(m["instance"], collections.deque(maxlen=2000)).append(now)
        if first:
            self.emit({"ev": "first_detection", "instance": m["instance"], "host": m["host"], "config": m["config"],
                       "t": now})

    def _on_decision(self, sample: Any) -> None:
        m = self._decode(sample, "adaptation_event")
        if m:
            d = m.get("decision") or {}
            self.emit({"ev": "decision", "trigger": m["trigger"], "outcome": m.get("outcome"),
                       "kind": d.get("trigger_kind"), "config": d.get("config"), "host": d.get("host"),
                       "instance": d.get("instance"), "latency_ms": d.get("latency_ms")})

    def _on_deploy(self, sample: Any) -> None:
        m = self._decode(sample, "deploy_event")
        if m:
            self.emit({"ev": "deploy", "event": m["event"], "host": m["host"], "instance": m["instance"],
                       "pid": m.get("pid"), "returncode": m.get("returncode"), "run_id": m.get("run_id")})

    def _on_alive(self, sample: Any) -> None:
        key = str(sample.key_expr).split("/")
        self.emit({"ev": "alive", "host": key[-2], "up": str(sample.kind).endswith("PUT")})

    # -- requests (main thread) ---------------------------------------------------

    def handle(self, line: str) -> None:
        try:
            request = json.loads(line)
            rid = request.get("id")
        except (ValueError, AttributeError) as exc:
            self.emit({"ev": "reply", "id": None, "ok": False, "error": f"bad request line: {exc}"})
            return
        try:
            result = self._answer(request)
            self.emit({"ev": "reply", "id": rid, "ok": True, "result": result})
        except Exception as exc:  # any failure is the requester's answer, never the probe's end
            self.emit({"ev": "reply", "id": rid, "ok": False, "error": f"{type(exc).__name__}: {exc}"})

    def _answer(self, request: dict[str, Any]) -> Any:
        from kgadapt.deploy.client import DeployerClient
        from kgadapt.knowledge.client import KnowledgeClient

        op = request.get("op")
        timeout = float(request.get("timeout", 2.0))
        if op == "query":
            return KnowledgeClient(self.session, self.robot, timeout=timeout).query(
                request["name"], request.get("params") or {})
        if op == "cypher":
            return KnowledgeClient(self.session, self.robot, timeout=timeout).cypher(
                request["cypher"], request.get("params") or {})
        if op == "launchers":  # each answering deployer's launcher: pid, ready, idle pool members
            import msgspec

            return {host: msgspec.to_builtins(launcher) for host, launcher in DeployerClient(
                self.session, self.robot, timeout=timeout).launchers(request.get("host", "*")).items()}
        if op == "list":
            import msgspec

            return msgspec.to_builtins(DeployerClient(self.session, self.robot, timeout=float(
                request.get("timeout", 2.0))).processes(request.get("host", "*")))
        if op == "active":
            since = time.time() - float(request.get("window", 1.0))
            with self._lock:
                return {k: dict(v) for k, v in self.instances.items() if v.get("last", 0) >= since}
        if op == "since":  # each instance's first detection at or after a time
            after = float(request["after"])
            with self._lock:
                firsts = {k: next((t for t in v if t >= after), None) for k, v in self._times.items()}
            return {k: t for k, t in firsts.items() if t is not None}
        if op == "fuzz":
            return fuzz(self.session, self.robot, examples=int(request.get("examples", 20)),
                        hosts=tuple(request.get("hosts") or ("onboard", "remote")))
        if op == "write":  # the soak's acknowledged writes (this robot's write API: no ACL on a plain cluster)
            return KnowledgeClient(self.session, self.robot, timeout=float(request.get("timeout", 3.0))).write(
                request["verb"], request.get("params") or {})
        if op == "squeeze":
            import msgspec

            from kgadapt.shared.hostmonitor import squeeze

            return msgspec.to_builtins(squeeze(self.session, self.robot, request["host"], float(request["reserve_mb"])))
        if op == "forge":  # host statuses on this robot's own keys, as a process holding its certificate could
            from kgadapt.shared import keys, messages

            for body in request["statuses"]:
                self.session.put(keys.host_status(self.robot, body["host"]), messages.encode("host_status", body))
            return len(request["statuses"])
        raise ConfigError(f"unknown probe op {op!r}: use query, cypher, list, active, since, fuzz, write, squeeze "
                          "or forge")


class ProbeHandle:
    """The probe as a child process (in a namespace or not): events collected, requests answered."""

    def __init__(self, argv: Sequence[str], *, log_path: Path) -> None:
        self.argv = list(argv)
        self.log_path = log_path
        self.child: ChildProcess | None = None
        self.events: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self._ids = itertools.count(1)
        self._write_lock = threading.Lock()  # requests may come from several threads (the soak's)

    @property
    def process(self) -> subprocess.Popen[str] | None:
        return self.child.process if self.child is not None else None

    def start(self, timeout: float = 20.0) -> None:
        self.child = ChildProcess(self.argv, name="probe", stdin=subprocess.PIPE, log=self.log_path, log_stdout=False,
                                  cwd=Path(__file__).resolve().parent.parent, on_line=self._event)
        self.child.wait_ready(timeout)

    def _event(self, line: str | None) -> None:
        """One line of the probe's output (on the child's reader thread); None: its output ended."""
        if line is None:
            event: dict[str, Any] = {"ev": "exit", "t": time.time()}
        else:
            try:
                event = json.loads(line)
            except ValueError:  # its readiness line, or anything else that is not an event
                return
            if not isinstance(event, dict):
                return
        with self._cond:
            self.events.append(event)
            self._cond.notify_all()

    def wait_event(self, match: Callable[[dict[str, Any]], bool], timeout: float, what: str) -> dict[str, Any]:
        """The first event (seen so far or coming) that matches; TransportError naming ``what`` after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            seen = 0
            while True:
                for event in self.events[seen:]:
                    if match(event):
                        return event
                    if event["ev"] == "exit":
                        raise TransportError(f"the probe exited while waiting for {what}; see {self.log_path}")
                seen = len(self.events)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TransportError(f"timed out after {timeout:g} s waiting for {what}")
                self._cond.wait(left)

    def request(self, op: str, *, wait: float = 30.0, **fields: Any) -> Any:
        """Ask the probe (answer within ``wait`` s); returns its result or raises TransportError with its error."""
        if self.process is None or self.process.stdin is None or self.process.poll() is not None:
            raise TransportError("the probe is not running")
        with self._write_lock:
            rid = next(self._ids)
            self.process.stdin.write(json.dumps({"id": rid, "op": op, **fields}) + "\n")
            self.process.stdin.flush()
        reply = self.wait_event(lambda e: e["ev"] == "reply" and e.get("id") == rid, wait, f"the probe's {op}")
        if not reply["ok"]:
            raise TransportError(f"probe {op}: {reply['error']}")
        return reply["result"]

    def stop(self) -> None:
        child, self.child = self.child, None
        if child is None:
            return
        try:
            if child.process.stdin:
                child.process.stdin.close()  # end of requests: the probe closes its session and exits
            child.process.wait(5)
        except (OSError, subprocess.TimeoutExpired):
            child.stop(StopPolicy(sigint_timeout=2.0, sigterm_timeout=2.0))


# -- the robot on three hosts -------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RobotSettings:
    """The robot across namespaces ``onboard`` (service, onboard agent), ``remote``, ``robot2`` (the probe)."""

    workdir: Path
    level: float = 120.0  # constant illumination: only faults change the placement
    fps: float = 15.0
    prefer: str = "remote-first"  # the detector starts on the remote host, so failover is observable
    log_level: str = "INFO"
    agent_mode: str = "client"  # every message passes the router, as across machines (docs/deploy.md)
    subnet: str = "10.213.7"
    zenoh_runtime: str | None = ZENOH_RUNTIME  # None: Zenoh's default threads (the router stalls in a cut)
    profile: Mapping[str, Any] | None = None  # the camera's illumination profile; None: constant at ``level``
    fake_fc: bool = False
    standby: bool = False  # the onboard agent keeps a warm standby (--standby)


@dataclass
class DetectorProcess:
    pid: int
    ppid: int
    host: str
    instance: str


def _ancestors(pid: int) -> list[int]:
    """``pid``'s parent, its parent, ... (psutil); empty when it is gone."""
    import psutil

    try:
        return [p.pid for p in psutil.Process(pid).parents()]
    except psutil.Error:
        return []


def held_pool_members(procs: Sequence[DetectorProcess], named: Mapping[int, int], *, agents: set[int],
                      ancestors: Callable[[int], list[int]]) -> set[int]:
    """The pids among ``procs`` that are idle pool members held by a live agent: ``named`` (pid -> the pid
    of the launcher whose deployer named it idle) says so, and that launcher is among its ancestors with
    one of ``agents`` (the live agents' pids) as the launcher's parent. A process that only looks like one
    (a detector under a launcher that no deployer names, a member whose agent is gone) is not."""
    held = set()
    for d in procs:
        launcher = named.get(d.pid)
        if launcher is None:
            continue
        chain = ancestors(d.pid)
        if launcher in chain and chain.index(launcher) + 1 < len(chain) and chain[chain.index(launcher) + 1] in agents:
            held.add(d.pid)
    return held


class RobotOnHosts:
    """Network, cluster and probe, started together and always stopped together.

    ``start()`` raises TransportError (or KgadaptError) naming what failed;
    ``stop()`` undoes everything that was started, also after a failed start.
    """

    def __init__(self, settings: RobotSettings) -> None:
        from kgadapt.operator.cluster import ClusterSettings, HostNetwork, LocalCluster, NetworkSettings

        self.settings = settings
        self.network = HostNetwork(NetworkSettings(subnet=settings.subnet))
        profile = settings.workdir / "profile.json"
        self.cluster = LocalCluster(ClusterSettings(
            workdir=settings.workdir, robot=ROBOT, profile=str(profile), fps=settings.fps, prefer=settings.prefer,
            calibrate=False, fake_fc=settings.fake_fc, log_level=settings.log_level, agent_mode=settings.agent_mode,
            standby=settings.standby,
            env=(("ZENOH_RUNTIME", settings.zenoh_runtime),) if settings.zenoh_runtime else (),
        ), network=self.network)
        self.probe: ProbeHandle | None = None

    def start(self, timeout: float = 60.0) -> None:
        s = self.settings
        s.workdir.mkdir(parents=True, exist_ok=True)
        (s.workdir / "profile.json").write_text(json.dumps(
            s.profile or {"points": [[0, s.level], [3600, s.level]], "noise": 2.0, "gradient": 0.2}))
        try:
            self.network.setup()
            self.cluster.prepare_store()
            self.cluster.start()
            self.probe = ProbeHandle(self.network.run_in("robot2", [
                sys.executable, "-m", "kgadapt.bench.reliability_bench", "probe", "--robot", ROBOT,
                "--connect", self.cluster.endpoint, "--mode", "client"]), log_path=s.workdir / "probe.log")
            self.probe.start()
            self.wait_detecting(since=0.0, timeout=timeout)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        try:
            if self.probe is not None:
                self.probe.stop()
        finally:
            try:
                self.cluster.stop()
            finally:
                self.network.shutdown()

    def __enter__(self) -> "RobotOnHosts":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- what is going on ---------------------------------------------------------

    def wait_detecting(self, *, host: str | None = None, since: float, timeout: float) -> dict[str, Any]:
        """The first detections of a new detector instance (on ``host``) after ``since``."""
        assert self.probe is not None
        return self.probe.wait_event(
            lambda e: e["ev"] == "first_detection" and e["t"] >= since and (host is None or e["host"] == host),
            timeout, f"first detections of a new detector{' on ' + host if host else ''}")

    def live_detectors(self, timeout: float = 2.0) -> list[dict[str, Any]]:
        """Live detector processes as the deployers report them (asked from the second robot)."""
        assert self.probe is not None
        processes = self.probe.request("list", host="*", timeout=timeout, wait=timeout + 10)
        return [p for p in processes if p.get("state") in KEPT_STATES and str(p.get("config", "")).startswith(
            "marker_detection")]

    def detector_processes(self, *, pooled: bool = False) -> list[DetectorProcess]:
        """Detector programs running in our namespaces, found with psutil (not through the agents); the
        idle pool members a live agent's launcher holds (:meth:`held_members`) only with ``pooled``: they
        are no detector yet."""
        import psutil

        hosts = {self.network.inode(h): h for h in ("onboard", "remote")}
        found = []
        for p in psutil.process_iter(["pid", "ppid", "cmdline", "status"]):
            cmdline = p.info.get("cmdline") or []
            if DETECTOR_MODULE not in cmdline or p.info.get("status") == psutil.STATUS_ZOMBIE:  # exited, not reaped yet
                continue
            try:
                inode = os.stat(f"/proc/{p.info['pid']}/ns/net").st_ino
            except OSError:
                continue
            if inode in hosts:
                instance = cmdline[cmdline.index("--instance") + 1] if "--instance" in cmdline else "?"
                found.append(DetectorProcess(p.info["pid"], p.info["ppid"], hosts[inode], instance))
        if pooled:
            return found
        agents = self.agent_pids()
        strays = [d for d in found if d.ppid not in agents]  # a held member is never an agent's child
        held = self.held_members(strays) if strays else set()
        return [d for d in found if d.pid not in held]

    def agent_pids(self) -> set[int]:
        return {c.process.pid for n, c in self.cluster.children.items()
                if n in ("onboard", "remote") and c.process.poll() is None}

    def held_members(self, procs: Sequence[DetectorProcess]) -> set[int]:
        """The pids among ``procs`` of idle pool members (deploy/launcher.py) that a live agent holds: named
        idle by that agent's deployer (its ``list`` reply), and below that deployer's launcher, the
        agent's child, in the process tree. A detector that is neither an agent's child nor such a member
        is an orphan."""

        assert self.probe is not None
        try:
            launchers = self.probe.request("launchers", timeout=2.0, wait=12)
        except KgadaptError:  # no deployer answered: none holds a member
            launchers = {}
        named = {int(pid): int(launcher["pid"]) for launcher in launchers.values() if launcher.get("pid")
                 for pid in launcher.get("idle_members") or []}
        return held_pool_members(procs, named, agents=self.agent_pids(), ancestors=_ancestors)

    def orphans(self) -> list[DetectorProcess]:
        """Detector programs whose parent is not a live agent of this cluster, other than the idle pool
        members a live agent's launcher holds."""
        agents = self.agent_pids()
        return [d for d in self.detector_processes() if d.ppid not in agents]

    def active(self, window: float = 1.0) -> dict[str, dict[str, Any]]:
        """Instances whose detections the second robot received in the last ``window`` seconds."""
        assert self.probe is not None
        return self.probe.request("active", window=window)

    def platforms(self) -> dict[str, dict[str, Any]]:
        assert self.probe is not None
        return {r["platform"]: r for r in self.probe.request("query", name="platforms", params={})}

    def profile(self, instance: str) -> list[dict[str, Any]]:
        """The ProcessProfile rows of ``instance`` (one per run)."""
        assert self.probe is not None
        return self.probe.request(
            "cypher", cypher="MATCH (r:ProcessProfile) WHERE r.instance = $instance "
                             "RETURN r.name AS run_id, r.host AS host, r.start_time AS start_time, "
                             "r.end_time AS end_time, r.exit_status AS exit_status", params={"instance": instance})

    def detections_since(self, after: float, *, timeout: float) -> dict[str, float]:
        """Wait for detections received at or after ``after``; each instance's first such time."""
        assert self.probe is not None
        deadline = time.monotonic() + timeout
        while True:
            firsts = self.probe.request("since", after=after)
            if firsts:
                return firsts
            if time.monotonic() >= deadline:
                raise TransportError(f"no detections within {timeout:g} s after {after:.3f}")
            time.sleep(0.05)

    def pids(self) -> dict[str, int]:
        return {n: c.process.pid for n, c in self.cluster.children.items()}

    def settle(self, *, since: float = 0.0, timeout: float = 20.0) -> dict[str, Any]:
        """Wait until exactly one detector is live and detecting (after ``since``), and its process is the only one.

        Returns the deployer's snapshot of it.
        """
        deadline = time.monotonic() + timeout
        last = "nothing seen yet"
        while time.monotonic() < deadline:
            try:
                live = self.live_detectors()
                procs = self.detector_processes()
                active = self.active(1.0)
            except TransportError as exc:
                last = str(exc)
                time.sleep(0.2)
                continue
            recent = {k: v for k, v in active.items() if v["last"] >= max(since, time.time() - 0.6)}
            # The deployer's snapshot must name the process found: the three are read one after the other,
            # and a snapshot still "starting" (no run, no pid) may come before the process and its detections.
            if (len(live) == 1 and len(procs) == 1 and set(recent) == {live[0]["instance"]}
                    and live[0].get("pid") == procs[0].pid):
                return live[0]
            last = (f"live {[(p['instance'], p['host'], p['state'], p.get('pid')) for p in live]}, processes "
                    f"{[(d.instance, d.host, d.pid) for d in procs]}, detecting {sorted(recent)}")
            time.sleep(0.2)
        raise TransportError(f"no single detector settled within {timeout:g} s: {last}")

    # -- faults -------------------------------------------------------------------

    def kill_remote(self, *, timeout: float = 15.0) -> dict[str, Any]:
        """``kill -9`` of the remote agent while it runs the detector; time the failover."""
        before = self.settle()
        if before["host"] != "remote":
            raise KgadaptError(f"the detector runs on {before['host']}, not on the remote host")
        killed_at = time.time()
        self.cluster.kill("remote", signal.SIGKILL)
        first = self.wait_detecting(host="onboard", since=killed_at, timeout=timeout)
        remote_left = _wait_until(lambda: not [d for d in self.detector_processes() if d.host == "remote"], 5.0)
        return {"fault": "remote_death", "failover_ms": round((first["t"] - killed_at) * 1000.0, 1),
                "old_instance": before["instance"], "new_instance": first["instance"],
                "remote_detector_gone": remote_left}

    def partition(self, cut_s: float = 5.0, *, timeout: float = 20.0) -> dict[str, Any]:
        """Cut the remote host's link for ``cut_s`` seconds, restore it; time failover and heal."""
        assert self.probe is not None
        before = self.settle()
        if before["host"] != "remote":
            raise KgadaptError(f"the detector runs on {before['host']}, not on the remote host")
        pids = self.pids()
        twin = before["instance"]
        cut_at = self.network.cut("remote")
        try:
            first = self.wait_detecting(host="onboard", since=cut_at, timeout=timeout)
            lost = self.probe.wait_event(lambda e: e["ev"] == "alive" and e["host"] == "remote" and not e["up"]
                                         and e["t"] >= cut_at, timeout, "the remote host to be seen lost")
            twin_alive_in_cut = any(d.instance == twin for d in self.detector_processes())
            time.sleep(max(0.0, cut_at + cut_s - time.time()))
        finally:
            healed_at = self.network.heal("remote")
        back = self.probe.wait_event(lambda e: e["ev"] == "alive" and e["host"] == "remote" and e["up"]
                                     and e["t"] >= healed_at, timeout, "the remote host to be seen back")
        stopped = self.probe.wait_event(lambda e: e["ev"] == "deploy" and e["instance"] == twin
                                        and e["event"] in ENDED_EVENTS and e["t"] >= healed_at,
                                        timeout, f"the twin {twin} to be stopped")
        decision = self.probe.wait_event(lambda e: e["ev"] == "decision" and e.get("kind") == TriggerKind.HOST_BACK
                                         and e["t"] >= healed_at, timeout, "the adaptation manager's host_back decision")
        # remote-first: once the twin is gone, a planned migration brings the detector back.
        returned = self.probe.wait_event(lambda e: e["ev"] == "decision" and e.get("kind") == TriggerKind.HOST_BACK
                                         and str(e.get("outcome", "")).startswith("migrated") and e["t"] >= healed_at,
                                         timeout, "the detector to move back to the preferred remote host")
        after = self.settle()
        graph_ok = _wait_until(lambda: self._graph_healed(twin), 10.0)
        platforms = self.platforms()
        return {
            "fault": "partition", "cut_s": round(healed_at - cut_at, 2),
            "failover_ms": round((first["t"] - cut_at) * 1000.0, 1),
            "lost_seen_ms": round((lost["t"] - cut_at) * 1000.0, 1),
            "rejoin_ms": round((back["t"] - healed_at) * 1000.0, 1),
            "heal_ms": round((stopped["t"] - healed_at) * 1000.0, 1),
            "twin": twin, "twin_ran_during_cut": twin_alive_in_cut, "twin_event": stopped["event"],
            "host_back_outcome": decision.get("outcome"),
            "returned_ms": round((returned["t"] - healed_at) * 1000.0, 1),
            "running_after": after["instance"], "running_host_after": after["host"],
            "graph_healed": graph_ok,
            "online": {h: bool(r.get("online")) for h, r in platforms.items()},
            "twin_profile": self.profile(twin),
            "restarted": sorted(n for n, pid in self.pids().items() if pids.get(n) != pid),
            "orphans": len(self.orphans()),
        }

    def _graph_healed(self, twin: str) -> bool:
        platforms = self.platforms()
        online = all(platforms.get(h, {}).get("online") for h in ("onboard", "remote"))
        return online and all(r.get("end_time") is not None for r in self.profile(twin))

    def kill_store_and_remote(self, *, timeout: float = 30.0) -> dict[str, Any]:
        """``kill -9`` of the knowledge store's server and of the remote agent at once; time the failover.

        The planner's queries fail until the knowledge service has its store back,
        so the failover only happens if the adaptation manager tries again.
        """
        before = self.settle()
        if before["host"] != "remote":
            raise KgadaptError(f"the detector runs on {before['host']}, not on the remote host")
        info = self.settings.workdir / "store" / "server.json"
        try:
            store_pid = int(json.loads(info.read_text())["pid"])
        except (OSError, ValueError, KeyError) as exc:
            raise KgadaptError(f"cannot find the knowledge store's server in {info}: {exc}") from exc
        killed_at = time.time()
        os.kill(store_pid, signal.SIGKILL)
        self.cluster.kill("remote", signal.SIGKILL)
        first = self.wait_detecting(host="onboard", since=killed_at, timeout=timeout)
        return {"fault": "store_and_remote_death", "failover_ms": round((first["t"] - killed_at) * 1000.0, 1),
                "new_instance": first["instance"]}

    def kill_detector(self, *, timeout: float = 30.0) -> dict[str, Any]:
        """``kill -9`` of the running detector process; time until a detector detects again.

        Its deployer sees the exit, the adaptation manager places a new one; the killed
        run's ProcessProfile must be closed and no second detector may be left.
        """
        before = self.settle()
        victims = [d for d in self.detector_processes() if d.instance == before["instance"]]
        if len(victims) != 1:
            raise KgadaptError(f"expected one process of {before['instance']}, found {victims}")
        killed_at = time.time()
        os.kill(victims[0].pid, signal.SIGKILL)
        assert self.probe is not None
        # The deployer may start the same instance again, so wait for its exit, then for detections.
        exited = self.probe.wait_event(lambda e: e["ev"] == "deploy" and e["instance"] == before["instance"]
                                       and e["event"] in ENDED_EVENTS and e["t"] >= killed_at,
                                       timeout, f"the deployer to see {before['instance']} exit")
        firsts = self.detections_since(exited["t"], timeout=timeout)
        after = self.settle(since=exited["t"], timeout=timeout)
        # The killed run's profile is closed: the old instance keeps an open one only if it runs again.
        still_open = 1 if after["instance"] == before["instance"] else 0
        closed = _wait_until(lambda: sum(r.get("end_time") is None for r in self.profile(before["instance"]))
                             == still_open, 10.0)
        return {"fault": "detector_kill", "host": victims[0].host, "old_instance": before["instance"],
                "new_instance": after["instance"], "new_host": after["host"], "exit_event": exited["event"],
                "resume_ms": round((min(firsts.values()) - killed_at) * 1000.0, 1),
                "profile_closed": closed, "orphans": len(self.orphans()), "running_after": after["instance"]}

    def restart_onboard(self, sig: int = signal.SIGTERM, *, timeout: float = 30.0) -> dict[str, Any]:
        """Stop the onboard agent with ``sig``, start it again, and see what became of its detector.

        ``resume_ms``: from the signal to the first detections after the restart (of the
        adopted detector, or of a new one).
        """
        assert self.probe is not None
        before = self.settle()
        agent = self.cluster.children["onboard"]
        signalled_at = time.time()
        self.cluster.kill("onboard", sig)
        agent.process.wait(timeout)
        stopped_ms = (time.time() - signalled_at) * 1000.0
        # The onboard detectors follow their agent by the parent-death signal, each after its own stop, which
        # may end just after the agent is reaped (seen once in a full test run): give them 5 s before looking,
        # so a detector still stopping is not taken for one left behind. One alive after 5 s is.
        _wait_until(lambda: not any(d.host == "onboard" for d in self.detector_processes(pooled=True)), 5.0)
        left = self.detector_processes()
        orphans_between = len(self.orphans())
        self.cluster.respawn("onboard")
        started_at = time.time()
        resumed = self.detections_since(started_at, timeout=timeout)
        after = self.settle(since=started_at, timeout=timeout)
        return {
            "fault": "onboard_restart", "signal": signal.Signals(sig).name,
            "before": before["instance"], "before_host": before["host"],
            "after": after["instance"], "after_host": after["host"],
            "outcome": "adopted" if after["instance"] == before["instance"] else "replaced",
            "detectors_while_down": [(d.instance, d.host) for d in left], "orphans_while_down": orphans_between,
            "orphans_after": len(self.orphans()), "agent_exit_ms": round(stopped_ms, 1),
            "resume_ms": round((min(resumed.values()) - signalled_at) * 1000.0, 1),
        }


def _wait_until(predicate: Callable[[], Any], timeout: float, interval: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout
    while True:
        try:
            if predicate():
                return True
        except KgadaptError:
            pass
        if time.monotonic() >= deadline:
            return False
        time.sleep(interval)


# -- bad inputs ---------------------------------------------------------------------------


def fuzz(session: Any, robot: str, *, examples: int = 20, hosts: Sequence[str] = ("onboard", "remote")
         ) -> dict[str, dict[str, Any]]:
    """Send hypothesis-generated malformed payloads to every kind of queryable; count the answers.

    Per target: ``error_reply`` (``reply_err``), ``refused`` (a deployer's ``ok: false``),
    ``accepted`` (an ok reply to a malformed request), ``no_reply`` (nothing, or a timeout).
    Afterwards each target must still answer a good request (``healthy``).
    """
    try:
        import msgpack
        from hypothesis import HealthCheck, given, settings
        from hypothesis import strategies as st
    except ImportError as exc:
        raise ConfigError(f"bad-input trials need hypothesis (pip install kgadapt[test]): {exc}") from exc
    from kgadapt.shared import keys, messages, rpc
    from kgadapt.shared.errors import RemoteError, RequestTimeout

    good = {
        "query_request": {"params": {"feature": "MarkerDetection"}},
        "cypher_request": {"cypher": "RETURN $x AS x", "params": {"x": 1}},
        "write_request": {"params": {"name": "fuzzed", "time": 1.0, "memory_free_mb": 10.0}},
        # A start that names nothing the store knows: even a "good" one runs nothing.
        "deploy_request": {"deployment": "no_such_deployment", "config": "no_such_config", "wait_ready": False},
    }
    any_value = st.one_of(st.integers(-(2**63), 2**63 - 1), st.floats(), st.text(max_size=20), st.binary(max_size=20),
                          st.lists(st.integers(), max_size=3), st.booleans(), st.none())

    def wire(kind: str) -> dict[str, Any]:
        return {"kind": kind, "v": messages.version_of(messages.KINDS[kind]), **good[kind]}

    def packed(body: Any) -> bytes:
        return msgpack.packb(body, use_bin_type=True)

    def malformed(kind: str, *, deployer: bool) -> Any:
        data = packed(wire(kind))
        fields = sorted(set(messages.KINDS[kind].__struct_fields__) - {"v"})
        limit = messages.KINDS[kind].MAX_SIZE
        strategies = [
            st.binary(min_size=1, max_size=300),
            st.integers(1, len(data) - 1).map(lambda n: data[:n]),
            st.tuples(st.sampled_from(fields), any_value).map(lambda kv: packed({**wire(kind), kv[0]: kv[1]})),
            st.sampled_from(sorted(set(messages.KINDS) - {kind})).map(lambda o: packed({**wire(kind), "kind": o})),
            st.integers(2, 99).map(lambda v: packed({**wire(kind), "v": v})),
            st.just(packed([wire(kind)])),
            st.integers(limit + 1, limit + 2048).map(lambda n: packed({**wire(kind), "padding": "x" * n})),
        ]
        if deployer:  # messages keep extra fields; a deployer refuses any that would say how to run something
            strategies.append(st.sampled_from(["command", "executable", "argv", "env"]).map(
                lambda f: packed({**wire(kind), f: "/bin/sh -c 'touch /tmp/pwned'"})))
        return st.one_of(*strategies)

    root = keys.robot_root(robot)
    targets = [(f"{root}/knowledge/query/placement", "query_request"), (f"{root}/knowledge/cypher", "cypher_request"),
               (f"{root}/knowledge/write/platform", "write_request")]
    for host in hosts:
        for verb in ("start", "stop", "list"):
            targets.append((keys.deployer_verb(robot, host, verb), "deploy_request"))

    def ask(key: str, payload: bytes) -> str:
        try:
            body = rpc.call(session, key, payload, bytes, timeout=5)
        except RemoteError:
            return "error_reply"
        except RequestTimeout:  # NoResponder included
            return "no_reply"
        if "/deployer/" in key:
            try:
                return "refused" if not messages.decode(body, "deploy_reply")["ok"] else "accepted"
            except KgadaptError:
                return "accepted"
        return "accepted"

    results: dict[str, dict[str, Any]] = {}
    for key, kind in targets:
        counts: dict[str, Any] = {"sent": 0, "error_reply": 0, "refused": 0, "accepted": 0, "no_reply": 0,
                                  "accepted_examples": []}

        @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(payload=malformed(kind, deployer="/deployer/" in key))
        def send(payload: bytes) -> None:
            counts["sent"] += 1
            outcome = ask(key, payload)
            counts[outcome] += 1
            if outcome == "accepted" and len(counts["accepted_examples"]) < 3:
                counts["accepted_examples"].append(repr(payload[:80]))

        send()
        outcome = ask(key, packed(wire(kind)))
        counts["healthy"] = int(outcome == "accepted" or ("/deployer/" in key and outcome == "refused"))
        results[key.removeprefix(root + "/")] = counts
    return results


# -- the bench ----------------------------------------------------------------------------


def register(bench_subparsers: Any) -> None:
    parser = bench_subparsers.add_parser(
        "reliability", help="faults across real hosts: store kill -9, remote death, partition, agent restart",
        description="Inject real faults and count what happened: kill -9 of the store during a burst of writes; "
        "with hosts as network namespaces (root), kill -9 of the remote agent, a cut link, restarts of the "
        "onboard agent, and malformed requests from another robot. Results to bench/results/reliability.json.")
    parser.add_argument("--store-trials", type=int, default=20, metavar="N",
                        help="store kill -9 trials, restarted by the server's owner (default 20)")
    parser.add_argument("--store-self-trials", type=int, default=2, metavar="N",
                        help="store kill -9 trials where the store restarts its server itself (default 2)")
    parser.add_argument("--failover-trials", type=int, default=2, metavar="N",
                        help="kill -9 of the remote agent (default 2)")
    parser.add_argument("--partition-trials", type=int, default=2, metavar="N", help="link cuts (default 2)")
    parser.add_argument("--restart-trials", type=int, default=1, metavar="N",
                        help="onboard agent restarts per signal, SIGTERM and SIGKILL (default 1)")
    parser.add_argument("--compound-trials", type=int, default=1, metavar="N",
                        help="kill -9 of the knowledge store and the remote agent at once (default 1)")
    parser.add_argument("--detector-trials", type=int, default=2, metavar="N",
                        help="kill -9 of the running detector process (default 2)")
    parser.add_argument("--cut", type=float, default=5.0, metavar="S", help="length of a link cut (default 5 s)")
    parser.add_argument("--fuzz", type=int, default=25, metavar="N",
                        help="malformed payloads per queryable (default 25; 0: none)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the store trials' kill points")
    parser.add_argument("--workdir", default=None, help="where logs and stores go (default: a temporary directory)")
    parser.add_argument("--out", default=str(RESULTS), help=f"results file (default {RESULTS})")
    parser.add_argument("--markdown", action="store_true", help="print the summary as a Markdown table")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    from kgadapt.bench.stats import machine_info
    from kgadapt.operator.cluster import HostNetwork

    for name in ("store_trials", "store_self_trials", "failover_trials", "partition_trials", "restart_trials",
                 "compound_trials", "detector_trials", "fuzz"):
        if getattr(args, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')} {getattr(args, name)}: use 0 or more")
    if args.cut <= 0:
        raise ConfigError(f"--cut {args.cut}: use a positive number of seconds")
    keep = args.workdir is not None
    workdir = Path(args.workdir) if keep else Path(tempfile.mkdtemp(prefix="kgadapt-reliability-"))
    say = _say(quiet=args.json)
    report: dict[str, Any] = {"machine": machine_info(), "time": time.time(), "trials": {}, "skipped": {}}
    try:
        report["trials"]["store_crash"] = trials = []
        modes = [("owner", i) for i in range(args.store_trials)] + [("store", i) for i in range(args.store_self_trials)]
        for mode, trial in modes:
            settings = StoreCrashSettings(restart=mode)
            trials.append(store_crash_trial(workdir / f"store-{mode}-{trial}", trial=trial, seed=args.seed,
                                            settings=settings))
            r = trials[-1]
            say(f"store kill -9 ({mode} restarts) {trial + 1}: {r['acked']} acknowledged, {r['lost']} lost, "
                f"restart {r['restart_ms']} ms, outage {r['outage_ms']} ms")
        wants_hosts = (args.failover_trials + args.partition_trials + args.restart_trials + args.compound_trials
                       + args.detector_trials + (args.fuzz > 0))
        reason = HostNetwork.unavailable_reason() if wants_hosts else None
        if reason:
            report["skipped"]["namespaces"] = reason
            say(f"namespace trials skipped: {reason}")
        elif wants_hosts:
            _host_trials(args, workdir / "hosts", report, say)
    finally:
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
    report["summary"] = summarize(report)
    report["totals"] = totals(report)
    out = write_report(Path(args.out), report)
    say(f"wrote {out}")
    if args.json:
        print(json.dumps({"totals": report["totals"], "summary": report["summary"]}, indent=1))
    else:
        print(summary_table(report["summary"], markdown=args.markdown))
        print(", ".join(f"{k.replace('_', ' ')} {v}" for k, v in report["totals"].items()))
    return 0


def _host_trials(args: argparse.Namespace, workdir: Path, report: dict[str, Any], say: Callable[[str], None]) -> None:
    trials = report["trials"]
    for name in ("remote_death", "partition", "onboard_restart", "store_and_remote_death", "detector_kill",
                 "bad_inputs"):
        trials[name] = []
    robot = RobotOnHosts(RobotSettings(workdir=workdir))
    with robot:
        say(f"robot up in network namespaces {robot.network.settings.tag}: service {robot.cluster.endpoint}")
        for i in range(args.partition_trials):
            trials["partition"].append(_attempt(lambda: robot.partition(args.cut)))
            say(f"partition {i + 1}: {_brief(trials['partition'][-1], 'failover_ms', 'heal_ms')}")
            _back_to_remote(robot)
        for i in range(args.failover_trials):
            trials["remote_death"].append(_attempt(robot.kill_remote))
            say(f"remote kill -9 {i + 1}: {_brief(trials['remote_death'][-1], 'failover_ms')}")
            robot.cluster.respawn("remote")
            _back_to_remote(robot)
        for i in range(args.restart_trials):
            for sig in (signal.SIGTERM, signal.SIGKILL):
                trials["onboard_restart"].append(_attempt(lambda: robot.restart_onboard(sig)))
                say(f"onboard restart ({signal.Signals(sig).name}) {i + 1}: "
                    f"{_brief(trials['onboard_restart'][-1], 'outcome', 'resume_ms')}")
        for i in range(args.compound_trials):
            trials["store_and_remote_death"].append(_attempt(robot.kill_store_and_remote))
            say(f"store and remote kill -9 {i + 1}: {_brief(trials['store_and_remote_death'][-1], 'failover_ms')}")
            robot.cluster.respawn("remote")
            _back_to_remote(robot)
        for i in range(args.detector_trials):
            trials["detector_kill"].append(_attempt(robot.kill_detector))
            say(f"detector kill -9 {i + 1}: {_brief(trials['detector_kill'][-1], 'resume_ms', 'new_host')}")
            _back_to_remote(robot)
        if args.fuzz:
            pids = robot.pids()
            result = _attempt(lambda: {"targets": robot.probe.request("fuzz", wait=900, examples=args.fuzz)})
            alive = {n: robot.cluster.children[n].process.poll() is None for n in pids}
            result["processes_alive"] = alive
            trials["bad_inputs"].append(result)
            say(f"bad inputs: {sum(t['sent'] for t in result.get('targets', {}).values())} sent; "
                f"processes alive: {alive}")


def _back_to_remote(robot: RobotOnHosts) -> None:
    """Start the next trial with the detector on the remote host: a clean restart of the onboard agent."""
    robot.settle()
    if robot.live_detectors()[0]["host"] != "remote":
        robot.restart_onboard(signal.SIGTERM)


def _attempt(fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    try:
        return fn()
    except KgadaptError as exc:  # a failed trial is a result, not the end of the bench
        return {"error": str(exc)}


def _brief(result: dict[str, Any], *fields: str) -> str:
    if "error" in result:
        return f"FAILED: {result['error'][:200]}"
    return ", ".join(f"{f} {result.get(f)}" for f in fields)


def summarize(report: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per fault: trials, failures, and the figures that matter."""
    from kgadapt.bench.stats import percentile

    rows: list[dict[str, Any]] = []
    trials = report["trials"]

    def times(results: list[dict[str, Any]], name: str) -> tuple[float | None, float | None]:
        values = [float(r[name]) for r in results if r.get(name) is not None]
        return (round(percentile(values, 50), 1), round(max(values), 1)) if values else (None, None)

    for mode, fault, field, timed in (
            ("owner", "store kill -9 during writes", "restart_ms", "restart to first answer (AOF replayed)"),
            ("store", "store kill -9, store restarts it", "outage_ms", "kill to next acknowledged write")):
        store = [r for r in trials.get("store_crash") or [] if r.get("restart") == mode]
        if store:
            p50, worst = times(store, field)
            rows.append({"fault": fault, "trials": len(store),
                         "failed": sum(1 for r in store if r.get("lost") or not r.get("killed")),
                         "measure": "acknowledged writes lost", "value": f"{sum(r['lost'] for r in store)} of "
                         f"{sum(r['acked'] for r in store)}", "p50_ms": p50, "max_ms": worst, "timed": timed})
    death = trials.get("remote_death") or []
    if death:
        p50, worst = times(death, "failover_ms")
        rows.append({"fault": "remote agent kill -9", "trials": len(death),
                     "failed": sum(1 for r in death if "error" in r or not r.get("remote_detector_gone")),
                     "measure": "detector onboard again", "value": f"{sum(1 for r in death if 'error' not in r)} "
                     f"of {len(death)}", "p50_ms": p50, "max_ms": worst,
                     "timed": "kill to first detections onboard"})
    cut = trials.get("partition") or []
    if cut:
        ok = [r for r in cut if "error" not in r and r.get("graph_healed") and not r.get("restarted")
              and not r.get("orphans")]
        for name, what in (("failover_ms", "cut to first detections onboard"),
                           ("heal_ms", "link up to the remote twin stopped"),
                           ("rejoin_ms", "link up to the remote host seen alive")):
            p50, worst = times(cut, name)
            rows.append({"fault": f"link cut {cut[0].get('cut_s', '?')} s" if "error" not in cut[0] else "link cut",
                         "trials": len(cut), "failed": len(cut) - len(ok), "measure": "one detector, graph right",
                         "value": f"{len(ok)} of {len(cut)}", "p50_ms": p50, "max_ms": worst, "timed": what})
    both = trials.get("store_and_remote_death") or []
    if both:
        p50, worst = times(both, "failover_ms")
        rows.append({"fault": "store and remote agent kill -9 at once", "trials": len(both),
                     "failed": sum(1 for r in both if "error" in r), "measure": "detector onboard again",
                     "value": f"{sum(1 for r in both if 'error' not in r)} of {len(both)}", "p50_ms": p50,
                     "max_ms": worst, "timed": "kill to first detections onboard"})
    killed = trials.get("detector_kill") or []
    if killed:
        p50, worst = times(killed, "resume_ms")
        good = [r for r in killed if "error" not in r and r.get("profile_closed") and not r.get("orphans")]
        rows.append({"fault": "detector kill -9", "trials": len(killed), "failed": len(killed) - len(good),
                     "measure": "one detector again, profile closed", "value": f"{len(good)} of {len(killed)}",
                     "p50_ms": p50, "max_ms": worst, "timed": "kill to first detections again"})
    restart = trials.get("onboard_restart") or []
    for sig in ("SIGTERM", "SIGKILL"):
        runs = [r for r in restart if r.get("signal") == sig]
        if runs:
            p50, worst = times(runs, "resume_ms")
            good = [r for r in runs if not r.get("orphans_after") and "error" not in r]
            rows.append({"fault": f"onboard agent {sig} + restart", "trials": len(runs),
                         "failed": len(runs) - len(good), "measure": "outcome, orphans",
                         "value": ", ".join(sorted({r.get('outcome', '?') for r in runs})) + ", 0 orphaned"
                         if len(good) == len(runs) else f"{len(runs) - len(good)} with orphans or errors",
                         "p50_ms": p50, "max_ms": worst, "timed": "signal to detections again"})
    bad = trials.get("bad_inputs") or []
    for result in bad:
        targets = result.get("targets") or {}
        sent = sum(t["sent"] for t in targets.values())
        answered = {k: sum(t[k] for t in targets.values()) for k in ("error_reply", "refused", "accepted", "no_reply")}
        crashed = [n for n, alive in (result.get("processes_alive") or {}).items() if not alive]
        rows.append({"fault": "malformed requests from another robot", "trials": sent,
                     "failed": answered["accepted"] + answered["no_reply"] + len(crashed),
                     "measure": "error replies / refusals / accepted / silent / crashes",
                     "value": f"{answered['error_reply']} / {answered['refused']} / {answered['accepted']} / "
                     f"{answered['no_reply']} / {len(crashed)}", "p50_ms": None, "max_ms": None,
                     "timed": f"{len(targets)} queryables"})
    return rows


def totals(report: dict[str, Any]) -> dict[str, Any]:
    """Trials run, faults injected, writes acknowledged and lost, malformed requests and crashes."""
    trials = report["trials"]
    faults = {"store_crash": 1, "remote_death": 1, "partition": 1, "onboard_restart": 1, "store_and_remote_death": 2,
              "detector_kill": 1}
    store = trials.get("store_crash") or []
    bad = [t for r in trials.get("bad_inputs") or [] for t in (r.get("targets") or {}).values()]
    return {
        "trials": sum(len(trials.get(name) or []) for name in faults),
        "faults_injected": sum(n * len(trials.get(name) or []) for name, n in faults.items()),
        "failed_trials": sum(1 for name in faults for r in trials.get(name) or [] if "error" in r or r.get("lost")),
        "acknowledged_writes": sum(r["acked"] for r in store),
        "acknowledged_writes_lost": sum(r["lost"] for r in store),
        "malformed_requests": sum(t["sent"] for t in bad),
        "malformed_answered_with_error_or_refusal": sum(t["error_reply"] + t["refused"] for t in bad),
        "crashed_processes": sum(1 for r in trials.get("bad_inputs") or []
                                 for alive in (r.get("processes_alive") or {}).values() if not alive),
    }


def summary_table(rows: list[dict[str, Any]], *, markdown: bool = False) -> str:
    from kgadapt.bench.stats import format_table

    header = ["fault", "trials", "failed", "measure", "value", "timed", "p50 ms", "max ms"]
    return format_table([[r["fault"], r["trials"], r["failed"], r["measure"], r["value"], r["timed"], r["p50_ms"],
                          r["max_ms"]] for r in rows], header, markdown=markdown)


def write_report(path: Path, report: dict[str, Any]) -> Path:
    """Write the report atomically (a reader never sees half a file)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(report, indent=1, default=str) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"cannot write results to {path}: {exc}") from exc
    return path


def _say(*, quiet: bool) -> Callable[[str], None]:
    def say(line: str) -> None:
        if not quiet:
            print(line, flush=True)
    return say


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["probe"]:
        return probe_main(argv[1:])
    print("usage: python -m kgadapt.bench.reliability_bench probe [--robot R] [--connect EP] [--mode M]; "
          "the bench itself is `kgadapt bench reliability`", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
