"""A deployment description, whatever notation it was written in.

Both deployment notations (systemd service files and plain deployment files)
end here: a ``Deployment`` node (+ the label of its notation) that DEPLOYS one
perception graph or component and is EXECUTABLE_ON one or more platforms.
The executable and arguments may use only the deployer's placeholders
(docs/CONTRACTS.md); the deployer fills them in from its own knowledge.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import sys
from dataclasses import dataclass

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, Origin, ParsedModel, Ref
from kgadapt.shared.keys import DEFAULT_ROBOT

PLACEHOLDERS = ("python", "robot", "host", "instance", "config", "connect")
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_ENV = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


@dataclass
class DeploymentDraft:
    """What a deployment notation found, with the line of each part (for errors)."""

    name: str
    name_origin: Origin
    kind: str  # schema label: SYSTEMD_SERVICE_FILE | DEPLOYMENT_FILE
    command: list[str] | None = None
    command_origin: Origin | None = None
    deploys: list[tuple[str, Origin]] | None = None
    platforms: list[tuple[str, Origin]] | None = None
    environment: list[tuple[str, Origin]] | None = None
    description: str | None = None
    # Deployments naming the same program family may take each other's configuration in
    # place (the running process reconfigured between two frames, no restart).
    reconfigurable_as: tuple[str, Origin] | None = None


def split_command(text: str, origin: Origin, what: str) -> list[str]:
    """Split a command line like a shell would (quotes respected, nothing expanded)."""
    try:
        words = shlex.split(text, comments=False, posix=True)
    except ValueError as exc:
        raise origin.error(f"{what}: {exc}") from exc
    if not words:
        raise origin.error(f"{what} is empty")
    return words


def check_name(name: str, origin: Origin, what: str) -> str:
    if not _NAME.match(name):
        raise origin.error(f"{what} {name!r} is not a valid name (letters, digits, _ . -)")
    return name


def check_placeholders(word: str, origin: Origin) -> None:
    for m in _PLACEHOLDER.finditer(word):
        if m.group(1) not in PLACEHOLDERS:
            raise origin.error(f"unknown placeholder {{{m.group(1)}}} in {word!r} "
                               f"(allowed: {', '.join('{' + p + '}' for p in PLACEHOLDERS)})")
    stray = _PLACEHOLDER.sub("", word)
    if "{" in stray or "}" in stray:
        raise origin.error(f"unbalanced brace in {word!r}")


def check_text(word: str, origin: Origin, what: str) -> None:
    # FalkorDB's Bolt listener splices string parameters into query text and so
    # refuses these; refusing them here keeps every store able to hold the model.
    if "'" in word or "\\" in word:
        raise origin.error(f"{what} {word!r} may not contain ' or \\")


# What the placeholders stand for when a command is tried at load time (check_runnable).
_SAMPLE = {"python": sys.executable, "robot": DEFAULT_ROBOT, "host": "onboard", "instance": "probe",
           "config": "probe", "connect": "tcp/127.0.0.1:7447"}


def check_runnable(command: list[str], origin: Origin) -> None:
    """Refuse now what would fail at start: a missing absolute executable, a module Python cannot
    find (``{python} -m MODULE``), or a ``kgadapt`` command line its parser refuses.

    A bare executable name is looked up on the target host's PATH at start; the loading
    host's PATH says nothing about it, so it is not checked here.
    """
    exe = command[0]
    if exe.startswith("/") and "{" not in exe and not (os.path.isfile(exe) and os.access(exe, os.X_OK)):
        raise origin.error(f"executable {exe!r} does not exist or is not executable")
    try:
        at = command.index("{python}")
    except ValueError:
        return
    if command[at + 1:at + 2] != ["-m"] or len(command) < at + 3:
        return
    module = command[at + 2]
    if "{" in module:
        return
    try:
        spec = importlib.util.find_spec(module)
        if spec is not None and spec.submodule_search_locations is not None:  # a package runs its __main__
            spec = importlib.util.find_spec(f"{module}.__main__")
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        raise origin.error(f"module {module!r} (run as {{python}} -m {module}) cannot be found by this Python")
    if module == "kgadapt":
        _check_kgadapt_arguments(command[at + 3:], origin)


def _check_kgadapt_arguments(words: list[str], origin: Origin) -> None:
    import contextlib
    import io

    from kgadapt.cli import build_parser

    argv = [_PLACEHOLDER.sub(lambda m: _SAMPLE[m.group(1)], w) for w in words]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as exc:
        if exc.code:
            why = err.getvalue().strip().splitlines()[-1:] or ["refused"]
            raise origin.error(why[0].replace("error: ", "", 1)) from None  # "kgadapt flight bridge: <what>"


def environment_entries(text: str, origin: Origin) -> list[str]:
    """``K=V K2="v 2"`` into ``["K=V", "K2=v 2"]``."""
    entries = split_command(text, origin, "environment")
    for entry in entries:
        if not _ENV.match(entry):
            raise origin.error(f"environment entry {entry!r} is not NAME=VALUE")
        if "{" in entry or "}" in entry:
            raise origin.error(f"environment entry {entry!r}: placeholders are allowed only in the command")
        check_text(entry, origin, "environment entry")
    return entries


def emit(model: ParsedModel, draft: DeploymentDraft, file_origin: Origin) -> None:
    """Check a finished draft and add its node and relations to ``model``."""
    if not draft.command:
        raise file_origin.error(f"deployment {draft.name} names no executable")
    if not draft.deploys:
        raise file_origin.error(f"deployment {draft.name} does not say what it deploys")
    if not draft.platforms:
        raise file_origin.error(f"deployment {draft.name} names no platform it is executable on")
    assert draft.command_origin is not None
    for word in draft.command:
        check_placeholders(word, draft.command_origin)
        check_text(word, draft.command_origin, "command word")
    check_runnable(draft.command, draft.command_origin)
    seen: set[str] = set()
    for platform, origin in draft.platforms:
        if platform in seen:
            raise origin.error(f"platform {platform!r} named twice")
        seen.add(platform)
    props = {
        "name": draft.name,
        "kind": draft.kind,
        "executable": draft.command[0],
        "arguments": draft.command[1:],
        "environment": [e for e, _ in draft.environment or []],
    }
    if draft.description:
        props["description"] = draft.description
    if draft.reconfigurable_as:
        props["reconfigurable_as"] = draft.reconfigurable_as[0]
    model.nodes.append(NodeSpec(S.DEPLOYMENT, draft.name, props, draft.name_origin, (draft.kind,)))
    me = Ref((S.DEPLOYMENT,), draft.name, "deployment")
    for target, origin in draft.deploys:
        model.edges.append(EdgeSpec(
            S.DEPLOYS, me, Ref((S.PERCEPTION_GRAPH, S.COMPONENT), target, "perception graph or component"), origin))
    for platform, origin in draft.platforms:
        model.edges.append(EdgeSpec(S.EXECUTABLE_ON, me, Ref((S.PLATFORM,), platform, "platform"), origin))


def name_list(text: str, origin: Origin, what: str) -> list[tuple[str, Origin]]:
    """``a, b c`` (commas or spaces) into checked names."""
    names = [n for n in re.split(r"[,\s]+", text.strip()) if n]
    if not names:
        raise origin.error(f"{what}: no name given")
    return [(check_name(n, origin, what), origin) for n in names]
