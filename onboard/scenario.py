"""The synthetic scenario: ArUco markers with known ids and poses under changing light.

Two halves:

* :class:`IlluminationProfile` — how bright the scene is over time. A small
  file of time/level points (JSON or CSV), linearly interpolated, with
  optional flicker per point, plus scene-wide gradient and sensor noise.
  Levels are the target *mean* luminance of a frame (0..255), the same scale
  as the illumination bands in the knowledge graph.
* :class:`SyntheticScene` — renders a grey frame of the markers (placed by a
  pinhole projection of a 3-D pose, swaying slowly like a hovering camera)
  exposed at a given level, and returns the ground truth with it: each
  marker's id and its four corners in image pixels, in ArUco's corner order.

File formats (errors name the file and line)::

    JSON  [[t, level], ...]
    JSON  {"points": [[t, level, flicker_depth?, flicker_hz?], ...],
           "gradient": 0.3, "noise": 2.0, "shot": 0.05, "readout_s": 0.02, "loop": true}
    CSV   t,level[,flicker_depth,flicker_hz]      ('#' comments, optional header row)

Flicker multiplies the level by ``1 + depth * sin(2 pi hz t)``; the phase also
advances down the rows by the rolling-shutter readout time, so fast flicker
shows as bands, as it does on a real camera. Depth is interpolated between
points; the frequency is the one of the segment's first point.
"""

from __future__ import annotations

import csv
import io
import json
import json.decoder
import json.scanner
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from shared.errors import ConfigError, ModelError

DEFAULT_DICTIONARY = "DICT_4X4_50"
SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
DEMO_PROFILE = SCENARIO_DIR / "demo.json"

_GLOBALS = {"gradient": (0.0, 0.9), "noise": (0.0, 50.0), "shot": (0.0, 5.0), "readout_s": (0.0, 0.2)}


# --------------------------------------------------------------------------- profile


@dataclass(frozen=True)
class ProfilePoint:
    """Level (mean luminance 0..255) at time ``t`` seconds, with its flicker."""

    t: float
    level: float
    flicker_depth: float = 0.0
    flicker_hz: float = 0.0


@dataclass(frozen=True, kw_only=True)
class IlluminationProfile:
    """Scene brightness over time: linear between points, flicker on top."""

    points: tuple[ProfilePoint, ...]
    gradient: float = 0.3  # brightness falls by this fraction across the frame
    noise: float = 2.0  # read noise, grey levels (sigma)
    shot: float = 0.05  # shot noise: variance grows by this times the signal
    readout_s: float = 0.02  # rolling-shutter readout time (row phase of flicker)
    loop: bool = True
    source: str = "<inline>"

    def __post_init__(self) -> None:
        if not self.points:
            raise ConfigError(f"illumination profile {self.source}: no points")

    @property
    def duration(self) -> float:
        return self.points[-1].t

    @classmethod
    def constant(cls, level: float, **kwargs: Any) -> "IlluminationProfile":
        """A profile that stays at ``level`` (calibration, tests)."""
        return cls(points=(ProfilePoint(0.0, float(level)),), source=f"<constant {level}>", **kwargs)

    def _local_time(self, t: float) -> float:
        if self.loop and self.duration > 0:
            return t % self.duration
        return min(max(t, 0.0), self.duration)

    def _segment(self, t: float) -> tuple[ProfilePoint, ProfilePoint, float]:
        pts = self.points
        t = self._local_time(t)
        if len(pts) == 1 or t <= pts[0].t:
            return pts[0], pts[0], 0.0
        for a, b in zip(pts, pts[1:]):
            if t <= b.t:
                span = b.t - a.t
                return a, b, (t - a.t) / span if span > 0 else 1.0
        return pts[-1], pts[-1], 0.0

    def level_at(self, t: float) -> float:
        """The base level at ``t`` (no flicker)."""
        a, b, u = self._segment(t)
        return a.level + (b.level - a.level) * u

    def flicker_at(self, t: float) -> tuple[float, float]:
        """``(depth, hz)`` of the flicker at ``t``."""
        a, b, u = self._segment(t)
        return a.flicker_depth + (b.flicker_depth - a.flicker_depth) * u, a.flicker_hz

    def row_gains(self, t: float, height: int) -> np.ndarray | None:
        """Per-row flicker multipliers for a frame exposed at ``t`` (None when steady)."""
        depth, hz = self.flicker_at(t)
        if depth <= 0 or hz <= 0:
            return None
        rows = t + np.arange(height, dtype=np.float64) * (self.readout_s / max(height, 1))
        return (1.0 + depth * np.sin(2 * math.pi * hz * rows)).astype(np.float32)


