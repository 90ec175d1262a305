"""Frames and rotations of the flight link: body FRD, local NED, and the camera's optical frame.

Attitude is (roll, pitch, yaw) in radians, as MAVLink's ATTITUDE gives it
(aerospace Z-Y-X order): ``body_to_ned`` rotates a body-FRD vector into the
local NED frame, ``ned_to_body`` back.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

Vector = tuple[float, float, float]


def vector(values: Iterable[float]) -> Vector:
    """Three numbers as a Vector; ValueError for any other count."""
    x, y, z = values
    return (x, y, z)


def rotation(attitude: Sequence[float]) -> tuple[Vector, Vector, Vector]:
    """The body-to-NED rotation matrix (rows) for (roll, pitch, yaw)."""
    roll, pitch, yaw = (float(a) for a in attitude)
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return (
        (cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy),
        (cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy),
        (-sp, sr * cp, cr * cp),
    )


def body_to_ned(attitude: Sequence[float], v: Sequence[float]) -> Vector:
    r = rotation(attitude)
    return vector(sum(r[i][j] * float(v[j]) for j in range(3)) for i in range(3))


def ned_to_body(attitude: Sequence[float], v: Sequence[float]) -> Vector:
    r = rotation(attitude)
    return vector(sum(r[j][i] * float(v[j]) for j in range(3)) for i in range(3))


def norm(v: Sequence[float]) -> float:
    return math.sqrt(sum(float(c) * float(c) for c in v))


def camera_to_body(v_cam: Sequence[float], *, yaw_deg: float = 0.0,
                   offset: Sequence[float] = (0.0, 0.0, 0.0)) -> Vector:
    """A point in a downward camera's optical frame (x right, y down the image, z out) in body FRD.

    With ``yaw_deg`` 0 the top of the image points to the nose: forward = -y, right = x,
    down = z. ``yaw_deg`` turns the camera clockwise (seen from above) about the body's
    down axis; ``offset`` is the camera's position in body FRD (m).
    """
    x, y, z = (float(c) for c in v_cam)
    f, r = -y, x
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return (c * f - s * r + float(offset[0]), s * f + c * r + float(offset[1]), z + float(offset[2]))


def body_to_camera(v_body: Sequence[float], *, yaw_deg: float = 0.0,
                   offset: Sequence[float] = (0.0, 0.0, 0.0)) -> Vector:
    """The inverse of :func:`camera_to_body`."""
    f, r, d = (float(v_body[i]) - float(offset[i]) for i in range(3))
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    f, r = c * f + s * r, -s * f + c * r
    return (r, -f, d)
