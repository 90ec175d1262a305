"""Data files shipped inside the kgadapt package, found through :mod:`importlib.resources`.

The domain models (``knowledge/models``), the synthetic-camera scenarios
(``onboard/perception/scenarios``) and the
deployment files (``deploy/systemd``, ``deploy/zenoh``, ...) are package data
(pyproject.toml), so an installed wheel finds them where it installed them and
a source checkout finds them in its folders; nothing read depends on the current
directory or on a checkout. Where results are written by default is here too
(:func:`results_dir`). The runtime parts never reach into ``kgadapt.sim`` or
``kgadapt.bench`` (the layering test, tests/test_layers.py): the simulator finds its own data.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from kgadapt.shared.errors import ConfigError


def shipped(package: str, *parts: str) -> Path:
    """The file or folder ``parts`` of ``package`` (e.g. ``"kgadapt.knowledge", "models"``) as a path.

    The callers hand these paths to code that walks folders and to child processes, so the
    package must be installed as files (a wheel or an editable install, not a zip archive).
    """
    try:
        root = resources.files(package)
    except ModuleNotFoundError as exc:
        raise ConfigError(f"package {package!r} is not installed, so its data {'/'.join(parts)!r} cannot be found") \
            from exc
    target = root.joinpath(*parts)
    if not isinstance(target, Path):
        raise ConfigError(f"{package}: {'/'.join(parts)} is not on the file system ({target!r}); "
                          f"install kgadapt as files (pip install), not from a zip archive")
    if not target.exists():
        raise ConfigError(f"{package} ships no {'/'.join(parts)} (looked for {target}): a broken installation")
    return target


def models() -> Path:
    """The shipped domain models: the folder ``kgadapt knowledge load`` reads by default."""
    return shipped("kgadapt.knowledge", "models")


def scenarios() -> Path:
    """The shipped synthetic-camera scenarios (illumination profiles)."""
    return shipped("kgadapt.onboard.perception", "scenarios")


def results_dir() -> Path:
    """Where benchmarks and calibration write unless told otherwise (their ``--out``).

    In a source checkout that is ``bench/results``, where the figures are committed; an installed
    wheel has no such folder (and must not write into site-packages), so it is ``bench-results``
    in the current directory.
    """
    # By path, not through the kgadapt.bench package: the runtime does not import the benchmarks.
    checkout = Path(__file__).parents[1] / "bench" / "results"
    if checkout.is_dir():
        return checkout.resolve()  # bench/results, not the kgadapt/bench link to it
    return Path("bench-results")
