"""A marker lying on the ground, seen by the vehicle's downward camera: detections without a renderer.

:class:`MarkerScene` projects the four corners of a square marker (``size_m``,
centre at ``north, east`` metres from home, on the ground, its top edge
towards north) through the vehicle's attitude and position, the camera's
mounting and its pinhole intrinsics, and returns them in ArUco's corner order
— what a detector would report, without its noise. The vehicle's pose comes
from a callable: the fake flight controller's truth in tests, the autopilot's
own LOCAL_POSITION_NED and ATTITUDE against SITL.

:func:`run_detections` publishes such detections over Zenoh at a given rate,
as the detector would, for the flight bridge to follow.
"""

from __future__ import annotations

import math
import random
import threading
import time
from dataclasses import dataclass
from typing import Callable

from kgadapt.onboard.flight.geometry import body_to_camera, ned_to_body
from kgadapt.onboard.flight.landing_targets import CameraModel

Pose = tuple[tuple[float, float, float], tuple[float, float, float]]  # attitude (rad), position NED (m)


@dataclass(frozen=True)
class MarkerScene:
    camera: CameraModel
    north: float
    east: float
    size_m: float
    marker_id: int = 7

    def corners(self, pose: Pose) -> list[list[float]] | None:
        """The marker's corners in pixels (top-left, top-right, bottom-right, bottom-left), None if not in view."""
        attitude, position = pose
        h = self.size_m / 2.0
        world = [(self.north + h, self.east - h), (self.north + h, self.east + h),
                 (self.north - h, self.east + h), (self.north - h, self.east - h)]
        cam = self.camera
        points = []
        for n, e in world:
            rel = (n - position[0], e - position[1], 0.0 - position[2])
            x, y, z = body_to_camera(ned_to_body(attitude, rel), yaw_deg=cam.yaw_deg, offset=cam.offset_m)
            if z <= 0.05:
                return None
            u, v = cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy
            if cam.width and not (0 <= u < cam.width and 0 <= v < cam.height):
                return None
            points.append([u, v])
        return points


def run_detections(session, robot: str, scene: MarkerScene, pose: Callable[[], Pose | None], *, rate_hz: float,
                   stop: threading.Event, instance: str = "scene", noise_px: float = 0.0, seed: int = 12) -> dict:
    """Publish ``detections`` of ``scene`` at ``rate_hz`` until ``stop``; returns counts (sent, out of view)."""
    from kgadapt.shared import keys, messages

    publisher = session.declare_publisher(keys.detector_markers(robot, instance))
    counts = {"sent": 0, "out_of_view": 0}
    rng = random.Random(seed)
    seq = 0
    period = 1.0 / rate_hz
    next_at = time.monotonic()
    try:
        while not stop.is_set():
            current = pose()
            frame_time = time.time()
            corners = scene.corners(current) if current is not None else None
            if corners is None:
                counts["out_of_view"] += 1
            else:
                seq += 1
                if noise_px > 0:
                    corners = [[u + rng.gauss(0, noise_px), v + rng.gauss(0, noise_px)] for u, v in corners]
                publisher.put(messages.encode("detections", {
                    "instance": instance, "config": "scene", "host": "scene", "seq": seq,
                    "frame_time": frame_time, "time": time.time(), "ids": [[scene.marker_id]],
                    "corners": [[corners]], "processing_ms": 0.0,
                }))
                counts["sent"] += 1
            next_at += period
            stop.wait(max(0.0, next_at - time.monotonic()))
    finally:
        publisher.undeclare()
    return counts


def fake_pose(fc) -> Callable[[], Pose]:
    """The fake flight controller's true attitude and position."""
    def pose() -> Pose:
        v = fc.vehicle
        return (v.roll, v.pitch, v.yaw), v.position_ned
    return pose


def link_pose(link) -> Callable[[], Pose | None]:
    """The attitude and local position the autopilot reports (for a real or SITL autopilot)."""
    def pose() -> Pose | None:
        s = link.state
        if s.attitude is None or s.position_ned is None:
            return None
        return s.attitude, s.position_ned
    return pose


def horizontal_error(north: float, east: float, position: tuple[float, float, float]) -> float:
    return math.hypot(position[0] - north, position[1] - east)
