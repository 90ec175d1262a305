"""Real photographs of ArUco markers through the camera model (tests, calibration checks, the bench).

The photographs (``sim/photographs``, sources in its SOURCES.txt) are
evenly lit desk photos. :func:`photo_frames` turns one into the frames a
fixed-exposure camera would take of the same scene in less light: the photo's
sRGB values are decoded to linear light, scaled so the encoded frame's mean is
the asked level, given shot and read noise and re-encoded
(:func:`kgadapt.onboard.perception.scene.camera_expose`), with a small random shift per frame as
a hovering camera would see it. :func:`photo_truth` finds the markers of the
photo's own dictionary at full brightness with default parameters: the
reference the darkened frames are scored against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from kgadapt.onboard.perception.scene import CameraModel, LightLayout, camera_expose, srgb_decode
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.resources import shipped

PHOTO_DIR = shipped("kgadapt.sim", "photographs")

# Which dictionary each photo's markers are from (SOURCES.txt); the custom one is left out.
PHOTO_DICTIONARIES = {
    "contrib_singlemarkersoriginal.jpg": "DICT_6X6_250",
    "contrib_img_00.jpg": "DICT_6X6_250",
    "contrib_img_01.jpg": "DICT_6X6_250",
    "contrib_img_02.jpg": "DICT_6X6_250",
    "contrib_img_03.jpg": "DICT_6X6_250",
    "contrib_chocclusion_original.jpg": "DICT_6X6_250",
    "contrib_gboriginal.png": "custom",
    "contrib_diamondmarkers.png": "custom",
}

# Real photographs of the other dictionaries' markers, found in repositories whose licence allows
# redistribution (SOURCES.txt: repository, commit, path, licence) but not shipped yet: material fetched
# from other repositories is placed by the steering session, not committed by a developer. Tests use
# those present here; `kgadapt bench perception --photos --photo DICTIONARY=FILE` measures any of them.
# name -> (dictionary they are read with, markers OpenCV's default detector finds at 640 x 480)
AWAITED_PHOTOS: dict[str, tuple[str, int]] = {
    "moveit_test_aruco_marker_detection.png": ("DICT_4X4_50", 12),
    "moveit_test_charuco_board_detection.jpg": ("DICT_5X5_1000", 16),  # of the board's 17
    "fiducials_tag_01_d7_14cm.png": ("DICT_5X5_1000", 1),
    "fiducials_tag_245-246_d7_14cm.png": ("DICT_5X5_1000", 2),
    "fiducials_403.jpg": ("DICT_5X5_1000", 1),
    "charuco2_board_image.jpg": ("DICT_ARUCO_MIP_36h12", 23),
}


@dataclass(frozen=True)
class PhotoFrame:
    image: np.ndarray  # grey uint8
    shift: tuple[int, int]  # (dx, dy) applied to the photo


def load_photo(name: str, *, width: int = 640, height: int = 480) -> np.ndarray:
    """A photograph from ``PHOTO_DIR`` as a grey frame of ``width x height``."""
    import cv2

    path = PHOTO_DIR / name
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ConfigError(f"cannot read photograph {path}")
    if image.shape != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return image


def photo_frames(
    photo: np.ndarray,
    level: float | None,
    *,
    count: int,
    camera: CameraModel = CameraModel(),
    light: LightLayout = LightLayout(),
    shift_px: int = 4,
    seed: int = 0,
) -> Iterator[PhotoFrame]:
    """``count`` frames of ``photo`` at ``level`` (None: its own brightness, noise only)."""
    import cv2

    rng = np.random.default_rng(seed)
    h, w = photo.shape
    linear = srgb_decode(photo)
    window = None
    if light.window > 0:
        window = np.zeros((h, w), bool)
        window[: int(round(light.window * h)), :] = True
    target = float(photo.mean()) if level is None else level
    for _ in range(count):
        dx, dy = (int(v) for v in rng.integers(-shift_px, shift_px + 1, size=2)) if shift_px else (0, 0)
        moved = cv2.warpAffine(linear, np.float32([[1, 0, dx], [0, 1, dy]]), (w, h), borderMode=cv2.BORDER_REFLECT)
        yield PhotoFrame(camera_expose(moved, target, camera, rng, window=window, window_gain=light.window_gain),
                         (dx, dy))


def photo_truth(photo: np.ndarray, dictionary: str) -> list[dict[str, Any]]:
    """The markers of ``dictionary`` in the photo at full brightness (default parameters)."""
    import cv2

    from kgadapt.onboard.perception.markers import aruco_dictionary as lookup

    detector = cv2.aruco.ArucoDetector(lookup(dictionary), cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(photo)
    if ids is None:
        return []
    return [{"id": int(i), "corners": c.reshape(4, 2).tolist()} for i, c in zip(ids.ravel(), corners)]


def shifted(truth: list[dict[str, Any]], shift: tuple[int, int]) -> list[dict[str, Any]]:
    dx, dy = shift
    return [{"id": t["id"], "corners": [[x + dx, y + dy] for x, y in t["corners"]]} for t in truth]
