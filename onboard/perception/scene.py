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
import math
from dataclasses import dataclass, field, fields, replace
from enum import Enum
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence, cast

import numpy as np

from kgadapt.onboard.flight.site import PRINT_LAYOUTS
from kgadapt.onboard.perception.markers import aruco_dictionary
from kgadapt.shared.errors import ConfigError, ModelError
from kgadapt.shared.resources import scenarios

DEFAULT_DICTIONARY = "DICT_4X4_50"
SCENARIO_DIR = scenarios()
DEMO_PROFILE = SCENARIO_DIR / "demo.json"

_GLOBALS = {"gradient": (0.0, 0.9), "noise": (0.0, 50.0), "shot": (0.0, 5.0), "readout_s": (0.0, 0.2)}
_GROUPS: dict[str, type] = {}  # filled below: profile keys holding an object (camera, light, scene)


# --------------------------------------------------------------------------- camera model


class Response(str, Enum):
    """How the camera turns light into grey levels."""

    SRGB = "srgb"  # gamma-encoded as real cameras deliver frames
    LINEAR = "linear"  # the old model: grey level proportional to light, noise in grey levels


@dataclass(frozen=True, kw_only=True)
class CameraModel:
    """A fixed-exposure camera: light -> electrons -> noise -> sRGB -> 8 bits.

    Light reaches the sensor (``full_well`` electrons at full scale), shot noise
    (Poisson) and read noise (``read_noise`` electrons, Gaussian) are added, and
    the result is gamma-encoded (sRGB) and quantised to 8 bits. The Poisson part
    is drawn as a Gaussian of the same variance with the electron count rounded:
    the usual Poisson-Gaussian approximation, five times faster than exact
    Poisson draws at 640x480 and indistinguishable to a marker detector. Motion
    blur (``blur_px`` long at ``blur_angle`` degrees) smears the light before the
    noise, as the exposure does.
    """

    response: Response = Response.SRGB
    full_well: float = 6000.0  # electrons at full scale (a small CMOS sensor at base gain)
    read_noise: float = 3.0  # electrons, sigma
    blur_px: float = 0.0
    blur_angle: float = 0.0
    lens_sigma: float = 0.0  # the lens's blur (a Gaussian point spread, pixels): a real frame's edges are never a step

    def __post_init__(self) -> None:
        if not 10 <= self.full_well <= 1e6 or not 0 <= self.read_noise <= 1000:
            raise ConfigError(f"camera model: full_well {self.full_well} in [10, 1e6], read_noise {self.read_noise} in [0, 1000]")
        if not 0 <= self.blur_px <= 64:
            raise ConfigError(f"camera model: blur_px {self.blur_px} outside [0, 64]")
        if not 0 <= self.lens_sigma <= 8:
            raise ConfigError(f"camera model: lens_sigma {self.lens_sigma} outside [0, 8]")


@dataclass(frozen=True, kw_only=True)
class LightLayout:
    """How the light falls across the scene, beyond the profile's gradient.

    ``window``: the top share of the frame is a window far brighter than the
    sensor holds (saturated); the profile's level is the mean of the rest.
    ``stripes``: shadows of blinds, ``stripes`` dark diagonal bands of
    ``stripe_depth``. ``spot``: a lamp at (x, y) with radius r (fractions of the
    frame), ``spot_gain`` times the ambient light at its centre.
    """

    window: float = 0.0
    window_gain: float = 20.0
    stripes: int = 0
    stripe_depth: float = 0.6
    spot: tuple[float, float, float] | None = None
    spot_gain: float = 10.0

    def __post_init__(self) -> None:
        if not 0 <= self.window <= 0.6 or not 1 <= self.window_gain <= 1000:
            raise ConfigError(f"light layout: window {self.window} in [0, 0.6], window_gain in [1, 1000]")
        if not 0 <= self.stripes <= 40 or not 0 <= self.stripe_depth < 1:
            raise ConfigError("light layout: stripes in [0, 40], stripe_depth in [0, 1)")
        if self.spot is not None and (len(self.spot) != 3 or not all(0 <= v <= 2 for v in self.spot)):
            raise ConfigError(f"light layout: spot is [x, y, radius] as fractions of the frame, not {self.spot!r}")
        if not 0 <= self.spot_gain <= 1000:
            raise ConfigError("light layout: spot_gain in [0, 1000]")


