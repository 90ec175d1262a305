"""Landing targets the autopilot accepts: the marker's position from its size, in each autopilot's frame.

Inputs: a **camera file** (intrinsics and how the camera is mounted) and the
**site file** (the markers of a site with their printed sizes, :mod:`kgadapt.onboard.flight.site`,
the same file the confirmer reads), both JSON, checked on load::

    camera.json   {"fx": 615.0, "fy": 615.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480,
                   "distortion": [k1, k2, p1, p2, k3],          # optional, OpenCV's order
                   "mount": {"yaw_deg": 0.0, "offset_m": [0.05, 0.0, 0.02]}}   # optional
    pad-a.site    {"site": "pad-a", "dictionary": "DICT_4X4_50",
                   "markers": [{"id": 7, "size_m": 0.30}, {"id": 8, "size_m": 0.15}]}

:class:`TargetBuilder` turns one detected marker into a :class:`LandingTarget`:

1. marker size known -> its pose (OpenCV ``solvePnP``, IPPE for squares) in the
   camera frame -> body FRD through the mounting -> for **ArduPilot**
   ``position_valid=1`` in MAV_FRAME_BODY_FRD with ``distance`` its norm; for
   **PX4** rotated by the attitude heard nearest the frame's time and added to
   the vehicle's local position: ``position_valid=1`` in MAV_FRAME_LOCAL_NED;
   A marker of the site's landing pad (one with a ``position``) stands for the
   pad's landing point: its offset (NED) turned into the body frame by the
   attitude and added, so every marker of the pad leads to the same spot;
2. no size, or no pose -> angles, with ``distance`` from the downward
   rangefinder along the line of sight when one is heard (ArduPilot then places
   the target even without its own rangefinder);
3. else angles alone.

Angles are always filled, in the body frame (``angle_x`` to the right,
``angle_y`` backwards), so set ``PLND_YAW_ALIGN=0`` and ``PLND_CAM_POS_*=0``:
the camera file carries the mounting.

:class:`TargetHold` keeps the last confirmed target as a point in local NED
(or, without a local position, in the body frame) and predicts it for the
vehicle's current attitude and position, so the bridge can re-send it between
detections for at most ``hold_s``.
"""

from __future__ import annotations

import enum
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from pymavlink.dialects.v20 import common as mavlink2

from kgadapt.onboard.flight.confirmation import Place
from kgadapt.onboard.flight.geometry import Vector, body_to_ned, camera_to_body, ned_to_body, norm, vector
from kgadapt.onboard.flight.mavlink import FlightState, LandingTarget
from kgadapt.onboard.flight.site import SiteMarkers, load_site
from kgadapt.shared.errors import ConfigError


def _number(where: str, name: str, value: Any, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {name} must be a finite number, not {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{where}: {name} must be positive, not {value!r}")
    return float(value)


def _read_json(path: str | Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot read: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{what} {path}: not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{what} {path}: must be a JSON object")
    return data


@dataclass(frozen=True, kw_only=True)
class CameraModel:
    """Pinhole intrinsics (pixels), optional distortion, and the camera's mounting on the vehicle."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 0
    height: int = 0
    distortion: tuple[float, ...] = ()
    yaw_deg: float = 0.0  # camera looking down; 0 = top of the image towards the nose
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # camera position in body FRD

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "camera") -> "CameraModel":
        known = {"fx", "fy", "cx", "cy", "width", "height", "distortion", "mount", "name"}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}; known: {', '.join(sorted(known))}")
        for name in ("fx", "fy", "cx", "cy"):
            if name not in data:
                raise ConfigError(f"{where}: lacks {name}")
        values = {n: _number(where, n, data[n], positive=n in ("fx", "fy")) for n in ("fx", "fy", "cx", "cy")}
        width, height = data.get("width", 0), data.get("height", 0)
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"{where}: {name} must be a whole number of pixels, not {value!r}")
        if width and not 0 <= values["cx"] <= width or height and not 0 <= values["cy"] <= height:
            raise ConfigError(f"{where}: principal point ({values['cx']}, {values['cy']}) outside the "
                              f"{width}x{height} image")
        distortion = data.get("distortion", [])
        if not isinstance(distortion, list) or len(distortion) not in (0, 4, 5, 8):
            raise ConfigError(f"{where}: distortion must be a list of 4, 5 or 8 numbers (OpenCV's order)")
        mount = data.get("mount", {})
        if not isinstance(mount, dict) or set(mount) - {"yaw_deg", "offset_m"}:
            raise ConfigError(f"{where}: mount must be {{\"yaw_deg\": ..., \"offset_m\": [x, y, z]}}")
        offset = mount.get("offset_m", [0.0, 0.0, 0.0])
        if not isinstance(offset, list) or len(offset) != 3:
            raise ConfigError(f"{where}: mount.offset_m must be [forward, right, down] metres")
        return cls(**values, width=width, height=height,
                   distortion=tuple(_number(where, "distortion", d) for d in distortion),
                   yaw_deg=_number(where, "mount.yaw_deg", mount.get("yaw_deg", 0.0)),
                   offset_m=vector(_number(where, "mount.offset_m", o) for o in offset))

    def as_dict(self) -> dict[str, Any]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width,
                "height": self.height, "distortion": list(self.distortion),
                "mount": {"yaw_deg": self.yaw_deg, "offset_m": list(self.offset_m)}}


def load_camera(path: str | Path) -> CameraModel:
    """A camera file, checked; ConfigError names the file and the field."""
    return CameraModel.from_dict(_read_json(path, "camera file"), where=f"camera file {path}")


# One site file format for the confirmer and the landing targets (onboard/flight/site.py); the old name stays
# for callers that load a site for its marker sizes.
load_site_markers = load_site


def marker_pose(corners: Sequence[Sequence[float]], size_m: float, camera: CameraModel) -> tuple[float, float, float] | None:
    """The marker centre in the camera's optical frame (m) from its four corners (ArUco order), or None."""
    import cv2  # only when a pose is wanted
    import numpy as np

    h = size_m / 2.0
    obj = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)
    img = np.array(corners, dtype=np.float64).reshape(4, 2)
    k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], dtype=np.float64)
    dist = np.array(camera.distortion, dtype=np.float64) if camera.distortion else None
    try:
        ok, _rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error:
        return None
    if not ok:
        return None
    t = vector(float(v) for v in tvec.reshape(3))
    return t if t[2] > 0 and all(math.isfinite(v) for v in t) else None