def load_profile(path: str | Path) -> IlluminationProfile:
    """Read a profile file (``.json`` or ``.csv``); raise ModelError naming file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ModelError(str(path), None, f"cannot read illumination profile: {exc.strerror or exc}") from exc
    if path.suffix.lower() == ".csv":
        return parse_profile_csv(text, source=str(path))
    return parse_profile_json(text, source=str(path))


def parse_profile_json(text: str, *, source: str = "<json>") -> IlluminationProfile:
    """Parse the JSON form; every error names ``source`` and the line."""
    data, positions = _json_with_positions(text, source)

    def line_of(obj: Any = None, key: str | None = None) -> int:
        if obj is not None and id(obj) in positions:
            return text.count("\n", 0, positions[id(obj)]) + 1
        if key is not None:
            at = text.find(f'"{key}"')
            if at >= 0:
                return text.count("\n", 0, at) + 1
        return 1

    options: dict[str, Any] = {}
    if isinstance(data, list):
        raw_points = data
    elif isinstance(data, dict):
        unknown = sorted(set(data) - {"points", "loop", *_GLOBALS})
        if unknown:
            raise ModelError(source, line_of(key=unknown[0]), f"unknown profile key {unknown[0]!r}")
        if "points" not in data:
            raise ModelError(source, 1, "profile object lacks 'points'")
        raw_points = data["points"]
        if not isinstance(raw_points, list):
            raise ModelError(source, line_of(key="points"), "'points' must be a list of [t, level, ...]")
        for key, (low, high) in _GLOBALS.items():
            if key in data:
                value = data[key]
                if not _is_number(value) or not low <= value <= high:
                    raise ModelError(source, line_of(key=key), f"{key!r} must be a number in [{low}, {high}], not {value!r}")
                options[key] = float(value)
        if "loop" in data:
            if not isinstance(data["loop"], bool):
                raise ModelError(source, line_of(key="loop"), "'loop' must be true or false")
            options["loop"] = data["loop"]
    else:
        raise ModelError(source, 1, f"a profile is a list of [t, level] or an object with 'points', not {type(data).__name__}")
    rows = [(line_of(p) if isinstance(p, list) else line_of(raw_points), p) for p in raw_points]
    return _build(rows, source, options)


def parse_profile_csv(text: str, *, source: str = "<csv>") -> IlluminationProfile:
    """Parse the CSV form ``t,level[,flicker_depth,flicker_hz]``."""
    rows: list[tuple[int, Any]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = [c.strip() for c in next(csv.reader(io.StringIO(stripped)))]
        if not rows and cells and cells[0].lower() in ("t", "time", "time_s"):
            continue  # header row
        values: list[Any] = []
        for cell in cells:
            try:
                values.append(float(cell))
            except ValueError:
                raise ModelError(source, number, f"{cell!r} is not a number") from None
        rows.append((number, values))
    return _build(rows, source, {})


def _build(rows: Sequence[tuple[int, Any]], source: str, options: dict[str, Any]) -> IlluminationProfile:
    if not rows:
        raise ModelError(source, 1, "the profile has no points")
    points: list[ProfilePoint] = []
    for line, raw in rows:
        if not isinstance(raw, list) or not 2 <= len(raw) <= 4 or not all(_is_number(v) for v in raw):
            raise ModelError(source, line, f"a point is [t, level] or [t, level, flicker_depth, flicker_hz], not {raw!r}")
        t, level, depth, hz = (list(map(float, raw)) + [0.0, 0.0])[:4]
        if not all(math.isfinite(v) for v in (t, level, depth, hz)):
            raise ModelError(source, line, f"point {raw!r} is not finite")
        if t < 0:
            raise ModelError(source, line, f"time {t} is negative")
        if points and t <= points[-1].t:
            raise ModelError(source, line, f"time {t} does not follow {points[-1].t}: times must increase")
        if not 0 <= level <= 255:
            raise ModelError(source, line, f"level {level} is outside 0..255")
        if not 0 <= depth < 1:
            raise ModelError(source, line, f"flicker depth {depth} is outside [0, 1)")
        if not 0 <= hz <= 500:
            raise ModelError(source, line, f"flicker frequency {hz} Hz is outside 0..500")
        points.append(ProfilePoint(t, level, depth, hz))
    return IlluminationProfile(points=tuple(points), source=source, **options)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _json_with_positions(text: str, source: str) -> tuple[Any, dict[int, int]]:
    """Decode JSON and remember where each list starts, to name lines in errors."""
    positions: dict[int, int] = {}
    keep: list[Any] = []  # keeps the lists alive so their ids stay unique

    def parse_array(s_and_end, scan_once, _w=json.decoder.WHITESPACE.match, _ws=json.decoder.WHITESPACE_STR):
        result, end = json.decoder.JSONArray(s_and_end, scan_once, _w, _ws)
        positions[id(result)] = s_and_end[1] - 1
        keep.append(result)
        return result, end

    decoder = json.JSONDecoder()
    decoder.parse_array = parse_array  # type: ignore[attr-defined]
    decoder.scan_once = json.scanner.py_make_scanner(decoder)  # the pure-Python scanner honours parse_array
    try:
        data = decoder.decode(text)
    except json.JSONDecodeError as exc:
        raise ModelError(source, exc.lineno, f"not valid JSON: {exc.msg}") from exc
    return data, positions


# --------------------------------------------------------------------------- scene


@dataclass(frozen=True)
class MarkerPose:
    """One marker: its id, where it appears and how it is turned.

    ``x``/``y`` place the marker's centre as fractions of the frame, ``size``
    is its apparent side as a fraction of the frame height; ``roll``, ``yaw``,
    ``pitch`` (degrees) turn it in 3-D before the pinhole projection.
    """

    id: int
    x: float
    y: float
    size: float
    roll: float = 0.0
    yaw: float = 0.0
    pitch: float = 0.0


DEFAULT_MARKERS: tuple[MarkerPose, ...] = (
    MarkerPose(3, 0.20, 0.27, 0.24, roll=8, yaw=20),
    MarkerPose(7, 0.52, 0.30, 0.18, roll=-25, pitch=15),
    MarkerPose(12, 0.82, 0.28, 0.20, roll=40, yaw=-25),
    MarkerPose(21, 0.28, 0.72, 0.16, roll=-5, yaw=-15, pitch=-20),
    MarkerPose(33, 0.62, 0.70, 0.26, roll=15),
    MarkerPose(42, 0.88, 0.74, 0.13, roll=-40, pitch=25),
)


@dataclass(frozen=True, kw_only=True)
class SceneSettings:
    """What the synthetic camera sees (sizes in pixels, sway in pixels and seconds)."""

    width: int = 640
    height: int = 480
    dictionary: str = DEFAULT_DICTIONARY
    markers: tuple[MarkerPose, ...] = DEFAULT_MARKERS
    sway_px: float = 6.0
    sway_period_s: float = 7.0
    distractors: int = 6  # dark squares without a valid code: chances for false detections
    seed: int = 1


@dataclass(frozen=True)
class Truth:
    """A marker that is in the frame: its id and corners (TL, TR, BR, BL of the marker)."""

    id: int
    corners: tuple[tuple[float, float], ...]

    def as_wire(self) -> dict[str, Any]:
        return {"id": self.id, "corners": [[round(x, 2), round(y, 2)] for x, y in self.corners]}


@dataclass
class RenderedFrame:
    """A grey frame with its ground truth and the light it was exposed at."""

    image: np.ndarray  # uint8, height x width
    truth: list[Truth]
    level: float  # the base level asked for (before flicker and gradient)
    time: float  # scenario time, seconds
    extras: dict[str, Any] = field(default_factory=dict)


_WHITE, _BLACK, _QUIET = 0.92, 0.04, 0.25  # reflectances; quiet zone as a fraction of the side


class SyntheticScene:
    """Renders the markers of ``settings`` at any time and light level."""

    def __init__(self, settings: SceneSettings = SceneSettings()) -> None:
        import cv2

        self.settings = settings
        w, h = settings.width, settings.height
        if w < 64 or h < 64:
            raise ConfigError(f"synthetic scene {w}x{h}: use at least 64x64")
        dictionary = _dictionary(settings.dictionary)
        self._rng = np.random.default_rng(settings.seed)
        self._background = self._make_background(cv2, w, h)
        ys = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
        xs = np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :]
        self._ramp = (0.6 * xs + 0.4 * ys).astype(np.float32)  # 0 at top-left, 1 at bottom-right
        self._patches: dict[int, tuple[np.ndarray, float, int]] = {}
        for pose in settings.markers:
            side = max(16, int(round(pose.size * h * 1.2)))
            code = cv2.aruco.generateImageMarker(dictionary, pose.id, side).astype(np.float32) / 255.0
            quiet = int(round(side * _QUIET))
            patch = np.ones((side + 2 * quiet, side + 2 * quiet), np.float32)
            patch[quiet:quiet + side, quiet:quiet + side] = code
            patch = _BLACK + (_WHITE - _BLACK) * patch
            self._patches[pose.id] = (patch, float(quiet), side)

    def _make_background(self, cv2: Any, w: int, h: int) -> np.ndarray:
        # Low-contrast blotches (a floor or wall) plus dark squares without a valid code.
        noise = self._rng.random((max(h // 40, 2), max(w // 40, 2))).astype(np.float32)
        base = 0.45 + 0.2 * cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
        for _ in range(self.settings.distractors):
            s = int(self._rng.uniform(0.05, 0.1) * h)
            x0 = int(self._rng.uniform(0, w - s))
            y0 = int(self._rng.uniform(0, h - s))
            base[y0:y0 + s, x0:x0 + s] = _BLACK + 0.1
            inner = s // 3
            base[y0 + inner:y0 + s - inner, x0 + inner:x0 + s - inner] = _WHITE * 0.8
        return np.clip(base, 0.0, 1.0).astype(np.float32)

    def reflectance(self, t: float) -> tuple[np.ndarray, list[Truth]]:
        """The scene's reflectance (0..1) at time ``t`` and the markers' truth."""
        import cv2

        s = self.settings
        w, h = s.width, s.height
        image = self._background.copy()
        phase = 2 * math.pi * t / s.sway_period_s if s.sway_period_s > 0 else 0.0
        dx, dy = s.sway_px * math.sin(phase), 0.6 * s.sway_px * math.sin(2 * phase + 0.7)
        truth: list[Truth] = []
        for pose in s.markers:
            patch, quiet, side = self._patches[pose.id]
            corners = _project(pose, w, h) + np.array([dx, dy], np.float32)
            x0, y0 = np.floor(corners.min(axis=0)).astype(int) - int(quiet) - 2
            x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + int(quiet) + 2
            if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
                continue  # (part) outside the frame: not in the truth, not drawn
            # Source points are the black square's outer edges in patch pixel coordinates.
            e0, e1 = quiet - 0.5, quiet + side - 0.5
            src = np.array([[e0, e0], [e1, e0], [e1, e1], [e0, e1]], np.float32)
            dst = corners - np.array([x0, y0], np.float32)
            # Extend the quad by the quiet zone so the white margin is drawn too.
            full = np.array([[-0.5, -0.5], [patch.shape[1] - 0.5, -0.5],
                             [patch.shape[1] - 0.5, patch.shape[0] - 0.5], [-0.5, patch.shape[0] - 0.5]], np.float32)
            matrix = cv2.getPerspectiveTransform(src, dst)
            size = (int(x1 - x0), int(y1 - y0))
            warped = cv2.warpPerspective(patch, matrix, size, flags=cv2.INTER_AREA if side > size[0] else cv2.INTER_LINEAR)
            mask = np.zeros((size[1], size[0]), np.float32)
            quad = cv2.perspectiveTransform(full[None], matrix)[0]
            cv2.fillConvexPoly(mask, np.round(quad * 16).astype(np.int32), 1.0, lineType=cv2.LINE_AA, shift=4)
            roi = image[y0:y1, x0:x1]
            roi[:] = roi * (1 - mask) + warped * mask
            truth.append(Truth(pose.id, tuple((float(x), float(y)) for x, y in corners)))
        return image, truth

    def render(self, t: float, profile: IlluminationProfile, rng: np.random.Generator | None = None) -> RenderedFrame:
        """The frame a camera sees at ``t`` under ``profile``."""
        level = profile.level_at(t)
        image, truth = self.reflectance(t)
        exposed = self.expose(image, level, profile, t=t, rng=rng)
        return RenderedFrame(exposed, truth, level, t)

    def expose(
        self,
        reflectance: np.ndarray,
        level: float,
        profile: IlluminationProfile,
        *,
        t: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Light ``reflectance`` so that the frame's mean is about ``level``; add flicker and noise."""
        rng = rng or self._rng
        light = 1.0 - profile.gradient * self._ramp
        lit = reflectance * light
        gain = level / max(float(lit.mean()), 1e-6)
        rows = profile.row_gains(t, lit.shape[0])
        if rows is not None:
            lit *= rows[:, None]
        signal = lit * gain
        sigma = np.sqrt(profile.noise ** 2 + profile.shot * signal) if profile.shot > 0 else profile.noise
        noisy = signal + rng.standard_normal(signal.shape, dtype=np.float32) * sigma
        return np.clip(noisy + 0.5, 0, 255).astype(np.uint8)