LAYOUTS = ("default", "photos")  # the marker layouts a scene may use (SceneOptions.layout)


@dataclass(frozen=True, kw_only=True)
class SceneOptions:
    """What a profile changes in the scene: marker size, and printed patterns that are not the site's markers.

    ``other_dict``: markers of another dictionary (DICT_6X6_250); ``charuco``:
    ChArUco-like boards (a chessboard with 6x6 markers in its white squares);
    ``texture``: patches of random high-contrast texture. ``markers: false``
    leaves the site's markers out (scenes for phantom counts). ``layout``:
    ``default`` (six markers of 60-125 px) or ``photos`` (:data:`PHOTO_MARKERS`:
    thirteen of 21-46 px, the small ones on a chessboard, as the real
    photographs show them).
    """

    marker_scale: float = 1.0
    markers: bool = True
    other_dict: int = 0
    charuco: int = 0
    texture: int = 0
    layout: str = "default"

    def __post_init__(self) -> None:
        if not 0.05 <= self.marker_scale <= 3:
            raise ConfigError(f"scene: marker_scale {self.marker_scale} outside [0.05, 3]")
        if self.layout not in LAYOUTS:
            raise ConfigError(f"scene: layout {self.layout!r} is not one of {', '.join(LAYOUTS)}")
        for name in ("other_dict", "charuco", "texture"):
            if not 0 <= getattr(self, name) <= 20:
                raise ConfigError(f"scene: {name} {getattr(self, name)} outside [0, 20]")


_SRGB_STEPS = 16384


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear light (0..1) to sRGB-encoded uint8, through a fine look-up table."""
    lut = _srgb_lut()
    index = np.clip(linear * (_SRGB_STEPS - 1) + 0.5, 0, _SRGB_STEPS - 1).astype(np.uint16)
    return lut[index]


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded grey levels (0..255) to linear light (0..1)."""
    v = np.asarray(encoded, np.float32) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


_LUT: list[np.ndarray] = []


def _srgb_lut() -> np.ndarray:
    if not _LUT:
        x = np.arange(_SRGB_STEPS, dtype=np.float64) / (_SRGB_STEPS - 1)
        v = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
        _LUT.append(np.clip(v * 255.0 + 0.5, 0, 255).astype(np.uint8))
    return _LUT[0]


def motion_kernel(length: float, angle_deg: float) -> np.ndarray:
    """A normalised line kernel ``length`` pixels long at ``angle_deg``."""
    import cv2

    size = int(math.ceil(length)) | 1
    kernel = np.zeros((size, size), np.float32)
    c = (size - 1) / 2.0
    dx, dy = math.cos(math.radians(angle_deg)) * (length - 1) / 2, math.sin(math.radians(angle_deg)) * (length - 1) / 2
    cv2.line(kernel, (int(round(c * 16 - dx * 16)), int(round(c * 16 - dy * 16))),
             (int(round(c * 16 + dx * 16)), int(round(c * 16 + dy * 16))), 1.0, 1, cv2.LINE_AA, shift=4)
    total = float(kernel.sum())
    if total <= 0:
        kernel[int(c), int(c)] = 1.0
        total = 1.0
    return kernel / total


def camera_expose(
    lit: np.ndarray,
    level: float,
    camera: CameraModel,
    rng: np.random.Generator,
    *,
    window: np.ndarray | None = None,
    window_gain: float = 20.0,
    gain: float | None = None,
) -> np.ndarray:
    """Expose relative light ``lit`` so that the encoded frame's mean (outside ``window``) is about ``level``.

    ``window`` is a boolean mask of pixels far brighter than the sensor holds.
    """
    import cv2

    if gain is None:
        sample = lit[::4, ::4] if window is None else lit[::4, ::4][~window[::4, ::4]]
        gain = _gain_for_level(sample.ravel(), level)
    linear: np.ndarray = lit * gain
    if window is not None and window.any():
        linear[window] = window_gain
    if camera.lens_sigma > 0:
        linear = cv2.GaussianBlur(linear, (0, 0), camera.lens_sigma, borderType=cv2.BORDER_REFLECT)
    if camera.blur_px > 1:
        linear = cv2.filter2D(linear, -1, motion_kernel(camera.blur_px, camera.blur_angle), borderType=cv2.BORDER_REFLECT)
    electrons = np.maximum(linear, 0.0) * camera.full_well
    sigma = np.sqrt(electrons + camera.read_noise ** 2)
    # The well clips after the noise: a window far beyond full scale is flat 255, as on a sensor.
    noisy = np.clip(np.round(electrons + rng.standard_normal(electrons.shape, dtype=np.float32) * sigma),
                    0.0, camera.full_well)
    return srgb_encode(noisy / camera.full_well)