class AutopilotProfile(enum.Enum):
    """Which LANDING_TARGET an autopilot takes with a position."""

    ARDUPILOT = "ardupilot"  # MAV_FRAME_BODY_FRD, distance > 0 (AC_PrecLand_MAVLink::handle_msg)
    PX4 = "px4"  # MAV_FRAME_LOCAL_NED: absolute position in the local frame (landing_target_estimator)

    @classmethod
    def of(cls, name: str | None, state: FlightState | None = None) -> "AutopilotProfile":
        """``ardupilot``, ``px4``, or ``auto``/None: from the autopilot's heartbeat (ArduPilot if unknown)."""
        if name in (None, "auto"):
            return cls.PX4 if state is not None and state.autopilot == "px4" else cls.ARDUPILOT
        try:
            return cls(name)
        except ValueError:
            raise ConfigError(f"autopilot profile {name!r}: use ardupilot, px4 or auto") from None


PoseAt = Callable[[float], "tuple[Vector, Vector | None] | None"]  # (attitude, position NED) at a time


def _body_angles(v_body: Sequence[float]) -> tuple[float, float]:
    """LANDING_TARGET angles of a body-FRD direction, as ArduPilot reads them back (los = (-tan ay, tan ax, 1))."""
    f, r, d = v_body
    d = max(float(d), 1e-6)
    return math.atan2(r, d), math.atan2(-f, d)


