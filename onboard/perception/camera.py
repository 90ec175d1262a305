"""Camera sources and the camera part that publishes frames and illumination over Zenoh.

Sources (all give grey frames with a capture time; the synthetic one adds
ground truth and the level it was lit at):

==========================  ==================================================
``synthetic[:PROFILE]``     :class:`SyntheticSource`: the ArUco scenario under a
                            profile file (default: the shipped demo profile)
``device:N`` or ``N``       :class:`OpenCVSource`: ``/dev/videoN`` through OpenCV
``file:PATH`` or a path     :class:`OpenCVSource`: a video file, looped
==========================  ==================================================

:class:`CameraPart` (an agent part: ``setup(session)`` / ``shutdown()``) runs
two threads. The capture thread paces the source at the configured rate and
hands frames to the publish thread through a bounded queue that drops the
*oldest* frame when full; the publish thread measures luminance, encodes JPEG
and puts ``frame`` and ``illumination`` messages. The Zenoh publisher uses
``CongestionControl.DROP``: a slow subscriber loses frames, the camera never
queues without bound.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from kgadapt.onboard.perception.illumination import LightEstimate, LightSettings, Luminance, Smoother, estimate_light, luminance
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, KgadaptError, TransportError

log = logging.getLogger(__name__)

DEFAULT_CAMERA = "cam0"


@dataclass
class CapturedFrame:
    """One grey frame as captured, with what the source knows about it."""

    gray: np.ndarray
    time: float  # capture time, seconds since the epoch
    truth: list[dict[str, Any]] | None = None
    level: float | None = None


class FrameSource(Protocol):
    """Where frames come from. ``open`` does the I/O; ``read`` returns None at the end."""

    description: str

    def open(self) -> None: ...

    def read(self) -> CapturedFrame | None: ...

    def close(self) -> None: ...


class SyntheticSource:
    """The synthetic ArUco scenario, rendered at the scenario time of each read.

    Scenario time runs from ``start_s`` at ``speed`` times the wall clock, so a
    one-minute profile can be replayed in ten seconds (speed 6).
    """

    def __init__(
        self,
        profile: Any = None,
        *,
        width: int = 640,
        height: int = 480,
        start_s: float = 0.0,
        speed: float = 1.0,
        seed: int = 0,
        clock: Callable[[], float] = time.time,
    ) -> None:
        from kgadapt.onboard.perception.scene import DEMO_PROFILE, IlluminationProfile, SceneSettings

        if speed <= 0:
            raise ConfigError(f"synthetic source speed must be positive, not {speed}")
        # A profile file is read in open(), not here (no I/O in __init__).
        self.profile: IlluminationProfile | None = profile if isinstance(profile, IlluminationProfile) else None
        self._profile_path = None if self.profile is not None else str(profile or DEMO_PROFILE)
        self.description = f"synthetic scenario under {self.profile.source if self.profile else self._profile_path}"
        self._scene_settings = SceneSettings(width=width, height=height)
        self._scene: Any = None
        self._start_s = start_s
        self._speed = speed
        self._seed = seed
        self._clock = clock
        self._t0: float | None = None
        self._rng: np.random.Generator | None = None

    def open(self) -> None:
        from kgadapt.onboard.perception.scene import SyntheticScene, load_profile

        if self._profile_path is not None:
            self.profile = load_profile(self._profile_path)
        assert self.profile is not None  # given to __init__, or loaded just above
        self._scene = SyntheticScene(self._scene_settings.with_options(self.profile.scene))
        self._rng = np.random.default_rng(self._seed)
        self._t0 = None

    def scenario_time(self, now: float) -> float:
        if self._t0 is None:
            self._t0 = now
        return self._start_s + (now - self._t0) * self._speed

    def read(self) -> CapturedFrame | None:
        if self._scene is None:
            raise ConfigError("synthetic source read before open()")
        now = self._clock()
        frame = self._scene.render(self.scenario_time(now), self.profile, self._rng)
        return CapturedFrame(frame.image, now, [t.as_wire() for t in frame.truth], round(frame.level, 2))

    def close(self) -> None:
        self._scene = None


class OpenCVSource:
    """A camera device or a video file through ``cv2.VideoCapture``.

    Devices get the asked resolution and rate and a one-frame driver buffer
    (so a read is the newest frame, not a stale one); files loop when they end.
    """

    def __init__(self, target: int | str, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, loop: bool = True) -> None:
        self.target = target
        self.description = f"camera device {target}" if isinstance(target, int) else f"video file {target}"
        self._width, self._height, self._fps, self._loop = width, height, fps, loop
        self._capture: Any = None

    def open(self) -> None:
        import cv2

        if isinstance(self.target, str) and not Path(self.target).exists():
            raise ConfigError(f"video file {self.target} does not exist")
        capture = cv2.VideoCapture(self.target)
        if not capture.isOpened():
            capture.release()
            raise ConfigError(f"OpenCV cannot open {self.description}")
        if isinstance(self.target, int):
            capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
            if self._width and self._height:
                capture.set(cv2.CAP_PROP_FRAME_WIDTH, self._width)
                capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self._height)
            if self._fps:
                capture.set(cv2.CAP_PROP_FPS, self._fps)
        self._capture = capture

    def read(self) -> CapturedFrame | None:
        import cv2

        if self._capture is None:
            raise ConfigError(f"{self.description} read before open()")
        ok, image = self._capture.read()
        if not ok and self._loop and isinstance(self.target, str):
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, image = self._capture.read()
        if not ok or image is None:
            return None
        now = time.time()
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return CapturedFrame(gray, now)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None


def make_source(spec: str, *, width: int = 640, height: int = 480, fps: float = 30.0,
                speed: float = 1.0, start_s: float = 0.0, seed: int = 0) -> FrameSource:
    """Build a source from ``synthetic[:PROFILE]``, ``device:N``, ``N``, ``file:PATH`` or a path."""
    if spec == "synthetic" or spec.startswith("synthetic:"):
        profile = spec.partition(":")[2] or None
        return SyntheticSource(profile, width=width, height=height, speed=speed, start_s=start_s, seed=seed)
    if spec.startswith("device:") or spec.isdigit():
        number = spec.partition(":")[2] if spec.startswith("device:") else spec
        if not number.isdigit():
            raise ConfigError(f"camera source {spec!r}: device:N needs a device number")
        return OpenCVSource(int(number), width=width, height=height, fps=fps)
    path = spec[len("file:"):] if spec.startswith("file:") else spec
    if not path:
        raise ConfigError("camera source is empty: use synthetic[:PROFILE], device:N or file:PATH")
    return OpenCVSource(path, width=width, height=height)


@dataclass(frozen=True, kw_only=True)
class CameraSettings:
    """How the camera part captures and publishes."""

    robot: str
    camera: str = DEFAULT_CAMERA
    fps: float = 30.0
    jpeg_quality: int = 80
    width: int = 640  # frames of another size are resized to this
    height: int = 480
    queue_size: int = 2  # frames between capture and publish; the oldest goes when full
    illumination_tau_s: float = 0.5
    light: LightSettings = LightSettings()
    marker_memory_s: float = 1.0  # markers detected this recently weigh the light estimate
    follow_detections: bool = True  # subscribe to the detectors' markers for that
    publish_truth: bool = True

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.camera, "camera name")
        if not 0 < self.fps <= 1000:
            raise ConfigError(f"camera rate {self.fps} fps: use a rate in (0, 1000]")
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"JPEG quality {self.jpeg_quality}: use 1..100")
        if not (16 <= self.width <= 8192 and 16 <= self.height <= 8192):
            raise ConfigError(f"camera resolution {self.width}x{self.height}: use 16..8192 each way")
        if self.queue_size < 1:
            raise ConfigError(f"camera queue size {self.queue_size}: use at least 1")


@dataclass
class CameraStats:
    """Counters of the camera part (read them any time; ints only grow)."""

    captured: int = 0
    published: int = 0
    dropped_queue: int = 0  # frames the publisher was too slow to take
    read_failures: int = 0
    encode_ms: list[float] = field(default_factory=list)  # the last few hundred


@dataclass(frozen=True)
class IlluminationReading:
    """What the illumination monitor measured for one frame."""

    seq: int
    time: float
    figures: Luminance
    smoothed: float  # EMA of light.level, what bands are read from
    light: LightEstimate | None = None


class CameraPart:
    """Captures from a source and publishes frames and illumination (an agent part).

    ``listeners`` get every :class:`IlluminationReading` on the publish thread
    (never a Zenoh thread), so an in-process adaptation manager can follow the
    light without a round trip through Zenoh.
    """

    name = "camera"

    def __init__(self, settings: CameraSettings, source: FrameSource) -> None:
        self.settings = settings
        self.source = source
        self.stats = CameraStats()
        self.latest: IlluminationReading | None = None
        self.error: KgadaptError | None = None
        self._listeners: list[Callable[[IlluminationReading], None]] = []
        self._queue: queue.Queue[tuple[int, CapturedFrame]] = queue.Queue(maxsize=settings.queue_size)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._frame_pub: Any = None
        self._light_pub: Any = None
        self._markers_sub: Any = None
        self._smoother = Smoother(settings.illumination_tau_s)
        self._markers: tuple[float, list[Any]] = (0.0, [])  # (frame time, corners) of the last markers seen
        self.finished = threading.Event()  # set when the source ended or failed

    def add_listener(self, listener: Callable[[IlluminationReading], None]) -> None:
        self._listeners.append(listener)

    def note_markers(self, corners: list[Any], frame_time: float) -> None:
        """Markers a detector found in the frame taken at ``frame_time``: the light estimate weighs their surroundings."""
        if corners and frame_time >= self._markers[0]:
            self._markers = (frame_time, list(corners))

    def _on_detections(self, sample: Any) -> None:
        # Zenoh callback: decode and keep a reference only (no I/O, no waiting).
        try:
            m = messages.decode_as(sample.payload.to_bytes(), messages.Detections)
        except Exception as exc:  # noqa: BLE001 - a foreign or malformed message: only the light estimate goes without it
            log.debug("camera: detections not used for the light estimate: %s", exc)
            return
        self.note_markers(m.corners, float(m.frame_time))

    def _recent_markers(self, now: float) -> list[Any]:
        at, corners = self._markers
        return corners if now - at <= self.settings.marker_memory_s else []

    def setup(self, session: Any) -> None:
        """Open the source, declare the publishers and start capturing."""
        import zenoh

        s = self.settings
        self.source.open()
        try:
            self._frame_pub = session.declare_publisher(
                keys.camera_frame(s.robot, s.camera),
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.DATA_HIGH,
                express=True,  # one frame is a whole message: batching only adds latency
            )
            self._light_pub = session.declare_publisher(
                keys.camera_illumination(s.robot, s.camera), congestion_control=zenoh.CongestionControl.DROP,
            )
            if s.follow_detections:
                self._markers_sub = session.declare_subscriber(keys.detector_markers(s.robot), self._on_detections)
        except Exception as exc:  # whatever zenoh raises: translated here
            self.shutdown()
            raise TransportError(f"camera {s.camera}: cannot declare publishers: {exc}") from exc
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._capture_loop, name=f"camera-{s.camera}-capture", daemon=True),
            threading.Thread(target=self._publish_loop, name=f"camera-{s.camera}-publish", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        log.info("camera %s: %s at %.1f fps, %dx%d, JPEG %d", s.camera, self.source.description, s.fps,
                 s.width, s.height, s.jpeg_quality)

    def shutdown(self) -> None:
        """Stop the threads, undeclare the publishers, close the source."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5)
        self._threads = []
        for pub in (self._markers_sub, self._frame_pub, self._light_pub):
            if pub is not None:
                rpc.undeclare_quietly(pub)
        self._frame_pub = self._light_pub = self._markers_sub = None
        try:
            self.source.close()
        except Exception as exc:  # noqa: BLE001 - closing: whatever the source's library raises, the camera still stops
            log.debug("camera source close: %s", exc)

    # -- threads -------------------------------------------------------------

    def _capture_loop(self) -> None:
        period = 1.0 / self.settings.fps
        due = time.monotonic()
        seq = 0
        failures = 0
        try:
            while not self._stop.is_set():
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    break
                due = max(due + period, time.monotonic() - period)  # never try to catch up a backlog
                frame = self.source.read()
                if frame is None:
                    failures += 1
                    self.stats.read_failures += 1
                    if failures >= 30:
                        raise ConfigError(f"{self.source.description} gave no frame 30 times in a row")
                    continue
                failures = 0
                seq += 1
                self.stats.captured += 1
                self._offer((seq, frame))
        except KgadaptError as exc:
            self.error = exc
            log.error("camera %s stopped: %s", self.settings.camera, exc)
        except Exception as exc:  # a source bug must not die silently
            self.error = KgadaptError(f"camera {self.settings.camera} capture failed: {exc}")
            log.exception("camera %s capture failed", self.settings.camera)
        finally:
            self.finished.set()

    def _offer(self, item: tuple[int, CapturedFrame]) -> None:
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()  # drop the oldest: the newest frame is worth more
                    self.stats.dropped_queue += 1
                except queue.Empty:
                    pass

    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            try:
                seq, frame = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                self._publish(seq, frame)
            except Exception:  # one bad frame must not stop the camera
                log.exception("camera %s: frame %d not published", self.settings.camera, seq)

    def _publish(self, seq: int, frame: CapturedFrame) -> None:
        import cv2

        s = self.settings
        gray = frame.gray
        truth = frame.truth
        if gray.shape != (s.height, s.width):
            sx, sy = s.width / gray.shape[1], s.height / gray.shape[0]
            gray = cv2.resize(gray, (s.width, s.height), interpolation=cv2.INTER_AREA)
            if truth:
                truth = [{"id": t["id"], "corners": [[x * sx, y * sy] for x, y in t["corners"]]} for t in truth]
        start = time.perf_counter()
        ok, jpeg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
        if not ok:
            raise ConfigError(f"camera {s.camera}: JPEG encoding failed")
        encode_ms = (time.perf_counter() - start) * 1e3
        if len(self.stats.encode_ms) >= 512:
            del self.stats.encode_ms[:256]
        self.stats.encode_ms.append(encode_ms)
        # The frame first: every detection waits for it, and the light figures below (0.4 ms a frame on the
        # bench's machine) are needed only by the illumination message that follows it.
        self._frame_pub.put(messages.encode(messages.Frame(
            camera=s.camera, seq=seq, time=frame.time, width=s.width, height=s.height, jpeg=jpeg.tobytes(),
            truth=truth if s.publish_truth else None, level=frame.level,
            sent=time.time(),  # lets a receiver tell transport time from capture and encoding time
        )))
        figures = luminance(gray)
        light = estimate_light(gray, self._recent_markers(frame.time), s.light)
        smoothed = self._smoother.update(light.level, frame.time)
        reading = IlluminationReading(seq, frame.time, figures, smoothed, light)
        self.latest = reading
        self._light_pub.put(messages.encode(messages.Illumination(
            camera=s.camera, seq=seq, time=frame.time,
            mean=round(figures.mean, 3), p5=figures.p5, p50=figures.p50, p95=figures.p95,
            smoothed=round(smoothed, 3), **light.as_wire(),
        )))
        self.stats.published += 1
        for listener in self._listeners:
            try:
                listener(reading)
            except Exception:  # a listener's bug must not stop the camera
                log.exception("camera %s: illumination listener failed", s.camera)