def _gain_for_level(sample: np.ndarray, level: float) -> float:
    """The factor that makes ``mean(srgb(clip(sample * f)))`` equal ``level`` (bisection on a log scale)."""
    if level <= 0 or sample.size == 0 or float(sample.max()) <= 0:
        return 0.0
    lut = _srgb_lut().astype(np.float32)

    def mean_at(f: float) -> float:
        idx = np.clip(sample * f * (_SRGB_STEPS - 1) + 0.5, 0, _SRGB_STEPS - 1).astype(np.int32)
        return float(lut[idx].mean())

    lo, hi = 1e-6, 1e3
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        if mean_at(mid) < level:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


_GROUPS.update(camera=CameraModel, light=LightLayout, scene=SceneOptions)

# --------------------------------------------------------------------------- profile


@dataclass(frozen=True)
class ProfilePoint:
    """Level (mean luminance 0..255) at time ``t`` seconds, with its flicker."""

    t: float
    level: float
    flicker_depth: float = 0.0
    flicker_hz: float = 0.0


@dataclass(frozen=True, kw_only=True)
class ProfileEvent:
    """From ``start`` to ``end`` seconds, another camera or light, or markers at another scale (a climb)."""

    start: float
    end: float
    camera: CameraModel | None = None
    light: LightLayout | None = None
    marker_scale: float | None = None  # multiplies the markers' size while the event lasts

    def __post_init__(self) -> None:
        if not 0 <= self.start < self.end:
            raise ConfigError(f"event from {self.start} to {self.end}: need 0 <= from < to")
        if self.marker_scale is not None and not 0.05 <= self.marker_scale <= 3:
            raise ConfigError(f"event marker_scale {self.marker_scale} outside [0.05, 3]")


@dataclass(frozen=True, kw_only=True)
class IlluminationProfile:
    """Scene brightness over time: linear between points, flicker on top."""

    points: tuple[ProfilePoint, ...]
    gradient: float = 0.3  # brightness falls by this fraction across the frame
    noise: float = 2.0  # read noise, grey levels (sigma)
    shot: float = 0.05  # shot noise: variance grows by this times the signal
    readout_s: float = 0.02  # rolling-shutter readout time (row phase of flicker)
    loop: bool = True
    camera: CameraModel = CameraModel()
    light: LightLayout = LightLayout()
    scene: "SceneOptions" = field(default_factory=lambda: SceneOptions())
    events: tuple[ProfileEvent, ...] = ()
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
        for a, b in zip(pts, pts[1:], strict=False):
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

    def event_at(self, t: float) -> ProfileEvent | None:
        """The event under way at ``t`` (the first listed, if they overlap)."""
        local = self._local_time(t)
        return next((e for e in self.events if e.start <= local < e.end), None)

    def at(self, t: float) -> "IlluminationProfile":
        """This profile with the camera and light of the event under way at ``t``."""
        event = self.event_at(t)
        if event is None or (event.camera is None and event.light is None):
            return self
        return replace(self, camera=event.camera or self.camera, light=event.light or self.light, events=())

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
        unknown = sorted(set(data) - {"points", "loop", "events", *_GLOBALS, *_GROUPS})
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
        for key, cls in _GROUPS.items():
            if key in data:
                options[key] = _group(cls, key, data[key], source, line_of(key=key))
        if "events" in data:
            options["events"] = _events(data["events"], source, line_of(key="events"))
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


