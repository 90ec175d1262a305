"""kgadapt is one package: every part installs under ``kgadapt.`` and finds its data through importlib.resources.

The folders stay at the top of the checkout (shared/, knowledge/, ...); pyproject.toml maps them to
kgadapt.shared, kgadapt.knowledge, ... and kgadapt/shared etc. link to them so that the checkout
has the installed layout. The wheel test builds a wheel of this checkout and installs it, without
dependencies and without an index, into a fresh virtualenv outside the checkout that borrows the
test environment's installed dependencies through a ``.pth`` line (the dependencies are not what is
tested, and installing them again would take minutes); it then runs there as a user would.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIG = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
PACKAGE_DIR: dict[str, str] = CONFIG["package-dir"]  # "kgadapt.shared" -> "shared"
TOPS = tuple(sorted(PACKAGE_DIR.values()))


def _package_folders() -> set[str]:
    found = {"kgadapt"}
    # Folders of the kgadapt folder itself (kgadapt/operator), not the links to the top-level parts.
    for init in (REPO / "kgadapt").rglob("__init__.py"):
        parts = init.parent.relative_to(REPO / "kgadapt").parts
        if parts and "__pycache__" not in parts and not (REPO / "kgadapt" / parts[0]).is_symlink():
            found.add(".".join(("kgadapt", *parts)))
    for name, folder in PACKAGE_DIR.items():
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO / folder).parts
            if "__pycache__" not in parts:
                found.add(".".join((name, *parts)))
    return found


def test_every_package_folder_is_installed_under_kgadapt():
    assert set(CONFIG["packages"]) == _package_folders()
    assert all(name.startswith("kgadapt.") and "/" not in folder for name, folder in PACKAGE_DIR.items())


def test_the_checkout_links_give_the_installed_layout():
    for name, folder in PACKAGE_DIR.items():
        link = REPO / "kgadapt" / name.removeprefix("kgadapt.")
        assert link.is_symlink() and os.readlink(link) == f"../{folder}", link


def _python_files() -> list[Path]:
    files = list((REPO / "kgadapt").glob("*.py"))  # kgadapt/shared etc. are the links to the folders below
    for top in ("tests", *TOPS):
        files += [p for p in (REPO / top).rglob("*.py") if "__pycache__" not in p.parts]
    return files


def test_no_module_imports_a_part_by_its_top_level_name():
    statement = re.compile(rf"^[ \t]*(?:from|import)[ \t]+(?:{'|'.join(TOPS)})\b.*", re.MULTILINE)
    wrong = [f"{path.relative_to(REPO)}: {m.group(0).strip()}" for path in _python_files()
             for m in statement.finditer(path.read_text())]
    assert wrong == [], "import them as kgadapt.<part>:\n" + "\n".join(wrong)


def _copy_source(target: Path) -> Path:
    target.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "results", "*.egg-info", "build")
    for part in ("pyproject.toml", "README.md", "kgadapt", *TOPS):
        source = REPO / part
        if source.is_dir():
            shutil.copytree(source, target / part, symlinks=True, ignore=ignore)
        else:
            shutil.copy2(source, target / part)
    return target


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A fresh virtualenv with the built wheel installed, and a directory outside the checkout to run in."""
    tmp = tmp_path_factory.mktemp("wheel")
    source = _copy_source(tmp / "src")
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-q",
                            "--disable-pip-version-check", "-w", str(tmp / "dist")],
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr[-3000:]
    wheel = next((tmp / "dist").glob("kgadapt-*.whl"))
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    site = next((venv / "lib").glob("python3*/site-packages"))
    # After the venv's own site-packages: the dependencies only (the test environment's .pth files,
    # the editable install's import hook among them, are not processed for a directory added this way).
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "zz_test_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(deps)))
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q",
                           "--disable-pip-version-check", "--no-deps", "--no-index", str(wheel)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    work = tmp / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "KGADAPT_STORE")}
    return venv, work, env


def _run(installed, *argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    venv, work, env = installed
    return subprocess.run([str(venv / "bin" / argv[0]), *argv[1:]], cwd=work, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_the_wheel_installs_nothing_but_kgadapt_at_the_top(installed):
    done = _run(installed, "python", "-c", "import shared")
    assert done.returncode == 1 and "No module named 'shared'" in done.stderr, done.stderr
    for top in TOPS:
        done = _run(installed, "python", "-c", f"import {top}")
        assert done.returncode == 1 and f"No module named '{top}'" in done.stderr, (top, done.stderr)
    venv = installed[0]
    done = _run(installed, "python", "-c", "import kgadapt.shared.errors as m, kgadapt.knowledge.importers as i; "
                                           "print(m.__file__); print(i.__file__)")
    assert done.returncode == 0, done.stderr
    assert all(Path(line).is_relative_to(venv) for line in done.stdout.split()), done.stdout


@pytest.mark.slow
def test_the_installed_wheel_finds_its_data_and_writes_results_where_it_runs(installed):
    done = _run(installed, "python", "-c", "from kgadapt.shared import resources as r; from kgadapt.sim import photos; "
                                           "print(r.models()); print(r.scenarios()); print(photos.PHOTO_DIR); "
                                           "print(r.results_dir().resolve())")
    assert done.returncode == 0, done.stderr
    models, scenarios, photographs, results = (Path(line) for line in done.stdout.split())
    assert models.is_relative_to(installed[0]) and (models / "deployments" / "detector_dusk.deploy").is_file()
    assert scenarios.is_relative_to(installed[0]) and (scenarios / "demo.json").is_file()
    assert scenarios.parent.name == "perception"  # the synthetic camera's profiles are perception's, not the simulator's
    assert photographs.is_relative_to(installed[0]) and (photographs / "contrib_img_00.jpg").is_file()
    assert results == installed[1] / "bench-results"  # not site-packages: the wheel has no bench/results


@pytest.mark.slow
def test_the_demo_queries_run_from_the_installed_wheel_outside_the_checkout(installed):
    done = _run(installed, "kgadapt", "demo", "--queries")
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"model files from {installed[0]}" in done.stdout, done.stdout[:500]
    assert "Fig. 4" in done.stdout and "Traceback" not in done.stderr


@pytest.mark.slow
def test_a_part_runs_as_a_module_of_the_installed_wheel(installed):
    for module in ("kgadapt.onboard.perception.detector", "kgadapt.sim.echo_detector"):
        done = _run(installed, "python", "-m", module, "--help")
        assert done.returncode == 0, (module, done.stderr)
        assert "usage:" in done.stdout, module


@pytest.mark.slow
def test_the_installed_wheel_runs_its_runtime_with_the_simulator_and_the_benchmarks_gone(installed):
    # As a robot's installation without sim/ and bench/ would: every runtime module, the synthetic camera
    # with the wheel's own profiles, the launcher's preloads, and the commands from the wheel's registry.
    from tests.test_layers import ABOVE, RUNTIME_CHECK, runtime_modules

    done = _run(installed, "python", "-c", f"ABOVE = {ABOVE!r}\nRUNTIME = {runtime_modules()!r}\n" + RUNTIME_CHECK)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-4000:]
    assert done.stdout.strip().endswith("modules; []"), done.stdout
    assert "needs kgadapt.sim.cli, which is not installed" in done.stderr
