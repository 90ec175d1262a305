"""The ``kgadapt`` command: one entry point, subcommands registered by each part.

The registry is the package's entry-point group ``kgadapt.commands`` (pyproject.toml), read with
:mod:`importlib.metadata`: each entry names a command (``flight``, or ``flight fake-fc`` for a
subcommand that another part adds to ``flight``) and the function that adds it, called with the
parent's subparsers. A function that adds a command others extend returns its own subparsers.
The root imports no part itself, so the runtime never pulls in ``kgadapt.sim`` or
``kgadapt.bench`` (tests/test_layers.py); a part whose module is not installed (a runtime-only
installation without the simulator or the benchmarks) keeps its command, and running it is an
error naming the module, never a silently missing subcommand. Modules are imported only to
register; heavy imports (cv2, the store drivers) belong inside the functions, which run only for
the chosen subcommand. Any :class:`KgadaptError` ends the command with exit status 1 and one
line on stderr naming the problem.
"""

from __future__ import annotations

import argparse
import logging
import sys
from importlib import metadata
from typing import Any, Callable, Sequence, cast

from kgadapt.shared.errors import ConfigError, KgadaptError

GROUP = "kgadapt.commands"


def commands() -> list[metadata.EntryPoint]:
    """The registry: every command's entry point, parents before their subcommands, then by name."""
    found = sorted(metadata.entry_points(group=GROUP), key=lambda ep: (len(ep.name.split()), ep.name))
    if not found:
        raise ConfigError(f"no kgadapt commands are registered (entry points {GROUP!r}): "
                          "install kgadapt (pip install -e . in a checkout) to run it")
    return found


def _version() -> str:
    try:
        return metadata.version("kgadapt")
    except metadata.PackageNotFoundError:  # run from a checkout without installing
        return "(not installed)"


def _register(entry: metadata.EntryPoint) -> Callable[[Any], Any] | None:
    """The entry's function, or None when its module is not installed (any other import error propagates)."""
    try:
        return cast(Callable[[Any], Any], entry.load())
    except ModuleNotFoundError as exc:
        if exc.name and (entry.module == exc.name or entry.module.startswith(exc.name + ".")):
            return None
        raise


def _not_installed(parent: Any, name: str, entry: metadata.EntryPoint) -> None:
    """A command whose part is missing: listed, and an error naming the module when run."""
    message = f"command {entry.name!r} needs {entry.module}, which is not installed"

    def fail(args: argparse.Namespace) -> int:
        raise ConfigError(message)

    # No option prefix: every word after the command is taken, so the one line said is the missing module.
    stub = parent.add_parser(name, help=f"(not installed: {entry.module})", add_help=False, prefix_chars="\0")
    stub.add_argument("rest", nargs=argparse.REMAINDER)
    stub.set_defaults(func=fail)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kgadapt",
        description="Graph-based software knowledge for run-time adaptation of a quadcopter's marker detection.",
    )
    parser.add_argument("--log-level", default=None,
                        help="DEBUG, INFO, WARNING or ERROR (default: INFO for the long-running services and "
                             "agents, one line per decision, host change and process start/stop; WARNING for the rest)")
    parser.add_argument("--version", action="version", version=f"kgadapt {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    parents: dict[tuple[str, ...], Any] = {(): sub}
    for entry in commands():
        path = tuple(entry.name.split())
        parent = parents.get(path[:-1])
        if parent is None:
            raise ConfigError(f"command {entry.name!r} ({entry.value}): no command {' '.join(path[:-1])!r} takes "
                              "subcommands from other parts")
        register = _register(entry)
        if register is None:
            _not_installed(parent, path[-1], entry)
            continue
        added = register(parent)
        if path[-1] not in parent.choices:
            raise ConfigError(f"{entry.value} is registered as command {entry.name!r} but adds no such command")
        if added is not None:
            parents[path] = added
    return parser


def _long_running(args: argparse.Namespace) -> bool:
    """The commands a person leaves running and watches: they say what they decide and do."""
    sub = getattr(args, "knowledge_command", None) or getattr(args, "deploy_command", None)
    return args.command in ("onboard", "remote") or (args.command in ("knowledge", "deploy") and sub == "serve")


def main(argv: Sequence[str] | None = None) -> int:
    try:
        parser = build_parser()
    except KgadaptError as exc:  # e.g. an installation without its command registry
        print(f"kgadapt: error: {exc}", file=sys.stderr)
        return 1
    args = parser.parse_args(argv)
    if args.log_level is None:
        args.log_level = "INFO" if _long_running(args) else "WARNING"
    level = getattr(logging, str(args.log_level).upper(), None)
    if not isinstance(level, int):
        parser.error(f"--log-level {args.log_level!r}: use DEBUG, INFO, WARNING or ERROR")
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        status = args.func(args)
    except KgadaptError as exc:
        print(f"kgadapt: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (e.g. `| head`); not an error of ours.
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    return int(status or 0)