def _events(raw: Any, source: str, line: int) -> tuple[ProfileEvent, ...]:
    """``events``: ``[{"from": t0, "to": t1, "camera": {...}, "light": {...}, "marker_scale": s}, ...]``."""
    if not isinstance(raw, list):
        raise ModelError(source, line, "'events' must be a list of {from, to, camera?, light?, marker_scale?}")
    out = []
    for i, item in enumerate(raw):
        where = f"events[{i}]"
        if not isinstance(item, dict):
            raise ModelError(source, line, f"{where} must be an object")
        unknown = sorted(set(item) - {"from", "to", "camera", "light", "marker_scale"})
        if unknown:
            raise ModelError(source, line, f"{where} has no {unknown[0]!r} (use from, to, camera, light, marker_scale)")
        start, end, scale = item.get("from"), item.get("to"), item.get("marker_scale")
        if not _is_number(start) or not _is_number(end) or (scale is not None and not _is_number(scale)):
            raise ModelError(source, line, f"{where}: from, to (and marker_scale) must be numbers")
        try:
            out.append(ProfileEvent(
                start=float(cast(float, start)), end=float(cast(float, end)),
                marker_scale=None if scale is None else float(scale),
                camera=_group(CameraModel, f"{where}.camera", item["camera"], source, line) if "camera" in item else None,
                light=_group(LightLayout, f"{where}.light", item["light"], source, line) if "light" in item else None))
        except ConfigError as exc:
            raise ModelError(source, line, f"{where}: {exc}") from exc
    return tuple(out)


