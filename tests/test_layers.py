"""The layering: the runtime a drone installs never imports the simulator's stand-ins or the benchmarks.

Runtime is kgadapt.shared, .knowledge, .onboard, .remote, .deploy, .operator and the modules of the package root;
kgadapt.sim (fake flight controller, echo detector, photographs, landing check) and kgadapt.bench sit
above it. import-linter checks every import statement, those inside functions too (pyproject.toml's
[tool.importlinter]); the last test runs the runtime with the simulator and the benchmarks made
impossible to import, which also catches an import by name (importlib, importlib.resources).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONTRACTS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
ABOVE = ("kgadapt.sim", "kgadapt.bench")


def _contract() -> dict:
    (found,) = [c for c in CONTRACTS if c["id"] == "runtime-without-sim-and-bench"]
    return found


def test_the_contract_names_every_runtime_part_and_module_of_the_root():
    contract = _contract()
    assert sorted(contract["forbidden_modules"]) == sorted(ABOVE)
    root = REPO / "kgadapt"
    runtime = {f"kgadapt.{p.stem}" for p in root.glob("*.py") if p.stem != "__init__"}
    runtime |= {f"kgadapt.{p.name}" for p in root.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    runtime -= set(ABOVE)
    assert runtime - set(contract["source_modules"]) == set(), "a runtime module the layering test does not check"


def test_no_runtime_module_imports_sim_or_bench():
    tool = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    if tool is None:
        pytest.fail("import-linter is not installed: pip install -e '.[test]'")
    done = subprocess.run([tool, "--no-cache", "--contract", _contract()["id"]], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "1 kept, 0 broken" in done.stdout


RUNTIME_CHECK = """
import importlib, importlib.abc, pkgutil, sys

class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name in ABOVE or name.startswith(tuple(p + "." for p in ABOVE)):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NotInstalled())
import kgadapt
imported = 0
for part in RUNTIME:
    package = importlib.import_module(part)
    modules = [part] + [m.name for m in pkgutil.walk_packages(getattr(package, "__path__", []), part + ".")]
    for name in modules:
        importlib.import_module(name)
        imported += 1

# What a host's launcher preloads to fork detectors: runtime detectors only.
from kgadapt.deploy.launcher import PRELOAD
for name in PRELOAD:
    importlib.import_module(name)

# The synthetic camera and the synthetic scene calibration renders, with the shipped demo profile.
from kgadapt.onboard.perception.camera import SyntheticSource
from kgadapt.shared.resources import results_dir
source = SyntheticSource()
source.open()
frame = source.read()
assert frame is not None and frame.gray.shape[:2] == (480, 640) and len(frame.truth) >= 1, frame
results_dir()

from kgadapt.cli import main
assert main(["flight", "fake-fc", "--armed"]) == 1  # listed, and an error naming the missing module
assert main(["bench", "table1", "--full"]) == 1
try:
    main(["onboard", "--help"])
except SystemExit as exc:
    assert exc.code == 0
print("imported", imported, "modules;", [m for m in sys.modules if m.startswith(ABOVE)])
"""


def runtime_modules() -> list[str]:
    """The runtime's packages and root modules, as the contract names them (``__main__`` would run the command)."""
    return [m for m in _contract()["source_modules"] if m != "kgadapt.__main__"]


@pytest.mark.slow
def test_the_runtime_runs_with_the_simulator_and_the_benchmarks_not_installed():
    code = f"ABOVE = {ABOVE!r}\nRUNTIME = {runtime_modules()!r}\n" + RUNTIME_CHECK
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-4000:]
    assert done.stdout.strip().endswith("modules; []"), done.stdout
    assert "needs kgadapt.sim.cli, which is not installed" in done.stderr
    assert "needs kgadapt.bench.cli, which is not installed" in done.stderr
    assert "usage: kgadapt onboard" in done.stdout