class TargetBuilder:
    """One detected marker -> the LANDING_TARGET for the autopilot (see the module docstring)."""

    def __init__(self, camera: CameraModel, markers: SiteMarkers | None = None) -> None:
        self.camera = camera
        self.markers = markers
        self.counters = {"position": 0, "rangefinder": 0, "angles": 0}

    def locate(self, corners: Sequence[Sequence[float]], *, marker_id: int, frame_time: float, state: FlightState,
               pose_at: PoseAt | None) -> Place | None:
        """Where the marker lies in the local frame at the frame's time (for the confirmation); None if unknown.

        Needs the vehicle's attitude and local position heard near the frame's time. The marker's
        distance comes from its size when the site gives it, else from the height (the downward
        rangefinder, or the height above the local origin: flat ground assumed).
        """
        pose = pose_at(frame_time) if pose_at is not None else None
        if pose is None:
            return None
        attitude, position = pose
        if position is None:
            return None
        cam = self.camera
        size = self.markers.size_of(marker_id) if self.markers is not None else None
        tvec = marker_pose(corners, size, cam) if size else None
        if tvec is not None and size:
            body = camera_to_body(tvec, yaw_deg=cam.yaw_deg, offset=cam.offset_m)
        else:
            u = sum(p[0] for p in corners) / 4.0
            v = sum(p[1] for p in corners) / 4.0
            ray = camera_to_body(((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0), yaw_deg=cam.yaw_deg)
            unit = tuple(c / norm(ray) for c in ray)
            down = body_to_ned(attitude, unit)[2]
            height = state.rangefinder_m or (-float(position[2]) if -float(position[2]) > 0.3 else None)
            if not height or down <= 0.05:
                return None
            body = vector(c * height / down for c in unit)
            side_px = sum(math.dist(corners[i], corners[(i + 1) % 4]) for i in range(4)) / 4.0
            size = side_px * norm(body) / cam.fx  # its side as the image shows it at that distance
        rel = body_to_ned(attitude, body)
        to = self.markers.to_landing_point(marker_id) if self.markers is not None else None
        if to is not None:  # a pad's marker: the place is the pad's landing point
            rel = (rel[0] + to[0], rel[1] + to[1], rel[2] + to[2])
        ned = (float(position[0]) + rel[0], float(position[1]) + rel[1], float(position[2]) + rel[2])
        if tvec is None:  # the distance from a height: no measurement model, the confirmer's fixed rule
            return Place(ned, float(size), norm(body))
        # How it was measured, for the confirmer's tolerance (kgadapt.onboard.flight.confirmation).
        side_px = sum(math.dist(corners[i], corners[(i + 1) % 4]) for i in range(4)) / 4.0
        velocity, rates = state.velocity_ned, state.rates
        return Place(ned, float(size), norm(body), los=vector(c / norm(rel) for c in rel), side_px=side_px,
                     focal_px=(cam.fx + cam.fy) / 2.0, speed_mps=norm(velocity) if velocity else 0.0,
                     rate_rad_s=norm(rates) if rates else 0.0)

    def build(self, corners: Sequence[Sequence[float]], *, marker_id: int, frame_time: float,
              profile: AutopilotProfile, state: FlightState, pose_at: PoseAt | None = None,
              measured: Sequence[float] | None = None) -> tuple[LandingTarget, "HeldTarget | None"]:
        """The target to send now, and what to hold for re-sending (None if it cannot be predicted).

        ``measured``: the marker's position in the camera's optical frame as the detector measured it (its
        ``poses``), used in place of the pose solved here from the site's marker size; the camera's mounting,
        the pad's landing point, the autopilot's frame and the hold apply to it alike.
        """
        cam = self.camera
        u = sum(p[0] for p in corners) / 4.0
        v = sum(p[1] for p in corners) / 4.0
        xs, ys = [p[0] for p in corners], [p[1] for p in corners]
        size_x = math.atan((max(xs) - cam.cx) / cam.fx) - math.atan((min(xs) - cam.cx) / cam.fx)
        size_y = math.atan((max(ys) - cam.cy) / cam.fy) - math.atan((min(ys) - cam.cy) / cam.fy)
        ray_body = camera_to_body(((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0), yaw_deg=cam.yaw_deg)
        angle_x, angle_y = _body_angles(ray_body)
        pose = pose_at(frame_time) if pose_at is not None else None
        attitude = pose[0] if pose else state.attitude
        position = pose[1] if pose and pose[1] is not None else state.position_ned
        size = self.markers.size_of(marker_id) if self.markers is not None else None
        if measured is not None:
            tvec: Sequence[float] | None = tuple(float(c) for c in measured)
        else:
            tvec = marker_pose(corners, size, cam) if size else None
        common: dict[str, Any] = dict(time=float(frame_time), size_x=size_x, size_y=size_y,
                                      target_num=marker_id if 0 <= marker_id <= 255 else 0)
        if tvec is not None:
            body = self._landing_point(camera_to_body(tvec, yaw_deg=cam.yaw_deg, offset=cam.offset_m), marker_id,
                                       attitude)
            angle_x, angle_y = _body_angles(body)
            held = HeldTarget.of(body, attitude, position, marker_id, frame_time)
            self.counters["position"] += 1
            if profile is AutopilotProfile.PX4:
                if held.ned is None:  # PX4 needs the local frame: without it only angles (its IR-Lock path)
                    return LandingTarget(angle_x=angle_x, angle_y=angle_y, distance=norm(body), **common), held
                return LandingTarget(angle_x=angle_x, angle_y=angle_y, distance=norm(body), position=held.ned,
                                     frame=mavlink2.MAV_FRAME_LOCAL_NED, **common), held
            return LandingTarget(angle_x=angle_x, angle_y=angle_y, distance=norm(body), position=body, **common), held
        height = state.rangefinder_m
        if height:
            # Angles plus the distance along the line of sight from the rangefinder's height.
            unit = tuple(c / norm(ray_body) for c in ray_body)
            down = body_to_ned(attitude, unit)[2] if attitude else unit[2]
            if down > 0.05:
                distance = height / down
                body = self._landing_point(vector(c * distance for c in unit), marker_id, attitude)
                angle_x, angle_y = _body_angles(body)
                distance = norm(body)
                self.counters["rangefinder"] += 1
                return (LandingTarget(angle_x=angle_x, angle_y=angle_y, distance=distance, **common),
                        HeldTarget.of(body, attitude, position, marker_id, frame_time))
        self.counters["angles"] += 1
        return LandingTarget(angle_x=angle_x, angle_y=angle_y, **common), None

    def _landing_point(self, body: Sequence[float], marker_id: int,
                       attitude: Sequence[float] | None) -> tuple[float, float, float]:
        """A pad marker's place in body FRD moved to the pad's landing point (the site's offset, NED, turned by
        the attitude); the marker itself when it is its own landing point or the attitude is unknown."""
        to = self.markers.to_landing_point(marker_id) if self.markers is not None else None
        if to is None or attitude is None:
            if to is not None:
                self.counters["pad_offset_unapplied"] = self.counters.get("pad_offset_unapplied", 0) + 1
            return (float(body[0]), float(body[1]), float(body[2]))
        shift = ned_to_body(attitude, to)
        return (float(body[0]) + shift[0], float(body[1]) + shift[1], float(body[2]) + shift[2])


@dataclass(frozen=True)
class HeldTarget:
    """A confirmed target as a point: in local NED when the vehicle's pose was known, else in body FRD."""

    body: tuple[float, float, float]
    ned: tuple[float, float, float] | None
    marker_id: int
    seen: float  # epoch of the frame
    with_position: bool = True  # the target was sent with a position (else angles + distance)

    @classmethod
    def of(cls, body: Sequence[float], attitude: Sequence[float] | None, position: Sequence[float] | None,
           marker_id: int, seen: float) -> "HeldTarget":
        ned: Vector | None = None
        if attitude is not None and position is not None:
            rel = body_to_ned(attitude, body)
            ned = vector(float(position[i]) + rel[i] for i in range(3))
        return cls(vector(float(c) for c in body), ned, marker_id, float(seen))

    def predict(self, now: float, state: FlightState, profile: AutopilotProfile) -> LandingTarget | None:
        """The target as it should look from the vehicle's current attitude and position."""
        body = self.body
        if self.ned is not None and state.attitude is not None and state.position_ned is not None:
            rel = tuple(self.ned[i] - state.position_ned[i] for i in range(3))
            body = ned_to_body(state.attitude, rel)
        elif self.ned is not None and profile is AutopilotProfile.PX4:
            pass  # PX4 takes the fixed NED point; the vehicle's motion does not change it
        if body[2] <= 0.05:
            return None  # the target is no longer below the vehicle
        angle_x, angle_y = _body_angles(body)
        target_num = self.marker_id if 0 <= self.marker_id <= 255 else 0
        if profile is AutopilotProfile.PX4:
            if self.ned is None:
                return None
            return LandingTarget(time=now, angle_x=angle_x, angle_y=angle_y, distance=norm(body),
                                 target_num=target_num, position=self.ned, frame=mavlink2.MAV_FRAME_LOCAL_NED)
        return LandingTarget(time=now, angle_x=angle_x, angle_y=angle_y, distance=norm(body), target_num=target_num,
                             position=body)


class TargetHold:
    """The last confirmed target, re-sent between detections for at most ``hold_s``."""

    def __init__(self, *, hold_s: float, resend_hz: float) -> None:
        if hold_s < 0 or resend_hz <= 0:
            raise ConfigError(f"target hold: hold_s >= 0 and resend_hz > 0, not {hold_s}, {resend_hz}")
        self.hold_s = hold_s
        self.period_s = 1.0 / resend_hz
        self.held: HeldTarget | None = None
        self.last_sent = -math.inf  # epoch of the last LANDING_TARGET, detected or predicted

    def confirm(self, held: HeldTarget | None, sent_at: float) -> None:
        self.held = held
        self.last_sent = sent_at

    def due(self, now: float) -> bool:
        held = self.held
        return held is not None and now - held.seen <= self.hold_s and now - self.last_sent >= self.period_s

    def predicted(self, now: float, state: FlightState, profile: AutopilotProfile) -> LandingTarget | None:
        if self.held is None or now - self.held.seen > self.hold_s:
            self.held = None
            return None
        return self.held.predict(now, state, profile)

