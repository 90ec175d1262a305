"""Deployments as plain deployment files (``.deploy``): one ``key: value`` per line.

::

  # Marker detector, dusk configuration.
  name: detector_dusk
  description: ArUco marker detector for dusk
  deploys: marker_detection_dusk
  executable: {python}
  arguments: -m kgadapt.onboard.perception.detector --robot {robot} --host {host} --instance {instance} --config {config} --connect {connect}
  environment: OPENCV_LOG_LEVEL=ERROR
  executable_on: onboard, remote
  reconfigurable_as: marker-detector

``name`` defaults to the file name without ``.deploy``. ``arguments`` are split
like a shell would (quotes respected, nothing expanded). ``environment`` may
repeat. ``reconfigurable_as`` names a program family: a running process of one
deployment may be reconfigured in place into another deployment of the same
family on the same host (no restart). Every other key is refused.
"""  # noqa: E501  (the example's arguments line is one line of a .deploy file)

from __future__ import annotations

from pathlib import Path

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import deployment as D
from kgadapt.knowledge.importers.model import Origin, ParsedModel

NOTATION = "deployment file"
KEYS = ("name", "description", "deploys", "executable", "arguments", "environment", "executable_on",
        "reconfigurable_as")


def parse(text: str, path: str) -> ParsedModel:
    """Read one ``.deploy`` file (raises ModelError naming file and line)."""
    model = ParsedModel(path=path, notation=NOTATION)
    top = Origin(path, 1)
    draft = D.DeploymentDraft(name=D.check_name(Path(path).stem, top, "deployment (file name)"),
                              name_origin=top, kind=S.DEPLOYMENT_FILE)
    seen: dict[str, int] = {}
    executable: list[str] | None = None
    arguments: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        origin = Origin(path, number)
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        key, sep, value = stripped.partition(":")
        key, value = key.strip(), value.strip()
        if not sep or not key.isidentifier():
            raise origin.error(f"unknown statement {stripped!r} (expected KEY: VALUE)")
        if key not in KEYS:
            raise origin.error(f"unknown key {key!r} (known: {', '.join(KEYS)})")
        if key != "environment" and key in seen:
            raise origin.error(f"{key} given twice (first at line {seen[key]})")
        seen[key] = number
        if key == "name":
            draft.name = D.check_name(value, origin, "name")
            draft.name_origin = origin
        elif key == "description":
            D.check_text(value, origin, "description")
            draft.description = value
        elif key == "deploys":
            draft.deploys = D.name_list(value, origin, "deploys")
        elif key == "executable":
            words = D.split_command(value, origin, "executable")
            if len(words) != 1:
                raise origin.error("executable is one word; put the rest in 'arguments:'")
            _check_words(words, origin)
            executable = words
            draft.command_origin = draft.command_origin or origin
        elif key == "arguments":
            arguments = D.split_command(value, origin, "arguments") if value else []
            _check_words(arguments, origin)
            draft.command_origin = origin
        elif key == "environment":
            draft.environment = (draft.environment or []) + [(e, origin) for e in D.environment_entries(value, origin)]
        elif key == "reconfigurable_as":
            draft.reconfigurable_as = (D.check_name(value, origin, "reconfigurable_as"), origin)
        else:
            draft.platforms = D.name_list(value, origin, "executable_on")
    if executable is not None:
        draft.command = executable + arguments
    D.emit(model, draft, top)
    return model


def _check_words(words: list[str], origin: Origin) -> None:
    for word in words:
        D.check_placeholders(word, origin)
        D.check_text(word, origin, "command word")
