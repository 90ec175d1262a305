"""Deployments as systemd service files (``.service``).

An ordinary unit file; the deployment is named after the file (``detector_day.service``
is deployment ``detector_day``) and the kgadapt facts systemd does not know go
into an ``[X-Kgadapt]`` section, which systemd ignores::

    [Unit]
    Description=ArUco marker detector, daylight configuration

    [Service]
    ExecStart={python} -m kgadapt.onboard.perception.detector --robot {robot} --host {host} --instance {instance} \\
              --config {config} --connect {connect}
    Environment=OPENCV_LOG_LEVEL=ERROR
    Restart=on-failure

    [X-Kgadapt]
    Deploys=marker_detection_day
    ExecutableOn=onboard remote
    ReconfigurableAs=marker-detector

    [Install]
    WantedBy=multi-user.target

``ExecStart`` gives the executable and its arguments (split like a shell,
placeholders as in docs/CONTRACTS.md; a real unit gets them filled in by the
deployer). ``Environment=`` may repeat. Other keys of ``[Unit]``, ``[Service]``
and ``[Install]`` are systemd's own and are kept out of the graph. ``ReconfigurableAs=``: see
:mod:`kgadapt.knowledge.importers.deployment_file`.
"""

from __future__ import annotations

from pathlib import Path

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import deployment as D
from kgadapt.knowledge.importers.model import Origin, ParsedModel

NOTATION = "systemd service file"
SECTIONS = ("Unit", "Service", "Install", "X-Kgadapt")
KGADAPT_KEYS = ("Name", "Deploys", "ExecutableOn", "ReconfigurableAs")


def parse(text: str, path: str) -> ParsedModel:
    """Read one ``.service`` file (raises ModelError naming file and line)."""
    model = ParsedModel(path=path, notation=NOTATION)
    top = Origin(path, 1)
    draft = D.DeploymentDraft(name=D.check_name(Path(path).stem, top, "deployment (file name)"),
                              name_origin=top, kind=S.SYSTEMD_SERVICE_FILE)
    section: str | None = None
    seen_sections: set[str] = set()
    for number, line in _logical_lines(text):
        origin = Origin(path, number)
        stripped = line.strip()
        if not stripped or stripped[0] in "#;":
            continue
        if stripped.startswith("["):
            if not stripped.endswith("]"):
                raise origin.error(f"section header {stripped!r} has no closing ']'")
            section = stripped[1:-1]
            if section not in SECTIONS:
                raise origin.error(f"unknown section [{section}] (known: {', '.join('[' + s + ']' for s in SECTIONS)})")
            if section in seen_sections:
                raise origin.error(f"section [{section}] appears twice")
            seen_sections.add(section)
            continue
        if "=" not in stripped:
            raise origin.error(f"unknown statement {stripped!r} (expected KEY=VALUE or [Section])")
        key, value = (part.strip() for part in stripped.split("=", 1))
        if not key:
            raise origin.error("a line starts with '=': the key is missing")
        if section is None:
            raise origin.error(f"{key}= before any [Section]")
        _entry(draft, section, key, value, origin)
    if "Service" not in seen_sections:
        raise top.error("no [Service] section")
    if "X-Kgadapt" not in seen_sections:
        raise top.error("no [X-Kgadapt] section: say what this unit Deploys= and where it is ExecutableOn=")
    D.emit(model, draft, top)
    return model


def _entry(draft: D.DeploymentDraft, section: str, key: str, value: str, origin: Origin) -> None:
    if section == "Service" and key == "ExecStart":
        if draft.command is not None:
            raise origin.error("ExecStart= given twice (one process per deployment)")
        if value[:1] in "-@+!:":
            raise origin.error(f"ExecStart= prefix {value[0]!r} is not supported here")
        draft.command = D.split_command(value, origin, "ExecStart")
        draft.command_origin = origin
    elif section == "Service" and key == "Environment":
        draft.environment = (draft.environment or []) + [(e, origin) for e in D.environment_entries(value, origin)]
    elif section == "Unit" and key == "Description":
        D.check_text(value, origin, "Description")
        draft.description = value
    elif section == "X-Kgadapt":
        if key not in KGADAPT_KEYS:
            raise origin.error(f"unknown key {key}= in [X-Kgadapt] (known: {', '.join(KGADAPT_KEYS)})")
        if key == "Name":
            draft.name = D.check_name(value, origin, "Name=")
            draft.name_origin = origin
        elif key == "Deploys":
            if draft.deploys is not None:
                raise origin.error("Deploys= given twice")
            draft.deploys = D.name_list(value, origin, "Deploys=")
        elif key == "ReconfigurableAs":  # program family: see deployment_file.py
            if draft.reconfigurable_as is not None:
                raise origin.error("ReconfigurableAs= given twice")
            draft.reconfigurable_as = (D.check_name(value, origin, "ReconfigurableAs="), origin)
        else:
            if draft.platforms is not None:
                raise origin.error("ExecutableOn= given twice")
            draft.platforms = D.name_list(value, origin, "ExecutableOn=")
    # every other key of [Unit], [Service], [Install] belongs to systemd


def _logical_lines(text: str) -> list[tuple[int, str]]:
    """Join lines ending in a backslash, as systemd does; keep the first line's number."""
    out: list[tuple[int, str]] = []
    pending: list[str] = []
    start = 0
    for number, line in enumerate(text.splitlines(), start=1):
        if not pending:
            start = number
        if line.endswith("\\"):
            pending.append(line[:-1] + " ")
            continue
        out.append((start, "".join(pending) + line))
        pending = []
    if pending:
        out.append((start, "".join(pending)))
    return out
