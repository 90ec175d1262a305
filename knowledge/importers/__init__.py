"""Importers: one module per modelling notation, each turning a file into nodes and relations.

=============  ===========================================  =========================
extension      notation                                     module
=============  ===========================================  =========================
``.rpsl``      perception-graph DSL of the paper's Fig. 3   :mod:`.rpsl`
``.platform``  platform model, AADL-like                    :mod:`.aadl`
``.service``   deployment as a systemd service file         :mod:`.systemd`
``.deploy``    deployment as a plain deployment file        :mod:`.deployment_file`
``.features``  feature model and illumination bands         :mod:`.feature_model`
``.site``      a landing site's markers (JSON)              :mod:`.site_model`
=============  ===========================================  =========================

Importers parse; they never evaluate model text. They check what one file
can check (syntax, names, numbers, units); the loader checks what needs every
file (references, duplicate names) before anything is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from kgadapt.knowledge.importers import aadl, deployment_file, feature_model, rpsl, site_model, systemd
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, Origin, ParsedModel, Ref
from kgadapt.shared.errors import ModelError

Importer = Callable[[str, str], ParsedModel]

IMPORTERS: dict[str, Importer] = {
    ".rpsl": rpsl.parse,
    ".platform": aadl.parse,
    ".service": systemd.parse,
    ".deploy": deployment_file.parse,
    ".features": feature_model.parse,
    ".site": site_model.parse,
}

__all__ = ["IMPORTERS", "EdgeSpec", "NodeSpec", "Origin", "ParsedModel", "Ref", "parse_file"]


def parse_file(path: Path | str) -> ParsedModel:
    """Parse one model file with the importer its extension names."""
    path = Path(path)
    importer = IMPORTERS.get(path.suffix)
    if importer is None:
        raise ModelError(str(path), None, f"no importer for {path.suffix or 'files without extension'!r} "
                                          f"(known: {', '.join(IMPORTERS)})")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ModelError(str(path), None, f"not UTF-8 text: {exc}") from exc
    except OSError as exc:
        raise ModelError(str(path), None, f"cannot read: {exc.strerror or exc}") from exc
    return importer(text, str(path))
