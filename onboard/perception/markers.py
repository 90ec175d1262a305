"""The marker-detection core: a detector configuration, pre-processing and ArUco.

A configuration is the ``config_json`` of a marker-detector component in the
knowledge graph (docs/CONTRACTS.md)::

    {"dictionary": "DICT_4X4_50",
     "preprocess": [{"op": "gamma", "gamma": 0.5}, {"op": "clahe", "clip_limit": 2.0, "tile": 8},
                    {"op": "stretch", "low_pct": 2, "high_pct": 98}, {"op": "blur", "ksize": 3}],
     "parameters": {"adaptiveThreshWinSizeMax": 53, "adaptiveThreshConstant": 3}}

:func:`parse_config` checks it (its schema: :class:`kgadapt.shared.preprocessing.ConfigJson`)
and says what is wrong (an unknown op, a
parameter ``cv2.aruco.DetectorParameters`` does not have, a value of the
wrong type); :class:`MarkerDetector` runs it on grey frames. :func:`score`
compares detections with a frame's ground truth.
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from kgadapt.shared.errors import ConfigError
from kgadapt.shared.preprocessing import OPS as _OPS
from kgadapt.shared.preprocessing import is_dictionary_file, read_settings


def aruco_dictionary(name: str, *, base: str | Path | None = None) -> Any:
    """The ArUco dictionary ``name``: a cv2.aruco DICT_* name or an OpenCV dictionary file; ConfigError when bad.

    A file (``.yml``/``.yaml``, OpenCV's ``nmarkers``/``markersize``/``marker_N``
    format) is read relative to ``base`` when its path is relative; it is
    checked (see :func:`read_dictionary_file`) and kept until it changes.
    """
    import cv2

    if is_dictionary_file(name):
        path = Path(name)
        if base is not None and not path.is_absolute():
            path = Path(base) / path
        return read_dictionary_file(path)
    key = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(key, int):
        raise ConfigError(f"unknown ArUco dictionary {name!r}: use a cv2.aruco DICT_* name such as DICT_4X4_50 "
                          f"or an OpenCV dictionary file (.yml)")
    return cv2.aruco.getPredefinedDictionary(key)


_FILES: dict[tuple[str, int, int], Any] = {}


def read_dictionary_file(path: str | Path) -> Any:
    """A ``cv2.aruco.Dictionary`` read from OpenCV's YAML dictionary file; ConfigError naming the file when bad.

    OpenCV's own reader takes a marker of the wrong length without a word (it
    packs whatever bits it gets), so every marker is checked first: ``nmarkers``
    markers ``marker_0`` .. ``marker_N-1``, each ``markersize`` x ``markersize``
    bits of 0 and 1. A file that does not say ``maxCorrectionBits`` gets what its
    markers allow: half the smallest distance between two of them (rotations
    included) less one, as OpenCV computes it for dictionaries it makes.
    """
    import cv2

    path = Path(path)
    try:
        stat = path.stat()
    except OSError as exc:
        raise ConfigError(f"dictionary file {path}: {exc.strerror or exc}") from exc
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    found = _FILES.get(key)
    if found is not None:
        return found
    where = f"dictionary file {path}"
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # a parse error surfaces as SystemError through the bindings
        detail = str(exc.__cause__ or exc).strip().splitlines()
        raise ConfigError(f"{where}: not OpenCV's YAML format: {detail[-1] if detail else exc}") from exc
    if not storage.isOpened():
        raise ConfigError(f"{where}: cannot be read as OpenCV's YAML format")
    try:
        root = storage.root()
        count_node, size_node = root.getNode("nmarkers"), root.getNode("markersize")
        if not count_node.isInt() or not size_node.isInt():
            raise ConfigError(f"{where}: needs integers nmarkers and markersize")
        count, size = int(count_node.real()), int(size_node.real())
        if not 1 <= count <= 4096 or not 2 <= size <= 16:
            raise ConfigError(f"{where}: nmarkers {count} in [1, 4096], markersize {size} in [2, 16]")
        bits = []
        for i in range(count):
            node = root.getNode(f"marker_{i}")
            text = node.string() if node.isString() else ""
            if not text:
                raise ConfigError(f"{where}: marker_{i} is missing (nmarkers is {count})")
            if len(text) != size * size or set(text) - {"0", "1"}:
                raise ConfigError(f"{where}: marker_{i} has {len(text)} characters, not markersize {size} x {size} = "
                                  f"{size * size} bits of 0 and 1")
            bits.append(np.frombuffer(text.encode(), np.uint8).reshape(size, size) - ord("0"))
        correction_node = root.getNode("maxCorrectionBits")
        correction = int(correction_node.real()) if correction_node.isInt() else _correction_bits(bits)
    finally:
        storage.release()
    dictionary = cv2.aruco.Dictionary(np.concatenate([cv2.aruco.Dictionary.getByteListFromBits(b) for b in bits]),
                                      size, correction)
    _FILES[key] = dictionary
    return dictionary


def _correction_bits(bits: Sequence[np.ndarray]) -> int:
    """How many wrong bits a marker may have and still be read as itself: (smallest distance - 1) // 2."""
    if len(bits) < 2:
        return max((bits[0].size - 1) // 2, 0) if bits else 0
    flat = np.stack([b.ravel() for b in bits]).astype(np.int16)
    rotated = [np.stack([np.rot90(b, k).ravel() for b in bits]).astype(np.int16) for k in range(4)]
    smallest = bits[0].size
    for i in range(len(bits)):
        for turned in rotated:
            distance = np.abs(turned[i + 1:] - flat[i]).sum(axis=1)
            if distance.size:
                smallest = min(smallest, int(distance.min()))
        # A marker must not read as itself turned either (OpenCV's own dictionaries count this too).
        for k in (1, 2, 3):
            smallest = min(smallest, int(np.abs(rotated[k][i] - flat[i]).sum()) or smallest)
    return max((smallest - 1) // 2, 0)


@dataclass(frozen=True)
class DetectorConfig:
    """A checked detector configuration."""

    name: str
    dictionary: str = "DICT_4X4_50"
    preprocess: tuple[tuple[str, tuple[tuple[str, Any], ...]], ...] = ()
    parameters: tuple[tuple[str, Any], ...] = ()

    def as_json(self) -> dict[str, Any]:
        return {
            "dictionary": self.dictionary,
            "preprocess": [{"op": op, **dict(args)} for op, args in self.preprocess],
            "parameters": dict(self.parameters),
        }


def parse_config(name: str, raw: str | Mapping[str, Any], *, dictionary: str | None = None) -> DetectorConfig:
    """Check a ``config_json`` (text or mapping); raise ConfigError naming ``name`` and the problem."""
    where = f"detector configuration {name!r}"
    if isinstance(raw, (str, bytes)):
        try:
            data = json.loads(raw)
        except ValueError as exc:
            raise ConfigError(f"{where}: config_json is not JSON: {exc}") from exc
    else:
        data = raw
    settings = read_settings(data, where, dictionary=dictionary)
    try:
        aruco_dictionary(settings.dictionary)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    config = DetectorConfig(name, settings.dictionary, settings.steps(), tuple(sorted(settings.parameters.items())))
    _detector_parameters(config)  # checks every parameter name and type now, not on the first frame
    return config


def _detector_parameters(config: DetectorConfig) -> Any:
    import cv2

    params = cv2.aruco.DetectorParameters()
    for key, value in config.parameters:
        if key.startswith("_") or not hasattr(params, key) or callable(getattr(params, key)):
            raise ConfigError(f"detector configuration {config.name!r}: cv2.aruco.DetectorParameters has no {key!r}")
        if isinstance(value, str) and value.startswith("CORNER_REFINE_"):
            value = getattr(cv2.aruco, value, value)  # a readable name for cornerRefinementMethod
        current = getattr(params, key)
        if isinstance(current, bool) != isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(
                f"detector configuration {config.name!r}: parameter {key!r} must be "
                f"{type(current).__name__}, not {value!r}"
            )
        if isinstance(current, int) and not isinstance(current, bool) and value != int(value):
            raise ConfigError(f"detector configuration {config.name!r}: parameter {key!r} must be an integer, not {value!r}")
        try:
            setattr(params, key, type(current)(value))
        except (TypeError, ValueError, OverflowError) as exc:
            raise ConfigError(f"detector configuration {config.name!r}: parameter {key!r} = {value!r}: {exc}") from exc
    return params


@dataclass
class Detection:
    """What one frame gave: marker ids and their corners, and the time it took."""

    ids: list[int]
    corners: list[list[list[float]]]  # per marker: 4 x [x, y]
    processing_ms: float
    preprocess_ms: float = 0.0
    clean: list[bool] = field(default_factory=list)  # per marker: its cells read clean (cells_are_clean)

    @property
    def clean_count(self) -> int:
        """Markers whose cells read clean (no ``clean`` list: all count): what reflexes and hedges weigh."""
        return sum(c is not False for c in (self.clean or [True] * len(self.ids))[:len(self.ids)])


def cells_are_clean(gray: np.ndarray, corners: Any, *, cells: int = 6, max_mixed: float = 0.2) -> bool:
    """Whether the marker at ``corners`` reads as ``cells`` x ``cells`` clean cells, each all dark or all light.

    A code that decodes where no marker of this dictionary is (a marker of a
    dictionary with more cells read on this one's coarser grid, a ChArUco board, a
    texture) has cells that straddle dark and light; a printed marker of the
    dictionary does not. Samples a 3 x 3 grid in the middle half of every cell
    (by the homography of the corners) and calls a cell mixed when its samples
    span more than half the marker's dark-to-light contrast; at most
    ``max_mixed`` of the cells may be mixed.
    """
    import cv2

    pts = np.asarray(corners, np.float32).reshape(4, 2)
    square, grid = _cell_grid(cells)
    matrix = cv2.getPerspectiveTransform(square, pts)
    xy = cv2.perspectiveTransform(grid[None], matrix)[0]
    h, w = gray.shape
    if xy[:, 0].min() < 0 or xy[:, 1].min() < 0 or xy[:, 0].max() > w - 1 or xy[:, 1].max() > h - 1:
        return True  # cut by the frame's edge: not enough to judge
    values = cv2.remap(gray, xy[:, 0].reshape(-1, 1), xy[:, 1].reshape(-1, 1), cv2.INTER_LINEAR).astype(np.float32)
    values = values.reshape(cells * cells, 3, 3)  # cell, x sample, y sample
    means = values.mean(axis=(1, 2))
    p10, p90 = _percentiles(means, 10, 90)
    contrast = float(p90 - p10)  # in the values' dtype, as np.percentile's difference was
    if contrast <= 0:
        return False
    # In a dark, noisy frame the samples of a clean cell spread by noise alone: the cleanest
    # quarter of the cells (a marker's border cells are clean even on a coarser grid) says how much.
    spread = values.max(axis=(1, 2)) - values.min(axis=(1, 2))
    limit = max(0.5 * contrast, 2.5 * float(_percentiles(spread, 25)[0]))
    return bool((spread > limit).mean() <= max_mixed)


@functools.lru_cache(maxsize=8)
def _cell_grid(cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit square of a marker of ``cells`` x ``cells`` cells, and where :func:`cells_are_clean` samples
    it (a 3 x 3 grid in the middle half of every cell, cell by cell), in cell units. The same for every
    marker of a dictionary: built once (it was 18 of a check's 118 us)."""
    square = np.array([[0, 0], [cells, 0], [cells, cells], [0, cells]], np.float32)
    sub = np.array([0.3, 0.5, 0.7], np.float32)
    cx, cy, sx, sy = np.meshgrid(np.arange(cells, dtype=np.float32), np.arange(cells, dtype=np.float32), sub, sub,
                                 indexing="ij")
    grid = np.stack([(cx + sx).ravel(), (cy + sy).ravel()], 1)
    square.setflags(write=False)
    grid.setflags(write=False)
    return square, grid


def _percentiles(values: np.ndarray, *qs: float) -> list[Any]:
    """``np.percentile(values, q)`` for each of ``qs``, the same scalars (linear between the closest ranks,
    in the values' own dtype, from the nearer rank), by one sort: for the few dozen values of a marker's
    cells about 3 us, where each np.percentile took 19, three times a marker on every frame."""
    ranked = np.sort(values, axis=None)
    last = ranked.size - 1
    out = []
    for q in qs:
        at = (q / 100) * last
        low = int(at)
        high = min(low + 1, last)
        t = at - low
        a, b = ranked[low], ranked[high]
        diff = b - a
        out.append(a + diff * t if t < 0.5 else b - diff * (1 - t))
    return out


class MarkerDetector:
    """Pre-processing and ``cv2.aruco.ArucoDetector`` for one configuration."""

    def __init__(self, config: DetectorConfig) -> None:
        import cv2

        self.config = config
        self._cv2 = cv2
        self._steps: list[Callable[[np.ndarray], np.ndarray]] = [self._step(op, dict(args)) for op, args in config.preprocess]
        found = aruco_dictionary(config.dictionary)
        self._cells = int(found.markerSize) + 2  # code cells plus the one-cell black border each side
        self._detector = cv2.aruco.ArucoDetector(found, _detector_parameters(config))

    def _step(self, op: str, args: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
        cv2 = self._cv2
        if op == "gamma":
            lut = np.clip(255.0 * (np.arange(256) / 255.0) ** args["gamma"] + 0.5, 0, 255).astype(np.uint8)
            return lambda img: cv2.LUT(img, lut)
        if op == "clahe":
            clahe = cv2.createCLAHE(clipLimit=args["clip_limit"], tileGridSize=(args["tile"], args["tile"]))
            apply: Callable[[np.ndarray], np.ndarray] = clahe.apply
            return apply
        if op == "stretch":
            low_pct, high_pct = args["low_pct"], args["high_pct"]

            def stretch(img: np.ndarray) -> np.ndarray:
                # Percentiles from a histogram of every 4th pixel: cheap and robust to noise.
                hist = cv2.calcHist([img[::4, ::4]], [0], None, [256], [0, 256]).ravel().cumsum()
                total = hist[-1]
                low = int(np.searchsorted(hist, total * low_pct / 100.0))
                high = int(np.searchsorted(hist, total * high_pct / 100.0))
                if high <= low:
                    return img
                scale = 255.0 / (high - low)
                stretched: np.ndarray = cv2.convertScaleAbs(img, alpha=scale, beta=-low * scale)
                return stretched

            return stretch
        if op == "blur":
            k = args["ksize"]
            return (lambda img: img) if k <= 1 else (lambda img: cv2.GaussianBlur(img, (k, k), 0))
        raise ConfigError(f"unknown pre-processing op {op!r} (use {', '.join(_OPS)})")  # parse_config refuses these first

    def preprocess(self, gray: np.ndarray) -> np.ndarray:
        for step in self._steps:
            gray = step(gray)
        return gray

    def detect(self, gray: np.ndarray) -> Detection:
        """Pre-process a grey frame and find markers in it."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ConfigError(f"detector needs a grey uint8 image, got {gray.dtype} {gray.shape}")
        start = time.perf_counter()
        image = self.preprocess(gray)
        mid = time.perf_counter()
        corners, ids, _rejected = self._detector.detectMarkers(image)
        clean = [cells_are_clean(gray, c, cells=self._cells) for c in corners] if ids is not None else []
        end = time.perf_counter()
        if ids is None:
            return Detection([], [], (end - start) * 1e3, (mid - start) * 1e3)
        return Detection(
            [int(i) for i in ids.ravel()],
            [[[round(float(x), 2), round(float(y), 2)] for x, y in c.reshape(4, 2)] for c in corners],
            (end - start) * 1e3,
            (mid - start) * 1e3,
            clean,
        )


@dataclass
class Score:
    """Detections against ground truth, summed over frames."""

    frames: int = 0
    truth: int = 0
    hits: int = 0
    false: int = 0
    corner_error_px: list[float] = field(default_factory=list)

    def add(self, other: "Score") -> None:
        self.frames += other.frames
        self.truth += other.truth
        self.hits += other.hits
        self.false += other.false
        self.corner_error_px += other.corner_error_px

    @property
    def detection_rate(self) -> float:
        return self.hits / self.truth if self.truth else 0.0

    @property
    def false_per_frame(self) -> float:
        """False markers per frame: what a phantom costs per frame, whatever else is seen."""
        return self.false / self.frames if self.frames else 0.0

    @property
    def false_per_reported(self) -> float:
        """False markers per marker reported: the share of reports that are wrong."""
        reported = self.hits + self.false
        return self.false / reported if reported else 0.0


def score(ids: Sequence[int], corners: Sequence[Any], truth: Sequence[Any], *, tolerance_px: float = 5.0,
          ignore: Sequence[int] = ()) -> Score:
    """Match detections to truth: same id and mean corner distance within ``tolerance_px``.

    ``truth`` items are :class:`kgadapt.onboard.perception.scene.Truth` or wire maps ``{"id", "corners"}``.
    A detection that matches nothing (wrong id, wrong place, or a second hit) is false;
    ids in ``ignore`` (markers partly hidden, e.g. by a saturated window) count neither way.
    """
    wanted: dict[int, np.ndarray] = {}
    for item in truth:
        tid, tc = (item["id"], item["corners"]) if isinstance(item, Mapping) else (item.id, item.corners)
        wanted[int(tid)] = np.asarray(tc, np.float32).reshape(4, 2)
    result = Score(frames=1, truth=len(wanted))
    for mid, mc in zip(ids, corners, strict=True):
        expected = wanted.get(int(mid))
        if expected is None:
            if int(mid) not in ignore:
                result.false += 1
            continue
        error = float(np.linalg.norm(np.asarray(mc, np.float32).reshape(4, 2) - expected, axis=1).mean())
        if error <= tolerance_px:
            result.hits += 1
            result.corner_error_px.append(error)
            del wanted[int(mid)]
        else:
            result.false += 1
    return result