def _group(cls: type, key: str, raw: Any, source: str, line: int) -> Any:
    """A camera/light/scene object of a profile, checked; errors name the file, line and key."""
    if not isinstance(raw, dict):
        raise ModelError(source, line, f"{key!r} must be an object")
    known = {f.name: f for f in fields(cls)}
    values: dict[str, Any] = {}
    for name, value in raw.items():
        if name not in known:
            raise ModelError(source, line, f"{key!r} has no {name!r} (use {', '.join(known)})")
        default = getattr(cls(), name)
        if name == "response":
            try:
                value = Response(value)
            except ValueError:
                raise ModelError(source, line, f"{key}.response must be srgb or linear, not {value!r}") from None
        elif name == "spot":
            if not (isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value)):
                raise ModelError(source, line, f"{key}.spot must be [x, y, radius], not {value!r}")
            value = tuple(float(v) for v in value)
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ModelError(source, line, f"{key}.{name} must be true or false, not {value!r}")
        elif isinstance(default, int):
            if not _is_number(value) or value != int(value):
                raise ModelError(source, line, f"{key}.{name} must be an integer, not {value!r}")
            value = int(value)
        elif not _is_number(value) or not math.isfinite(value):
            raise ModelError(source, line, f"{key}.{name} must be a number, not {value!r}")
        values[name] = value
    try:
        return cls(**values)
    except ConfigError as exc:
        raise ModelError(source, line, str(exc)) from exc


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _json_with_positions(text: str, source: str) -> tuple[Any, dict[int, int]]:
    """Decode JSON and remember where each list starts, to name lines in errors.

    The lists of the decoded value, visited depth first in document order, are the ``[`` outside strings
    in the text, in order. A duplicate key (whose first value JSON drops) breaks that pairing: then no
    list has a position and errors name the key's line or line 1.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ModelError(source, exc.lineno, f"not valid JSON: {exc.msg}") from exc
    lists: list[Any] = []

    def visit(value: Any) -> None:
        if isinstance(value, list):
            lists.append(value)
            for item in value:
                visit(item)
        elif isinstance(value, dict):
            for item in value.values():
                visit(item)

    visit(data)
    opens = _array_openings(text)
    if len(opens) != len(lists):
        return data, {}
    return data, {id(value): at for value, at in zip(lists, opens, strict=True)}


def _array_openings(text: str) -> list[int]:
    """Offsets of the ``[`` of a JSON text that are not inside a string."""
    openings: list[int] = []
    in_string = escaped = False
    for at, char in enumerate(text):
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char == "[":
            openings.append(at)
    return openings


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
    on_board: bool = False  # printed in a chessboard's white square (a ChArUco board), see SceneSettings.board


DEFAULT_MARKERS: tuple[MarkerPose, ...] = (
    MarkerPose(3, 0.20, 0.27, 0.24, roll=8, yaw=20),
    MarkerPose(7, 0.52, 0.30, 0.18, roll=-25, pitch=15),
    MarkerPose(12, 0.82, 0.28, 0.20, roll=40, yaw=-25),
    MarkerPose(21, 0.28, 0.72, 0.16, roll=-5, yaw=-15, pitch=-20),
    MarkerPose(33, 0.62, 0.70, 0.26, roll=15),
    MarkerPose(42, 0.88, 0.74, 0.13, roll=-40, pitch=25),
)


def _photo_markers() -> tuple[MarkerPose, ...]:
    # Sides (px at 480 rows) spread as the markers of the real photographs (sim/photographs) are at 640x480:
    # nine of 21-30 px in a chessboard's white squares (the ChArUco boards), four of 34-46 px on their own.
    sides = (21, 22, 23, 24, 25, 26, 27, 28, 30, 34, 38, 42, 46)
    rng = np.random.default_rng(1)
    out = []
    for i, side in enumerate(sides):
        x, y = 0.08 + 0.84 * ((i % 5) + 0.5) / 5, 0.1 + 0.8 * ((i // 5) + 0.5) / 3
        roll, yaw, pitch = (float(v) for v in rng.uniform(-1, 1, 3) * (10, 15, 15))
        out.append(MarkerPose(i * 17 % 250, x, y, side / 480, roll=roll, yaw=yaw, pitch=pitch, on_board=side < 32))
    return tuple(out)


# The markers as the real photographs show them: the calibration's blur condition uses these (docs/perception.md).
PHOTO_MARKERS: tuple[MarkerPose, ...] = _photo_markers()
PHOTO_QUIET_ZONE = 0.15


def markers_for(dictionary_size: int, ids: Sequence[int] = (), sizes_m: Mapping[int, float] | None = None,
                poses: Sequence[MarkerPose] = DEFAULT_MARKERS) -> tuple[MarkerPose, ...]:
    """The scene's markers for a dictionary of ``dictionary_size`` markers, or for a site's ``ids`` and sizes.

    Without ids, the default ids that the dictionary has, and for the others ids
    spread over the dictionary (a 35-marker custom dictionary has no id 42).
    With a site's ids, its first ones (as many as there are poses) take the
    poses, and a marker printed smaller than the site's largest appears
    smaller by as much (at the same distance).
    """
    if dictionary_size < 1:
        raise ConfigError(f"a dictionary of {dictionary_size} markers")
    if ids:
        chosen = sorted({int(i) for i in ids if 0 <= int(i) < dictionary_size})[: len(poses)]
        if not chosen:
            raise ConfigError(f"none of the site's ids {sorted(ids)[:6]} is in a dictionary of {dictionary_size} markers")
        known = [sizes_m[i] for i in chosen if sizes_m and sizes_m.get(i)]
        largest = max(known) if known else 0.0
        out = []  # a site with fewer ids than poses fills only the first poses
        for pose, marker_id in zip(poses, chosen, strict=False):
            factor = (sizes_m[marker_id] / largest) if largest and sizes_m and sizes_m.get(marker_id) else 1.0
            out.append(replace(pose, id=marker_id, size=min(max(pose.size * factor, 0.05), 0.6)))
        return tuple(out)
    taken: set[int] = set()
    out = []
    for k, pose in enumerate(poses):
        marker_id = pose.id if pose.id < dictionary_size else (k * 7 + 3) % dictionary_size
        while marker_id in taken:
            marker_id = (marker_id + 1) % dictionary_size
        taken.add(marker_id)
        out.append(replace(pose, id=marker_id))
    return tuple(out[:dictionary_size])


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
    marker_scale: float = 1.0  # multiplies every marker's size (small markers: 0.3 gives 3-6 px per cell)
    other_dict: int = 0  # markers of DICT_6X6_250 printed in the background
    charuco: int = 0  # ChArUco-like boards in the background
    texture: int = 0  # patches of random high-contrast texture
    quiet_zone: float = 0.25  # white margin around each marker, as a fraction of its side
    board: float = 0.15  # markers on_board: the chessboard's black squares beside theirs, this deep (x side)
    # How the site prints its markers (a site file's "layout", kgadapt.onboard.flight.site): "apart" as the
    # poses say; "chessboard": every marker in a chessboard's white square (on_board); "touching": a marker in
    # every square of a chessboard, so each touches its diagonal neighbours at the corners (PRINT_LAYOUTS).
    print_layout: str = "apart"
    seed: int = 1

    def __post_init__(self) -> None:
        if self.print_layout not in PRINT_LAYOUTS:
            raise ConfigError(f"scene: print_layout {self.print_layout!r} is not one of {', '.join(PRINT_LAYOUTS)}")

    def with_options(self, options: "SceneOptions") -> "SceneSettings":
        """These settings as a profile's ``scene`` object changes them."""
        markers, quiet = self.markers, self.quiet_zone
        if options.layout == "photos":
            markers, quiet = PHOTO_MARKERS, PHOTO_QUIET_ZONE
        return replace(self, markers=markers if options.markers else (), marker_scale=options.marker_scale,
                       other_dict=options.other_dict, charuco=options.charuco, texture=options.texture,
                       quiet_zone=quiet)


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


_WHITE, _BLACK = 0.92, 0.04  # reflectances


class SyntheticScene:
    """Renders the markers of ``settings`` at any time and light level."""

    def __init__(self, settings: SceneSettings = SceneSettings()) -> None:
        import cv2

        self.settings = settings
        w, h = settings.width, settings.height
        if w < 64 or h < 64:
            raise ConfigError(f"synthetic scene {w}x{h}: use at least 64x64")
        dictionary = aruco_dictionary(settings.dictionary)
        self._rng = np.random.default_rng(settings.seed)
        self._background = self._make_background(cv2, w, h)
        ys = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
        xs = np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :]
        self._ramp = (0.6 * xs + 0.4 * ys).astype(np.float32)  # 0 at top-left, 1 at bottom-right
        self._fields: dict[Any, np.ndarray] = {}
        self._patches: dict[int, tuple[np.ndarray, float, int]] = {}
        self._poses = tuple(replace(p, size=p.size * settings.marker_scale) for p in settings.markers)
        for pose in self._poses:
            side = max(16, int(round(pose.size * h * 1.2)))
            code = cv2.aruco.generateImageMarker(dictionary, pose.id, side).astype(np.float32) / 255.0
            if settings.print_layout == "touching":
                self._patches[pose.id] = _touching_patch(code, int(dictionary.markerSize) + 2, self._rng)
                continue
            quiet = int(round(side * settings.quiet_zone))
            ring = int(round(side * settings.board)) if pose.on_board or settings.print_layout == "chessboard" else 0
            pad = quiet + ring
            patch = np.ones((side + 2 * pad, side + 2 * pad), np.float32)
            if ring:
                # The chessboard squares beside the marker's white square are black; those at its corners white.
                inner = slice(ring, ring + side + 2 * quiet)
                patch[:ring, inner] = patch[-ring:, inner] = patch[inner, :ring] = patch[inner, -ring:] = 0.0
            patch[pad:pad + side, pad:pad + side] = code
            patch = _BLACK + (_WHITE - _BLACK) * patch
            self._patches[pose.id] = (patch, float(pad), side)

    def _make_background(self, cv2: Any, w: int, h: int) -> np.ndarray:
        # Low-contrast blotches (a floor or wall) plus dark squares without a valid code.
        noise = self._rng.random((max(h // 40, 2), max(w // 40, 2))).astype(np.float32)
        base = 0.45 + 0.2 * cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
        for _ in range(self.settings.distractors):
            s = int(self._rng.uniform(0.05, 0.1) * h)
            x0 = int(self._rng.uniform(0, w - s))
            y0 = int(self._rng.uniform(0, h - s))
            base[y0:y0 + s, x0:x0 + s] = _BLACK + 0.1
            # A dark frame one sixth of the side wide around a light inside: a marker's outline with no
            # code. (A light centre of a third of the side was DICT_4X4_50's id 17 at some poses.)
            inner = max(s // 6, 1)
            base[y0 + inner:y0 + s - inner, x0 + inner:x0 + s - inner] = _WHITE * 0.8
        self._add_patterns(cv2, base)
        frame: np.ndarray = np.clip(base, 0.0, 1.0).astype(np.float32)
        return frame

    def _add_patterns(self, cv2: Any, base: np.ndarray) -> None:
        """Printed things that are not the site's markers: other dictionaries, ChArUco-like boards, texture."""
        h, w = base.shape
        s, rng = self.settings, self._rng
        other = aruco_dictionary("DICT_6X6_250")

        def place(patch: np.ndarray) -> None:
            ph, pw = patch.shape
            if ph >= h or pw >= w:
                return
            y0, x0 = int(rng.uniform(0, h - ph)), int(rng.uniform(0, w - pw))
            base[y0:y0 + ph, x0:x0 + pw] = patch

        for _ in range(s.other_dict):
            side = int(rng.uniform(0.12, 0.22) * h)
            code = cv2.aruco.generateImageMarker(other, int(rng.integers(0, 250)), side, borderBits=1)
            quiet = max(2, side // 6)
            place(_BLACK + (_WHITE - _BLACK) * np.pad(code.astype(np.float32) / 255.0, quiet, constant_values=1.0))
        for _ in range(s.charuco):
            squares = int(rng.integers(4, 7))
            board = cv2.aruco.CharucoBoard((squares, squares - 1), 0.04, 0.03, other)
            side = int(rng.uniform(0.35, 0.55) * h)
            # Drawn at a size OpenCV always accepts, then scaled to the one wanted.
            image = board.generateImage((squares * 40, (squares - 1) * 40), marginSize=10)
            image = cv2.resize(image, (side, int(side * (squares - 1) / squares)), interpolation=cv2.INTER_AREA)
            place(_BLACK + (_WHITE - _BLACK) * image.astype(np.float32) / 255.0)
        for _ in range(s.texture):
            side = int(rng.uniform(0.2, 0.35) * h)
            cells = int(rng.integers(6, 24))
            blocks = (rng.random((cells, cells)) > 0.5).astype(np.float32)
            patch = cv2.resize(blocks, (side, side), interpolation=cv2.INTER_NEAREST)
            patch = cv2.GaussianBlur(patch, (3, 3), 0) if rng.random() < 0.5 else patch
            place(_BLACK + (_WHITE - _BLACK) * patch)

    def reflectance(self, t: float, *, scale: float = 1.0) -> tuple[np.ndarray, list[Truth]]:
        """The scene's reflectance (0..1) at time ``t`` and the markers' truth (markers ``scale`` times their size)."""
        import cv2

        s = self.settings
        w, h = s.width, s.height
        image = self._background.copy()
        phase = 2 * math.pi * t / s.sway_period_s if s.sway_period_s > 0 else 0.0
        dx, dy = s.sway_px * math.sin(phase), 0.6 * s.sway_px * math.sin(2 * phase + 0.7)
        truth: list[Truth] = []
        for pose in self._poses:
            patch, quiet, side = self._patches[pose.id]
            shown = pose if scale == 1.0 else replace(pose, size=pose.size * scale)
            corners = _project(shown, w, h) + np.array([dx, dy], np.float32)
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
        event = profile.event_at(t)
        profile = profile.at(t)
        image, truth = self.reflectance(t, scale=event.marker_scale if event and event.marker_scale else 1.0)
        exposed = self.expose(image, level, profile, t=t, rng=rng)
        if profile.light.window > 0:
            # A marker the window covers is not seen: it leaves the truth.
            edge = profile.light.window * self.settings.height + 2
            covered = [m for m in truth if min(y for _x, y in m.corners) <= edge]
            truth = [m for m in truth if m not in covered]
            # Partly covered markers may or may not be found: neither a hit nor a false detection.
            extras = {"hidden": [m.id for m in covered]}
            return RenderedFrame(exposed, truth, level, t, extras)
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
        """Light ``reflectance`` so that the frame's mean is about ``level``; add flicker and noise.

        With the sRGB camera (the default) the level is the mean of the encoded
        frame outside a window, as a real camera would deliver it.
        """
        rng = rng or self._rng
        light = self._light_field(profile)
        lit = reflectance * light
        rows = profile.row_gains(t, lit.shape[0])
        if profile.camera.response is Response.SRGB:
            if rows is not None:
                # Flicker changes the light around the level the profile asks for, not the level itself.
                window = self._window_mask(profile)
                sample = lit[::4, ::4] if window is None else lit[::4, ::4][~window[::4, ::4]]
                gain = _gain_for_level(sample.ravel(), level)
                lit = lit * gain * rows[:, None]
                return camera_expose(lit, 0.0, profile.camera, rng, window=window,
                                     window_gain=profile.light.window_gain, gain=1.0)
            return camera_expose(lit, level, profile.camera, rng, window=self._window_mask(profile),
                                 window_gain=profile.light.window_gain)
        gain = level / max(float(lit.mean()), 1e-6)
        if rows is not None:
            lit *= rows[:, None]
        signal = lit * gain
        sigma = np.sqrt(profile.noise ** 2 + profile.shot * signal) if profile.shot > 0 else profile.noise
        noisy = signal + rng.standard_normal(signal.shape, dtype=np.float32) * sigma
        window = self._window_mask(profile)
        if window is not None:
            noisy[window] = 255.0
        frame: np.ndarray = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
        return frame

    def _light_field(self, profile: IlluminationProfile) -> np.ndarray:
        """The relative light over the frame: gradient, blind stripes, spotlight."""
        key = (profile.gradient, profile.light)
        cached = self._fields.get(key)
        if cached is not None:
            return cached
        h, w = self._ramp.shape
        light = 1.0 - profile.gradient * self._ramp
        layout = profile.light
        if layout.stripes > 0:
            ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
            phase = (xs + ys) / (w + h) * layout.stripes
            shadow = (np.sin(2 * math.pi * phase) > 0.2).astype(np.float32)
            light = light * (1.0 - layout.stripe_depth * _smooth(shadow, 7))
        if layout.spot is not None:
            x, y, r = layout.spot
            ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
            d2 = ((xs / w - x) ** 2 + (ys / h - y) ** 2) / max(r * r, 1e-6)
            light = light * (1.0 + layout.spot_gain * np.exp(-d2))
        light = light.astype(np.float32)
        self._fields = {key: light}  # one profile at a time: keep only the last field
        return light

    def _window_mask(self, profile: IlluminationProfile) -> np.ndarray | None:
        share = profile.light.window
        if share <= 0:
            return None
        h, w = self._ramp.shape
        mask = np.zeros((h, w), bool)
        mask[: int(round(share * h)), :] = True
        return mask


def _touching_patch(code: np.ndarray, cells: int, rng: np.random.Generator) -> tuple[np.ndarray, float, int]:
    """A marker (``code``, 0..1, ``cells`` cells a side with its border) in a board with a marker in every square.

    Around it, half of each neighbouring square: those beside it hold inverted
    codes (their white border is the marker's only margin, one cell), those at
    its corners hold codes with a black border that touches the marker's at the
    corner. The neighbours' codes are random bits, and cut in half they form no
    marker of their own.
    """
    import cv2

    side = code.shape[0]

    def neighbour(inverted: bool) -> np.ndarray:
        bits = np.zeros((cells, cells), np.float32)
        bits[1:-1, 1:-1] = rng.random((cells - 2, cells - 2)) > 0.5
        square: np.ndarray = cv2.resize(bits, (side, side), interpolation=cv2.INTER_NEAREST)
        return 1.0 - square if inverted else square

    board = np.ones((3 * side, 3 * side), np.float32)
    for row in range(3):
        for col in range(3):
            square = code if (row, col) == (1, 1) else neighbour(inverted=(row + col) % 2 == 1)
            board[row * side:(row + 1) * side, col * side:(col + 1) * side] = square
    band = max(int(round(2 * side / cells)), 2)  # two cells of each neighbour: its border and a row of bits
    patch = _BLACK + (_WHITE - _BLACK) * board[side - band:2 * side + band, side - band:2 * side + band]
    return patch, float(band), side


def _smooth(image: np.ndarray, k: int) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(image, (k, k), 0)


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
    corners: np.ndarray = (uv + np.array([pose.x * width, pose.y * height])).astype(np.float32)
    return corners


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
