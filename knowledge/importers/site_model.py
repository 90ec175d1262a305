"""Site models (``*.site``): the markers laid out where the robot lands, as Site and Marker nodes.

The format is the one the onboard side reads (:mod:`kgadapt.onboard.flight.site`:
markers with id, printed size, dictionary, optional name and position), and
the same checks apply, each naming the file and line: JSON, unique ids,
positive sizes, dictionaries OpenCV knows (asked in a child process,
:func:`kgadapt.knowledge.importers.detector_check.dictionary_verdicts`, since
loading models must not load OpenCV), ids within their dictionary.
"""

from __future__ import annotations

from typing import Any

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import detector_check
from kgadapt.knowledge.importers.model import EdgeSpec, NodeSpec, Origin, ParsedModel, Ref
from kgadapt.onboard.flight.site import json_lines, parse_site


def parse(text: str, path: str) -> ParsedModel:
    site = parse_site(text, path, check=lambda names: detector_check.dictionary_verdicts(names, path))
    key_lines, marker_lines = json_lines(text)
    model = ParsedModel(path=path, notation="site")
    site_origin = Origin(path, key_lines.get("site", 1))
    model.nodes.append(NodeSpec(S.SITE, site.site, {"dictionary": site.dictionary, "layout": site.layout},
                                site_origin))
    for index, (mid, size) in enumerate(site.sizes_m.items()):
        origin = Origin(path, marker_lines[index] if index < len(marker_lines) else site_origin.line)
        props: dict[str, Any] = {"marker_id": mid, "size_m": size, "dictionary": site.dictionary_of(mid)}
        if mid in site.names:
            props["marker_name"] = site.names[mid]
        if mid in site.positions:
            props["position"] = list(site.positions[mid])
        name = f"{site.site}/{mid}"
        model.nodes.append(NodeSpec(S.MARKER, name, props, origin))
        model.edges.append(EdgeSpec(S.HAS_MARKER, Ref((S.SITE,), site.site, "site"), Ref((S.MARKER,), name, "marker"),
                                    origin))
    return model
