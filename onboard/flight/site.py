"""The markers of a site: one format, loaded into the graph or read from a file, used by the confirmer and the targets.

A site (``*.site``, JSON) names the markers laid out where the robot lands,
their printed sizes (the black square's side, in metres) and their ArUco
dictionary::

    {"site": "hall-1", "dictionary": "DICT_4X4_50",
     "markers": [{"id": 33, "size_m": 0.20},
                 {"id": 45, "size_m": 0.26, "name": "pad, approach", "position": [0.0, -0.19, 0.0]},
                 {"id": 16, "size_m": 0.02, "name": "pad, touchdown", "position": [0.0, 0.0, 0.0]},
                 {"id": 5, "size_m": 0.30, "dictionary": "DICT_6X6_250"}]}

``layout`` says how the markers are printed, for the calibration scene to draw
them so (:mod:`kgadapt.onboard.perception.calibration`): ``apart`` (the
default: each marker alone with a white margin), ``chessboard`` (each in a white
square of a chessboard, as on OpenCV's ChArUco boards: black squares beside its
margin) or ``touching`` (a marker in every square of a chessboard, as on the
ArUco author's ChArUco2 boards: a marker's only margin is its neighbours'
inverted border, and it touches its diagonal neighbours at the corners).

``site`` defaults to the file's name, ``dictionary`` (the site's, and each
marker's unless it names its own) to ``DICT_4X4_50``. ``position`` is where
the marker lies from the site's **landing point**, metres (north, east, down:
lay the pad out squared to north). A marker with a position is part of the
landing pad: seeing it guides the vehicle to the landing point, its offset
taken away, so every marker of the pad leads to the same spot (a big marker
for the approach, a small one beside the landing point that stays in the
camera's view down to touchdown). A marker without a position is itself a
landing point. The dictionary must be one OpenCV knows
(or a custom dictionary file, as :func:`kgadapt.onboard.perception.markers.aruco_dictionary`
takes it; a relative path is read from the site file's folder), ids unique
and within the dictionary, sizes positive. Anything else is a
:class:`ModelError` naming the file and the line.

``kgadapt knowledge load`` loads site files with the other models
(:mod:`kgadapt.knowledge.importers.site_model`); the onboard agent and the flight
bridge take the site from the graph (:func:`site_from_graph`, named query
``site_markers``) unless a file overrides it (``--site FILE``, :func:`load_site`).
The ids keep phantom markers from becoming landing targets
(:mod:`kgadapt.onboard.flight.confirmation`); the sizes let a landing target carry the
marker's position (:mod:`kgadapt.onboard.flight.landing_targets`).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from kgadapt.shared.errors import ConfigError, ModelError

DEFAULT_DICTIONARY = "DICT_4X4_50"
MAX_ID = 1023  # the largest predefined ArUco dictionaries (ARUCO_ORIGINAL, 7X7_1000) stop below 1024
MAX_SIZE_M = 10.0  # a larger "marker" is a typo (centimetres for metres)
_KEYS = {"site", "dictionary", "markers", "layout"}
PRINT_LAYOUTS = ("apart", "chessboard", "touching")  # how a site prints its markers (module docstring)
_MARKER_KEYS = {"id", "size_m", "name", "dictionary", "position"}
# What the flight bridge's log and `kgadapt status` say when neither a marker size nor a rangefinder
# distance gives the landing targets a range.
ANGLES_ONLY = "landing targets carry angles only; ArduPilot needs a rangefinder or the marker's size"
_SITE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

# What a dictionary check says of each name: None when usable (with the number of ids it holds,
# when known), else the problem. Callers choose where OpenCV runs (here, or in a child process).
DictionaryVerdict = tuple[str | None, int | None]
DictionaryCheck = Callable[[list[str]], Mapping[str, DictionaryVerdict]]


@dataclass(frozen=True, kw_only=True)
class SiteMarkers:
    """The markers at a site: id -> printed size (m), and optional names, dictionaries and positions."""

    site: str
    dictionary: str = DEFAULT_DICTIONARY
    sizes_m: Mapping[int, float]
    names: Mapping[int, str] = field(default_factory=dict)
    dictionaries: Mapping[int, str] = field(default_factory=dict)  # only markers not of the site's dictionary
    positions: Mapping[int, tuple[float, float, float]] = field(default_factory=dict)
    layout: str = "apart"  # how the markers are printed: one of PRINT_LAYOUTS
    source: str = ""  # where it came from: a file's path, or "graph"

    @property
    def ids(self) -> frozenset[int]:
        return frozenset(self.sizes_m)

    def size_of(self, marker_id: int) -> float | None:
        return self.sizes_m.get(marker_id)

    def dictionary_of(self, marker_id: int) -> str:
        return self.dictionaries.get(marker_id, self.dictionary)

    def to_landing_point(self, marker_id: int) -> tuple[float, float, float] | None:
        """From the marker to the site's landing point (NED, m); None when the marker is its own landing point."""
        position = self.positions.get(marker_id)
        if position is None or not any(position):
            return None
        return (-position[0], -position[1], -position[2])

    def place_of(self, marker_id: int) -> int:
        """The landing point a marker leads to, as a key: -1 for the pad's (every marker with a position),
        else the marker's own id. Sightings of one place are one track for the confirmation."""
        return -1 if marker_id in self.positions else marker_id


