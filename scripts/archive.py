"""Offline install archives: kgadapt's wheel, a wheelhouse of every dependency, an install script.

``make dist`` (``python scripts/archive.py``: a build script run in a checkout, not part of
the installed package) writes one archive per machine architecture, ``dist/kgadapt-VERSION-linux-ARCH.tar.gz``, holding::

    kgadapt-VERSION-linux-ARCH/
        install.sh        creates the virtualenv with pip --no-index, the user, directories, units
        wheelhouse/       kgadapt and every dependency, for each supported Python version
        systemd/          the units (install.sh points them at the virtualenv)
        zenoh/            router and host configurations
        README.txt

The wheelhouse holds the base (what the onboard and remote agents need) and
the ``store``, ``memgraph`` and ``certs`` extras, so that any host of the
robot can be installed from the same archive with no network; plots and
benchmarks stay out (a workstation installs ``kgadapt[all]`` from an index).
Before packing, each Python version's install is resolved offline from the
wheelhouse for the target platform (``pip install --dry-run --no-index``):
an archive that lacks a wheel is never written.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from kgadapt.shared.errors import ConfigError
from kgadapt.shared.resources import shipped

ROOT = Path(__file__).resolve().parents[1]
DIST = ROOT / "dist"
PYTHONS = ("3.11", "3.12", "3.13")
ARCHES = ("x86_64", "aarch64")
# Extras carried by the archive: every host role can be installed offline.
ARCHIVE_EXTRAS = ("store", "memgraph", "certs")
# manylinux tags pip should accept, newest glibc last (Raspberry Pi OS 12 and Ubuntu 22.04+ have glibc >= 2.35).
_GLIBC = ("2_17", "2_28", "2_31", "2_34", "2_35")


@dataclass(frozen=True, kw_only=True)
class ArchiveSettings:
    arch: str
    pythons: tuple[str, ...] = PYTHONS
    out: Path = DIST

    def __post_init__(self) -> None:
        if self.arch not in ARCHES:
            raise ConfigError(f"architecture {self.arch!r}: use one of {', '.join(ARCHES)}")
        for version in self.pythons:
            if version not in PYTHONS:
                raise ConfigError(f"Python {version!r}: kgadapt supports {', '.join(PYTHONS)}")


def version() -> str:
    import tomllib

    from kgadapt.bench.footprint import checkout

    return str(tomllib.loads((checkout() / "pyproject.toml").read_text())["project"]["version"])


def platform_flags(arch: str) -> list[str]:
    flags = ["--platform", f"manylinux2014_{arch}"]
    for glibc in _GLIBC:
        flags += ["--platform", f"manylinux_{glibc}_{arch}"]
    return flags


def _pip(*args: str, what: str) -> None:
    done = subprocess.run([sys.executable, "-m", "pip", *args, "--disable-pip-version-check"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        lines = [line for line in done.stderr.splitlines() if "is ignored: it is neither a file" not in line]
        raise ConfigError(f"{what} failed: {' '.join(lines)[-1500:]}")


def build_wheel(target: Path) -> Path:
    """kgadapt's own wheel (pure Python), built from this checkout."""
    with tempfile.TemporaryDirectory(prefix="kgadapt-wheel-") as tmp:
        from kgadapt.bench.footprint import copy_source

        source = copy_source(Path(tmp) / "src")
        _pip("wheel", "--no-deps", "-q", "-w", str(target), str(source), what="building kgadapt's wheel")
    wheels = sorted(target.glob("kgadapt-*.whl"))
    if not wheels:
        raise ConfigError(f"no kgadapt wheel appeared in {target}")
    return wheels[-1]


def fill_wheelhouse(wheelhouse: Path, own_wheel: Path, settings: ArchiveSettings) -> None:
    """Download every dependency's wheel for each Python version, then prove the install resolves offline."""
    requirement = f"{own_wheel}[{','.join(ARCHIVE_EXTRAS)}]"
    for py in settings.pythons:
        _pip("download", "-q", "--only-binary=:all:", *platform_flags(settings.arch), "--python-version", py,
             "--implementation", "cp", "-d", str(wheelhouse), requirement,
             what=f"downloading wheels for Python {py} on {settings.arch}")
    for py in settings.pythons:
        with tempfile.TemporaryDirectory(prefix="kgadapt-resolve-") as target:
            _pip("install", "--dry-run", "-q", "--no-index", "--find-links", str(wheelhouse), "--only-binary=:all:",
                 *platform_flags(settings.arch), "--python-version", py, "--implementation", "cp",
                 "--target", target, f"kgadapt[{','.join(ARCHIVE_EXTRAS)}]",
                 what=f"resolving the offline install for Python {py} on {settings.arch}")


def build(settings: ArchiveSettings, *, progress: Callable[[str], object] = print) -> Path:
    """Write ``dist/kgadapt-VERSION-linux-ARCH.tar.gz`` and return its path."""
    name = f"kgadapt-{version()}-linux-{settings.arch}"
    with tempfile.TemporaryDirectory(prefix="kgadapt-dist-") as tmp:
        root = Path(tmp) / name
        wheelhouse = root / "wheelhouse"
        wheelhouse.mkdir(parents=True)
        progress(f"{name}: building kgadapt's wheel")
        own = build_wheel(wheelhouse)
        progress(f"{name}: wheels for Python {', '.join(settings.pythons)}")
        fill_wheelhouse(wheelhouse, own, settings)
        shutil.copy2(shipped("kgadapt.deploy", "install", "install.sh"), root / "install.sh")
        (root / "install.sh").chmod(0o755)
        shutil.copytree(shipped("kgadapt.deploy", "systemd"), root / "systemd")
        shutil.copytree(shipped("kgadapt.deploy", "zenoh"), root / "zenoh")
        (root / "README.txt").write_text(_readme(name, settings))
        settings.out.mkdir(parents=True, exist_ok=True)
        archive = settings.out / f"{name}.tar.gz"
        partial = archive.with_name(archive.name + ".part")
        with tarfile.open(partial, "w:gz") as tar:
            tar.add(root, arcname=name)
        partial.replace(archive)
    progress(f"{archive} ({archive.stat().st_size / 2**20:.0f} MB)")
    return archive


def _readme(name: str, settings: ArchiveSettings) -> str:
    return f"""{name}: kgadapt for Linux {settings.arch}, Python {', '.join(settings.pythons)}, installable offline.

  sudo ./install.sh                     # onboard or remote host: the agents
  sudo ./install.sh --extras store      # the host that runs the knowledge service
  ./install.sh --help                   # every option (prefix, user, unit directory, ...)

Then follow docs/deploy.md, "Running on a quadcopter and a remote host".
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python scripts/archive.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", action="append", choices=ARCHES, help="architecture (repeatable; default: all)")
    parser.add_argument("--python", action="append", choices=PYTHONS, help="Python version (repeatable; default: all)")
    parser.add_argument("--out", type=Path, default=DIST, help="output directory (default %(default)s)")
    args = parser.parse_args(argv)
    try:
        for arch in args.arch or ARCHES:
            build(ArchiveSettings(arch=arch, pythons=tuple(args.python or PYTHONS), out=args.out))
    except ConfigError as exc:
        print(f"make dist: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
