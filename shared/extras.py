"""Optional parts of kgadapt, installed as extras, imported only where needed.

The base install is what a drone runs (the onboard and remote agents); the
knowledge store, Memgraph client, plots, certificates and benchmarks are
extras (pyproject.toml). A command that needs one imports it through
:func:`require`, so a missing extra ends the command with one line that
names what to install, never an ImportError traceback.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from kgadapt.shared.errors import MissingExtra

# extra -> what it is for, as a command would name it
EXTRAS = {
    "store": "the knowledge store (embedded FalkorDB or a FalkorDB server)",
    "memgraph": "a Memgraph or other Bolt store",
    "plots": "drawing plots",
    "certs": "making TLS certificates",
    "bench": "the benchmarks",
}


def installed(module: str) -> bool:
    """Whether ``module`` imports (for what is optional, such as a default plot)."""
    try:
        importlib.import_module(module)
    except ModuleNotFoundError:
        return False
    return True


def require(module: str, *, extra: str, what: str | None = None) -> ModuleType:
    """Import ``module``; if it (or one of its own imports) is missing, raise :class:`MissingExtra`."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        raise MissingExtra(extra, what or EXTRAS[extra], exc.name or module) from exc