def check_dictionaries_here(names: list[str]) -> dict[str, DictionaryVerdict]:
    """OpenCV's verdict on each dictionary name, in this process (imports OpenCV)."""
    import importlib

    # Imported by name: the knowledge side type-checks this module without following it into OpenCV.
    aruco_dictionary = importlib.import_module("kgadapt.onboard.perception.markers").aruco_dictionary
    out: dict[str, DictionaryVerdict] = {}
    for name in names:
        try:
            dictionary = aruco_dictionary(name)
        except (ConfigError, ModelError) as exc:
            out[name] = (str(exc), None)
            continue
        except Exception as exc:  # noqa: BLE001 - cv2.error or a file the custom-dictionary reader cannot take
            out[name] = (f"OpenCV cannot use ArUco dictionary {name!r}: {exc}", None)
            continue
        count = getattr(getattr(dictionary, "bytesList", None), "shape", (None,))[0]
        out[name] = (None, int(count) if isinstance(count, int) else None)
    return out


def load_site(path: str | Path, *, check: DictionaryCheck | None = check_dictionaries_here) -> SiteMarkers:
    """Read and check a site file; ModelError names the file, the line and what is wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelError(str(path), None, f"cannot read site file: {getattr(exc, 'strerror', None) or exc}") from exc
    return parse_site(text, str(path), check=check)


def parse_site(text: str, path: str, *, check: DictionaryCheck | None = check_dictionaries_here) -> SiteMarkers:
    """A site from its text (``path`` names it in errors and gives its default name and folder)."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ModelError(path, getattr(exc, "lineno", None), f"not valid JSON: {exc}") from exc
    key_lines, marker_lines = json_lines(text)
    return site_from_dict(data, where=path, default_name=Path(path).stem, key_lines=key_lines,
                          marker_lines=marker_lines, check=check, folder=Path(path).parent)


