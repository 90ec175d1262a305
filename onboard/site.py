"""The markers of a site: one file format, read once, used by the confirmer and the landing targets.

A site file (``*.site``, JSON) names the markers laid out where the robot
lands, and their printed sizes (the black square's side, in metres)::

    {"site": "hall-1", "dictionary": "DICT_4X4_50",
     "markers": [{"id": 33, "size_m": 0.20}, {"id": 42, "size_m": 0.10, "name": "pad B"}]}

The ids keep phantom markers from becoming landing targets
(:mod:`kgadapt.onboard.confirmation`); the sizes let a landing target carry the
marker's position (:mod:`kgadapt.onboard.landing_targets`). ``site`` defaults to the
file's name, ``dictionary`` to ``DICT_4X4_50``. Anything else is refused with
a :class:`ModelError` naming the file and the marker.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from kgadapt.shared.errors import ModelError

DEFAULT_DICTIONARY = "DICT_4X4_50"
MAX_ID = 1023  # the largest ArUco dictionaries (ARUCO_ORIGINAL, 7X7_1000) stop below 1024
MAX_SIZE_M = 10.0  # a larger "marker" is a typo (centimetres for metres)
_KEYS = {"site", "dictionary", "markers"}
_MARKER_KEYS = {"id", "size_m", "name"}


@dataclass(frozen=True, kw_only=True)
class SiteMarkers:
    """The markers at a site: id -> printed size (m), and optional names."""

    site: str
    dictionary: str = DEFAULT_DICTIONARY
    sizes_m: Mapping[int, float]
    names: Mapping[int, str] = field(default_factory=dict)

    @property
    def ids(self) -> frozenset[int]:
        return frozenset(self.sizes_m)

    def size_of(self, marker_id: int) -> float | None:
        return self.sizes_m.get(marker_id)


def load_site(path: str | Path) -> SiteMarkers:
    """Read and check a site file; ModelError names the file and what is wrong."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ModelError(str(path), None, f"cannot read site file: {exc.strerror or exc}") from exc
    except ValueError as exc:
        raise ModelError(str(path), getattr(exc, "lineno", None), f"not valid JSON: {exc}") from exc
    return site_from_dict(data, where=str(path), default_name=path.stem)


def site_from_dict(data: Any, *, where: str, default_name: str = "") -> SiteMarkers:
    """A site from its parsed JSON (``where`` names it in errors)."""
    if not isinstance(data, dict) or not isinstance(data.get("markers"), list) or not data["markers"]:
        raise ModelError(where, None, "a site file is an object with a non-empty 'markers' list "
                                      'of {"id": N, "size_m": S}')
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise ModelError(where, None, f"unknown key {unknown[0]!r} (a site file has {', '.join(sorted(_KEYS))})")
    for key in ("site", "dictionary"):
        if key in data and not isinstance(data[key], str):
            raise ModelError(where, None, f"{key!r} must be a string, not {data[key]!r:.40}")
    sizes: dict[int, float] = {}
    names: dict[int, str] = {}
    for i, m in enumerate(data["markers"]):
        if not isinstance(m, dict) or set(m) - _MARKER_KEYS:
            raise ModelError(where, None, f'marker {i} must be {{"id": N, "size_m": S}} (and an optional '
                                          f'"name"), not {m!r:.80}')
        mid, size = m.get("id"), m.get("size_m")
        if isinstance(mid, bool) or not isinstance(mid, int) or not 0 <= mid <= MAX_ID:
            raise ModelError(where, None, f"marker {i}: 'id' must be an integer 0..{MAX_ID}, not {mid!r}")
        if mid in sizes:
            raise ModelError(where, None, f"marker {i}: id {mid} listed twice")
        if isinstance(size, bool) or not isinstance(size, (int, float)) or not size > 0:
            raise ModelError(where, None, f"marker {i} (id {mid}): size_m must be positive metres, not {size!r}")
        if size > MAX_SIZE_M:
            raise ModelError(where, None, f"marker {i} (id {mid}): size_m {size} m is not a marker's size "
                                          f"(at most {MAX_SIZE_M:g} m)")
        if "name" in m and not isinstance(m["name"], str):
            raise ModelError(where, None, f"marker {i} (id {mid}): 'name' must be a string")
        sizes[mid] = float(size)
        if "name" in m:
            names[mid] = m["name"]
    return SiteMarkers(site=data.get("site") or default_name, dictionary=data.get("dictionary") or DEFAULT_DICTIONARY,
                       sizes_m=sizes, names=names)