def _project(pose: MarkerPose, width: int, height: int) -> np.ndarray:
    """Corners (TL, TR, BR, BL) of a marker turned by roll/yaw/pitch, by a pinhole camera."""
    f = float(height)  # about 53 degrees vertical field of view
    side = pose.size * height
    distance = 1.0  # the marker is scaled so that it appears ``side`` pixels tall face-on
    half = 0.5 * side * distance / f
    local = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float64)
    r, yw, p = (math.radians(a) for a in (pose.roll, pose.yaw, pose.pitch))
    rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    ry = np.array([[math.cos(yw), 0, math.sin(yw)], [0, 1, 0], [-math.sin(yw), 0, math.cos(yw)]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    points = local @ (rx @ ry @ rz).T + np.array([0, 0, distance])
    uv = f * points[:, :2] / points[:, 2:3]
    return (uv + np.array([pose.x * width, pose.y * height])).astype(np.float32)


def _dictionary(name: str) -> Any:
    import cv2

    key = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(key, int):
        raise ConfigError(f"unknown ArUco dictionary {name!r}: use a cv2.aruco DICT_* name such as DICT_4X4_50")
    return cv2.aruco.getPredefinedDictionary(key)


def dictionary(name: str) -> Any:
    """The predefined ArUco dictionary called ``name``; ConfigError when unknown."""
    return _dictionary(name)


def frames(
    scene: SyntheticScene,
    profile: IlluminationProfile,
    *,
    fps: float,
    count: int | None = None,
    start: float = 0.0,
    seed: int = 0,
) -> Iterable[RenderedFrame]:
    """Render frames at scenario times ``start + i / fps`` (no pacing: as fast as asked)."""
    rng = np.random.default_rng(seed)
    i = 0
    while count is None or i < count:
        yield scene.render(start + i / fps, profile, rng)
        i += 1