def site_from_dict(data: Any, *, where: str, default_name: str = "", key_lines: Mapping[str, int] | None = None,
                   marker_lines: list[int] | None = None, check: DictionaryCheck | None = None,
                   folder: Path | None = None) -> SiteMarkers:
    """A site from its parsed JSON (``where`` names it in errors, with the lines when known)."""
    key_lines, marker_lines = key_lines or {}, marker_lines or []

    def fail(message: str, line: int | None = None) -> ModelError:
        return ModelError(where, line, message)

    if not isinstance(data, dict) or not isinstance(data.get("markers"), list) or not data["markers"]:
        raise fail("a site file is an object with a non-empty 'markers' list of {\"id\": N, \"size_m\": S}",
                   key_lines.get("markers", 1))
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise fail(f"unknown key {unknown[0]!r} (a site file has {', '.join(sorted(_KEYS))})", key_lines.get(unknown[0]))
    for key in ("site", "dictionary"):
        if key in data and (not isinstance(data[key], str) or not data[key]):
            raise fail(f"{key!r} must be a non-empty string, not {data[key]!r:.40}", key_lines.get(key))
    layout = data.get("layout", "apart")
    if layout not in PRINT_LAYOUTS:
        raise fail(f"'layout' must be one of {', '.join(PRINT_LAYOUTS)} (how the markers are printed), "
                   f"not {layout!r:.40}", key_lines.get("layout"))
    site = data.get("site") or default_name
    if not _SITE_NAME.match(site):
        raise fail(f"site name {site!r} must be letters, digits, '_', '-' or '.' (at most 64)", key_lines.get("site"))
    default_dictionary = data.get("dictionary") or DEFAULT_DICTIONARY
    sizes: dict[int, float] = {}
    names: dict[int, str] = {}
    dictionaries: dict[int, str] = {}
    positions: dict[int, tuple[float, float, float]] = {}
    lines: dict[int, int | None] = {}
    for i, m in enumerate(data["markers"]):
        line = marker_lines[i] if i < len(marker_lines) else None
        if not isinstance(m, dict) or set(m) - _MARKER_KEYS:
            raise fail(f'marker {i} must be {{"id": N, "size_m": S}} (and optional "name", "dictionary", '
                       f'"position"), not {m!r:.80}', line)
        mid, size = m.get("id"), m.get("size_m")
        if isinstance(mid, bool) or not isinstance(mid, int) or not 0 <= mid <= MAX_ID:
            raise fail(f"marker {i}: 'id' must be an integer 0..{MAX_ID}, not {mid!r}", line)
        if mid in sizes:
            raise fail(f"marker {i}: id {mid} listed twice (first on line {lines[mid]})"
                       if lines.get(mid) else f"marker {i}: id {mid} listed twice", line)
        if isinstance(size, bool) or not isinstance(size, (int, float)) or not size > 0:
            raise fail(f"marker {i} (id {mid}): size_m must be positive metres, not {size!r}", line)
        if size > MAX_SIZE_M:
            raise fail(f"marker {i} (id {mid}): size_m {size} m is not a marker's size (at most {MAX_SIZE_M:g} m)", line)
        if "name" in m and (not isinstance(m["name"], str) or "'" in m["name"] or "\\" in m["name"]):
            raise fail(f"marker {i} (id {mid}): 'name' must be a string without ' or \\", line)
        if "dictionary" in m and (not isinstance(m["dictionary"], str) or not m["dictionary"]):
            raise fail(f"marker {i} (id {mid}): 'dictionary' must be a dictionary's name", line)
        if "position" in m:
            pos = m["position"]
            if (not isinstance(pos, list) or len(pos) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) < 1e6 for v in pos)):
                raise fail(f"marker {i} (id {mid}): 'position' must be [north, east, down] metres, not {pos!r:.60}", line)
            positions[mid] = (float(pos[0]), float(pos[1]), float(pos[2]))
        sizes[mid] = float(size)
        lines[mid] = line
        if "name" in m:
            names[mid] = m["name"]
        if m.get("dictionary", default_dictionary) != default_dictionary:
            dictionaries[mid] = m["dictionary"]
    if check is not None:
        wanted = sorted({default_dictionary, *dictionaries.values()})
        verdicts = check([_resolved(name, folder) for name in wanted])
        for name in wanted:
            problem, count = verdicts.get(_resolved(name, folder), (None, None))
            users = [mid for mid in sizes if dictionaries.get(mid, default_dictionary) == name]
            if problem:
                first = next((mid for mid in users if mid in dictionaries), None)
                line = lines.get(first) if first is not None else key_lines.get("dictionary", lines.get(users[0]))
                raise fail(problem if repr(name) in problem else f"dictionary {name!r}: {problem}", line)
            for mid in users:
                if count is not None and mid >= count:
                    raise fail(f"marker id {mid} is not in dictionary {name!r} (ids 0..{count - 1})", lines.get(mid))
    # Kept as found, an absolute path for a file: the models name their configurations' dictionary files so
    # (knowledge/importers/rpsl.py), and the site's must compare equal to them from any working directory.
    return SiteMarkers(site=site, dictionary=_resolved(default_dictionary, folder), sizes_m=sizes, names=names,
                       dictionaries={mid: _resolved(name, folder) for mid, name in dictionaries.items()},
                       positions=positions, layout=layout, source=where)


def _resolved(name: str, folder: Path | None) -> str:
    """A custom dictionary file named relative to the site file, as its absolute path; other names as they are."""
    if name.startswith("DICT_"):
        return name
    if Path(name).is_absolute():
        return str(Path(name).resolve())
    if folder is None:
        return name
    candidate = folder / name
    return str(candidate.resolve()) if candidate.exists() else name


_SPACE = re.compile(r"[ \t\n\r]*")


def json_lines(text: str) -> tuple[dict[str, int], list[int]]:
    """The line of each top-level key and of each entry of ``markers`` in a (valid) JSON text.

    Walks the top level with :meth:`json.JSONDecoder.raw_decode`, which says where each value
    ends; empty answers when the text is not an object (the checks then name no line).
    """
    decoder = json.JSONDecoder()
    key_lines: dict[str, int] = {}
    marker_lines: list[int] = []

    def line(at: int) -> int:
        return text.count("\n", 0, at) + 1

    def skip(at: int) -> int:
        space = _SPACE.match(text, at)
        return space.end() if space else at

    try:
        i = skip(0)
        if text[i] != "{":
            return {}, []
        i = skip(i + 1)
        while text[i] != "}":
            start = i
            key, i = decoder.raw_decode(text, i)
            key_lines[str(key)] = line(start)
            i = skip(skip(i) + 1)  # the colon
            if key == "markers" and text[i] == "[":
                marker_lines = []
                i = skip(i + 1)
                while text[i] != "]":
                    marker_lines.append(line(i))
                    _, i = decoder.raw_decode(text, i)
                    i = skip(i)
                    if text[i] == ",":
                        i = skip(i + 1)
                i += 1
            else:
                _, i = decoder.raw_decode(text, i)
            i = skip(i)
            if text[i] == ",":
                i = skip(i + 1)
    except (IndexError, ValueError):
        pass  # not the shape the checks want: they say so, without a line
    return key_lines, marker_lines


def site_from_rows(rows: Iterable[Mapping[str, Any]], *, where: str = "graph") -> SiteMarkers | None:
    """The site of the ``site_markers`` query's rows (None without rows); ConfigError when several sites answer."""
    rows = list(rows)
    if not rows:
        return None
    sites = sorted({str(r["site"]) for r in rows})
    if len(sites) > 1:
        raise ConfigError(f"the knowledge graph holds several sites ({', '.join(sites)}): choose one "
                          "(--site-name NAME) or give a site file (--site FILE)")
    first = rows[0]
    default = first.get("site_dictionary") or DEFAULT_DICTIONARY
    sizes: dict[int, float] = {}
    names: dict[int, str] = {}
    dictionaries: dict[int, str] = {}
    positions: dict[int, tuple[float, float, float]] = {}
    for r in rows:
        mid, size = r.get("marker_id"), r.get("size_m")
        if isinstance(mid, bool) or not isinstance(mid, int) or not isinstance(size, (int, float)) or not size > 0:
            raise ConfigError(f"site {sites[0]!r} in the {where}: marker {mid!r} has no usable id and size ({size!r})")
        sizes[mid] = float(size)
        if r.get("marker_name"):
            names[mid] = str(r["marker_name"])
        if r.get("dictionary") and r["dictionary"] != default:
            dictionaries[mid] = str(r["dictionary"])
        pos = r.get("position")
        if isinstance(pos, list) and len(pos) == 3:
            positions[mid] = (float(pos[0]), float(pos[1]), float(pos[2]))
    return SiteMarkers(site=sites[0], dictionary=default, sizes_m=sizes, names=names, dictionaries=dictionaries,
                       positions=positions, source=where)


def site_from_graph(client: Any, site: str | None = None, *, wait_s: float = 0.0) -> SiteMarkers | None:
    """The site's markers from the knowledge graph (named query ``site_markers``); None when no site is loaded.

    ``site`` chooses one when the graph holds several. ``wait_s``: ask again for that long while the
    knowledge service does not answer (an agent's start).
    """
    rows = client.query("site_markers", {"site": site} if site else {}, wait_s=wait_s)
    found = site_from_rows(rows)
    if found is None and site:
        raise ConfigError(f"no site {site!r} in the knowledge graph (kgadapt knowledge load knowledge/models)")
    return found


def main() -> int:
    """``python -m kgadapt.onboard.flight.site``: OpenCV's verdict on dictionary names, for the model loader.

    stdin: a JSON list of names; stdout: a JSON object name -> [problem or null, ids or null].
    The loader asks in a process of its own: loading models must not load OpenCV.
    """
    import sys

    names = json.load(sys.stdin)
    json.dump({name: list(v) for name, v in check_dictionaries_here([str(n) for n in names]).items()}, sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
