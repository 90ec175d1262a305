"""The flight bridge: detections in over Zenoh, LANDING_TARGET out over MAVLink, flight state back.

:class:`FlightBridge` is a part of the onboard agent. It follows the
detections of the running marker detector (``kgadapt/<robot>/detector/*/markers``),
turns the chosen marker of each detection into a LANDING_TARGET with the
camera's model, intrinsics and mounting
(:class:`kgadapt.onboard.flight.landing_targets.TargetBuilder`), and publishes the flight
controller's state (:class:`kgadapt.onboard.flight.mavlink.FlightState`) as ``flight_state``
on ``kgadapt/<robot>/flight/state`` every ``state_period_s`` and at once when
the link, arming, mode or landed state changes.

Geometry. Angles are measured from the principal point with the pinhole model:
``angle_x = atan((u - cx) / fx)``, ``angle_y = atan((v - cy) / fy)`` where
``(u, v)`` is the marker's centre in pixels (mean of its four corners), +x to
the right and +y down the image, as LANDING_TARGET defines them. A pose, when
a detection carries one, is the marker's position in the camera's optical
frame (x right, y down, z out of the lens, metres): it takes the place of the
pose solved from the site's marker size, and goes through the camera's
mounting to body FRD like it. :func:`landing_target` is the same for a camera
mounted straight at the body's origin, without a site or an autopilot's profile.
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Sequence

from kgadapt.onboard.flight.confirmation import ConfirmationSettings, MarkerConfirmer, Place
from kgadapt.onboard.flight.landing_targets import AutopilotProfile, CameraModel, TargetBuilder, TargetHold
from kgadapt.onboard.flight.mavlink import FlightLink, FlightState, LandingTarget, LinkSettings
from kgadapt.onboard.flight.site import ANGLES_ONLY, SiteMarkers
from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import ConfigError, FlightLinkError, KgadaptError, MessageError, TransportError

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (from the Camera node of the models: fx, fy, cx, cy)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise FlightLinkError(f"camera intrinsic {name} must be a finite number, not {value!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise FlightLinkError(f"camera focal lengths must be positive, not fx={self.fx}, fy={self.fy}")


def intrinsics_from_graph(client: Any, camera: str, *, wait_s: float = 0.0) -> CameraIntrinsics:
    """The intrinsics of component ``camera`` from the knowledge graph (a KnowledgeClient's named query).

    ``wait_s``: ask again for that long while the knowledge service does not answer or refuses
    (it may be starting, or its store reloading after a restart), as an agent's start should.
    """
    rows = client.query("camera_intrinsics", {"camera": camera}, wait_s=wait_s)
    if not rows or any(rows[0].get(k) is None for k in ("fx", "fy", "cx", "cy")):
        raise ConfigError(f"camera {camera!r} has no intrinsics (fx, fy, cx, cy) in the knowledge graph")
    return CameraIntrinsics(**{k: float(rows[0][k]) for k in ("fx", "fy", "cx", "cy")})


def marker_points(corners: Any) -> list[tuple[float, float]]:
    """The four (x, y) corners of one marker, from ``[[x,y]*4]``, ``[[[x,y]*4]]`` or ``[x,y]*4`` flat."""
    points = corners
    if isinstance(points, (list, tuple)) and len(points) == 1 and isinstance(points[0], (list, tuple)):
        points = points[0]  # OpenCV's 1x4x2 shape
    if isinstance(points, (list, tuple)) and len(points) == 8 and all(_is_number(v) for v in points):
        points = [points[i:i + 2] for i in range(0, 8, 2)]
    if not isinstance(points, (list, tuple)) or len(points) != 4:
        raise MessageError(f"marker corners must be four (x, y) points, not {corners!r:.80}")
    result = []
    for point in points:
        if not isinstance(point, (list, tuple)) or len(point) != 2 or not all(_is_number(v) for v in point):
            raise MessageError(f"marker corner must be (x, y) numbers, not {point!r:.80}")
        result.append((float(point[0]), float(point[1])))
    return result


def landing_target(
    corners: Any,
    intrinsics: CameraIntrinsics,
    *,
    frame_time: float,
    marker_id: int = 0,
    pose: Sequence[float] | None = None,
) -> LandingTarget:
    """The LANDING_TARGET for one marker seen at ``corners`` (pixels) in a frame taken at ``frame_time``."""
    points = marker_points(corners)
    u = sum(p[0] for p in points) / 4.0
    v = sum(p[1] for p in points) / 4.0
    k = intrinsics
    xs = [p[0] for p in points]
    ys = [p[1] for p in points]
    position = None
    distance = 0.0
    if pose is not None:
        x_cam, y_cam, z_cam = (float(c) for c in pose)
        position = (-y_cam, x_cam, z_cam)
        distance = math.sqrt(x_cam * x_cam + y_cam * y_cam + z_cam * z_cam)
    return LandingTarget(
        time=float(frame_time),
        angle_x=math.atan((u - k.cx) / k.fx),
        angle_y=math.atan((v - k.cy) / k.fy),
        size_x=math.atan((max(xs) - k.cx) / k.fx) - math.atan((min(xs) - k.cx) / k.fx),
        size_y=math.atan((max(ys) - k.cy) / k.fy) - math.atan((min(ys) - k.cy) / k.fy),
        distance=distance,
        target_num=marker_id if 0 <= marker_id <= 255 else 0,
        position=position,
    )


def choose_marker(detections: messages.Detections, target_id: int | None, site: SiteMarkers | None = None) -> int | None:
    """Index of the marker to land on: ``target_id`` (or, when it is a marker of the site's pad, the largest of
    the pad's markers) if seen, else the largest in the image; None if none."""
    ids, corners = detections.ids, detections.corners
    if len(ids) != len(corners):
        raise MessageError(f"detections has {len(ids)} ids but {len(corners)} corner sets")
    wanted: list[int] = list(range(len(ids)))
    if target_id is not None:
        if site is None or site.place_of(target_id) == target_id:
            return next((i for i, marker in enumerate(ids) if marker_id_of(marker) == target_id), None)
        pad = site.place_of(target_id)
        wanted = [i for i, marker in enumerate(ids) if (mid := marker_id_of(marker)) is not None
                  and mid in site.sizes_m and site.place_of(mid) == pad]
    best, best_area = None, -1.0
    for i in wanted:
        c = corners[i]
        points = marker_points(c)
        area = abs(sum(points[j][0] * points[j - 1][1] - points[j - 1][0] * points[j][1] for j in range(4))) / 2
        if area > best_area:
            best, best_area = i, area
    return best


def marker_id_of(value: object) -> int | None:
    """A marker id from ``7`` or OpenCV's ``[7]`` (ids come as an N x 1 array); None if not an id."""
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _pose_of(detections: messages.Detections, index: int) -> list[float] | None:
    """The optional pose of marker ``index``: ``poses[index]`` as [x, y, z] or {"tvec": [x, y, z]}."""
    poses = detections.poses
    if not isinstance(poses, list) or index >= len(poses) or poses[index] is None:
        return None
    pose = poses[index]
    if isinstance(pose, dict):
        pose = pose.get("tvec")
    if not isinstance(pose, (list, tuple)) or len(pose) != 3 or not all(_is_number(v) for v in pose):
        raise MessageError(f"detections pose {index} must be [x, y, z] metres, not {poses[index]!r:.80}")
    return [float(v) for v in pose]


@dataclass(frozen=True, kw_only=True)
class BridgeSettings:
    """What the bridge follows, where it sends, and how often."""

    robot: str
    link: LinkSettings
    intrinsics: CameraIntrinsics
    detector: str = "*"  # detector instance to follow; "*" = whichever runs
    target_id: int | None = None  # marker id to land on; None = the largest marker seen
    state_period_s: float = 0.2  # flight_state at 5 Hz, plus at once on a discrete change
    max_target_hz: float = 30.0  # LANDING_TARGET at the detection rate, capped here
    max_detection_age_s: float = 0.5  # older detections would steer towards where the marker was
    max_clock_skew_s: float = 0.5  # a frame time further ahead than this is refused, not trusted
    queue_limit: int = 64
    camera: CameraModel | None = None  # intrinsics + mounting (a camera file); None: ``intrinsics``, mounted straight
    markers: SiteMarkers | None = None  # the site's marker sizes: with them the target goes with its position
    profile: str = "auto"  # ardupilot | px4 | auto (from the autopilot's heartbeat)
    hold_s: float = 1.5  # re-send the last target, predicted, this long after its frame ...
    resend_hz: float = 10.0  # ... at this rate: ArduPilot's estimator wants a measurement every 0.5 s
    # no phantom landing targets (kgadapt.onboard.flight.confirmation)
    confirmation: ConfirmationSettings = ConfirmationSettings()


StateCallback = Callable[[FlightState], None]

_STOP = object()


class FlightBridge:
    """Detections -> LANDING_TARGET, flight controller -> ``flight_state``. ``setup(session)``/``shutdown()``.

    ``on_state(state)`` (e.g. a write of the FlightControl component's run-time
    properties into the graph) runs on a thread of its own with the latest
    published state, so a slow callback never delays a landing target.
    """

    def __init__(self, settings: BridgeSettings, *, on_state: StateCallback | None = None,
                 chosen_detector: Callable[[], str | None] | None = None) -> None:
        keys.check_name(settings.robot, "robot name")
        if settings.detector != "*":
            keys.check_name(settings.detector, "detector instance")
        if settings.state_period_s <= 0 or settings.max_target_hz <= 0:
            raise FlightLinkError("state_period_s and max_target_hz must be positive")
        self.settings = settings
        AutopilotProfile.of(settings.profile)  # a bad name fails here, not at the first detection
        self._targets = TargetBuilder(settings.camera or _camera_of(settings.intrinsics), settings.markers)
        self._hold = TargetHold(hold_s=settings.hold_s, resend_hz=settings.resend_hz)
        self._on_state = on_state
        # With an adaptation manager in the same process: the one instance it chose (None: none).
        # Detections from any other instance, forged ones included, never steer the landing.
        self._chosen = chosen_detector
        self.link = FlightLink(settings.link)
        self.link.on_state(self._on_link_state)
        self.confirmer = MarkerConfirmer(settings.confirmation)
        self._queue: queue.SimpleQueue[tuple[object, bytes | FlightState | None]] = queue.SimpleQueue()
        self._queued = 0  # detections waiting; SimpleQueue has no bound of its own
        self._queued_lock = threading.Lock()
        self._publisher: zenoh.Publisher | None = None
        self._subscriber: zenoh.Subscriber[None] | None = None
        self._worker: threading.Thread | None = None
        self._notifier: threading.Thread | None = None
        self._latest_for_callback: FlightState | None = None
        self._callback_ready = threading.Condition()
        self._stopping = False
        self._last_published: tuple[object, ...] | None = None
        self._last_frame_time = -math.inf
        self._last_target_mono = time.monotonic()
        self._tokens = 2.0
        self._last_send_error: tuple[Any, ...] = ()  # the last failure's type and arguments: logged once
        self.sent_times: collections.deque[float] = collections.deque(maxlen=4096)  # epoch of each LANDING_TARGET
        self.angles_only: bool | None = None  # the last target sent carried angles only (None: none sent yet)
        self._angles_only_warned = False
        self.counters = {
            "detections": 0, "malformed": 0, "no_target": 0, "stale": 0, "duplicate": 0, "rate_limited": 0,
            "targets_sent": 0, "send_failed": 0, "published": 0, "queue_full": 0, "targets_resent": 0,
            "not_chosen": 0, "unconfirmed": 0, "placed": 0,
        }

    # -- lifecycle

    def setup(self, session: zenoh.Session) -> None:
        """Open the MAVLink link, declare the publisher and subscriber, start the worker."""
        self._stopping = False
        self.link.setup()
        try:
            self._publisher = session.declare_publisher(keys.flight_state(self.settings.robot))
            self._subscriber = session.declare_subscriber(
                keys.detector_markers(self.settings.robot, self.settings.detector), self._on_sample
            )
        except Exception as exc:  # whatever zenoh raises: translated here
            self.link.shutdown()
            raise TransportError(f"flight bridge cannot declare on Zenoh: {exc}") from exc
        self._worker = threading.Thread(target=self._work, name="flight-bridge", daemon=True)
        self._worker.start()
        if self._on_state is not None:
            self._notifier = threading.Thread(target=self._notify, name="flight-state-callback", daemon=True)
            self._notifier.start()
        log.info("flight bridge up: %s -> LANDING_TARGET on %s", self.settings.detector, self.link.endpoint.url)

    def shutdown(self) -> None:
        """Undeclare, stop the threads, close the link."""
        self._stopping = True
        subscriber, self._subscriber = self._subscriber, None
        if subscriber is not None:
            rpc.undeclare_quietly(subscriber)
        self._queue.put((_STOP, None))
        if self._worker is not None:
            self._worker.join(timeout=2.0)
            self._worker = None
        with self._callback_ready:
            self._callback_ready.notify_all()
        if self._notifier is not None:
            self._notifier.join(timeout=2.0)
            self._notifier = None
        publisher, self._publisher = self._publisher, None
        if publisher is not None:
            rpc.undeclare_quietly(publisher)
        self.link.shutdown()

    @property
    def state(self) -> FlightState:
        return self.link.state

    def set_intrinsics(self, intrinsics: CameraIntrinsics) -> None:
        """Use other intrinsics from the next detection on (the camera's resolution changed)."""
        camera = self._targets.camera
        self._targets.camera = CameraModel(fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
                                           distortion=camera.distortion, yaw_deg=camera.yaw_deg,
                                           offset_m=camera.offset_m)

    @property
    def profile(self) -> AutopilotProfile:
        return AutopilotProfile.of(self.settings.profile, self.link.state)

    # -- inputs (called on Zenoh's and the link's threads: only enqueue)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._chosen is not None and keys.last_chunk(str(sample.key_expr), 2) != self._chosen():
            self.counters["not_chosen"] += 1
            return
        with self._queued_lock:
            if self._queued >= self.settings.queue_limit:
                self.counters["queue_full"] += 1
                return
            self._queued += 1
        self._queue.put(("detections", bytes(sample.payload.to_bytes())))

    def _on_link_state(self, state: FlightState) -> None:
        self._queue.put(("state", state))

    # -- the worker

    def _work(self) -> None:
        period = self.settings.state_period_s
        next_publish = time.monotonic()
        while True:
            wake = next_publish
            if self._hold.held is not None:
                wake = min(wake, time.monotonic() + max(0.0, self._hold.last_sent + self._hold.period_s - time.time()))
            try:
                kind, value = self._queue.get(timeout=max(0.0, wake - time.monotonic()))
            except queue.Empty:
                kind, value = None, None
            if kind is _STOP:
                return
            try:
                if kind == "detections" and isinstance(value, bytes):
                    with self._queued_lock:
                        self._queued -= 1
                    self._handle_detections(value)
                elif (kind == "state" and isinstance(value, FlightState)
                      and (value.event or value.discrete() != self._last_published)):
                    self._publish(value)
                    next_publish = time.monotonic() + period
            except Exception:  # the bridge must outlive any one bad input
                log.exception("flight bridge: cannot handle %s", kind)
            if time.monotonic() >= next_publish:
                self._publish(self.link.state)
                next_publish = time.monotonic() + period
            if self._hold.due(time.time()):
                self._resend()

    def _resend(self) -> None:
        """Between detections: the last confirmed target, predicted for the vehicle's motion since its frame."""
        now = time.time()
        target = self._hold.predicted(now, self.link.state, self.profile)
        self._hold.last_sent = now
        if target is None:
            return
        try:
            self.link.send_landing_target(target)
        except FlightLinkError:
            self.counters["send_failed"] += 1
            return
        self.counters["targets_resent"] += 1
        self.sent_times.append(now)

    def _handle_detections(self, payload: bytes) -> None:
        self.counters["detections"] += 1
        try:
            detections = messages.decode_as(payload, messages.Detections)
            if self._chosen is not None and detections.instance != self._chosen():
                self.counters["not_chosen"] += 1
                return
            confirmed = self._confirmed(detections)
            if confirmed is None:  # a frame the confirmation has seen (a second detector in a migration)
                self.counters["duplicate"] += 1
                return
            if detections.ids and not confirmed.ids:
                self.counters["unconfirmed"] += 1
                return
            detections = confirmed
            index = choose_marker(detections, self.settings.target_id, self.settings.confirmation.site)
            if index is None:
                self.counters["no_target"] += 1
                return
            marker_id = marker_id_of(detections.ids[index]) or 0
            target, held = self._targets.build(
                marker_points(detections.corners[index]), marker_id=marker_id,
                frame_time=float(detections.frame_time), profile=self.profile, state=self.link.state,
                pose_at=self.link.pose_at, measured=_pose_of(detections, index),  # the detector's own pose, if any
            )
        except (MessageError, FlightLinkError) as exc:
            self.counters["malformed"] += 1
            if self.counters["malformed"] % 100 == 1:
                log.warning("flight bridge dropped a detections message (%d so far): %s",
                            self.counters["malformed"], exc)
            return
        age = time.time() - target.time
        if age > self.settings.max_detection_age_s:
            self.counters["stale"] += 1
            return
        if age < -self.settings.max_clock_skew_s:
            # From the future: sending it would make it the newest frame and every real
            # detection after it a "duplicate", silencing LANDING_TARGET.
            self.counters["future"] = self.counters.get("future", 0) + 1
            return
        if target.time <= self._last_frame_time:
            # the same (or an older) frame from a second detector while a migration overlaps them
            self.counters["duplicate"] += 1
            return
        # A token bucket (burst 2) rather than a minimum gap: a detector at exactly the cap, with
        # jitter, keeps its full rate, and a faster one is held to max_target_hz on average.
        now = time.monotonic()
        self._tokens = min(2.0, self._tokens + (now - self._last_target_mono) * self.settings.max_target_hz)
        self._last_target_mono = now
        if self._tokens < 1.0:
            self.counters["rate_limited"] += 1
            return
        try:
            self.link.send_landing_target(target)
        except FlightLinkError as exc:
            self.counters["send_failed"] += 1
            if (type(exc), *exc.args) != self._last_send_error:
                self._last_send_error = (type(exc), *exc.args)
                log.warning("flight bridge: LANDING_TARGET not sent: %s", exc)
            return
        self._last_send_error = ()
        self._last_frame_time = target.time
        self._tokens -= 1.0
        self.counters["targets_sent"] += 1
        self._hold.confirm(held, time.time())
        self.sent_times.append(time.time())
        self._note_target_kind(target)

    def _note_target_kind(self, target: LandingTarget) -> None:
        """Warn once when targets carry angles only: ArduPilot then needs its own rangefinder."""
        self.angles_only = target.position is None and not target.distance > 0
        if self.angles_only:
            self.counters["angles_only"] = self.counters.get("angles_only", 0) + 1
            if not self._angles_only_warned:
                self._angles_only_warned = True
                log.warning("%s (no size for marker %d in the site's markers, no rangefinder distance heard)",
                            ANGLES_ONLY, target.target_num)

    def _confirmed(self, detections: messages.Detections) -> messages.Detections | None:
        """Only confirmed markers (``kgadapt.onboard.flight.confirmation``); None for a frame already seen.

        Stale and future frames pass unchanged: the checks below count and refuse them.
        """
        frame_time = detections.frame_time
        age = time.time() - frame_time
        if age > self.settings.max_detection_age_s or age < -self.settings.max_clock_skew_s:
            return detections
        return self.confirmer.keep(detections, frame_time, self._places(detections))

    def _places(self, detections: messages.Detections) -> list[Place | None] | None:
        """Where each candidate lies in the local frame (None where unknown), so that the confirmation
        allows for the vehicle's motion between frames (kgadapt.onboard.flight.confirmation)."""
        ids, corners = detections.ids, detections.corners
        if not ids or len(ids) != len(corners) or self.link.pose_at(float(detections.frame_time)) is None:
            return None
        site = self.settings.confirmation.site
        state = self.link.state
        places = []
        for raw_id, c in zip(ids, corners, strict=True):
            mid = marker_id_of(raw_id)
            try:
                place = (None if mid is None or (site is not None and mid not in site.sizes_m)
                         else self._targets.locate(marker_points(c), marker_id=mid,
                                                   frame_time=float(detections.frame_time), state=state,
                                                   pose_at=self.link.pose_at))
            except MessageError:
                place = None  # the confirmer names the malformed marker
            places.append(place)
            if place is not None:
                self.counters["placed"] += 1
        return places

    def _publish(self, state: FlightState) -> None:
        publisher = self._publisher
        if publisher is None:
            return
        # angles_only absent while the targets carry a range (as every optional field: absent = no news)
        body = state.as_message(angles_only=True if self.angles_only else None)
        try:
            publisher.put(messages.encode(body))
        except Exception as exc:  # noqa: BLE001 - zenoh errors: log and try again next period
            log.warning("flight bridge: flight_state not published: %s", exc)
            return
        self._last_published = state.discrete()
        self.counters["published"] += 1
        if self._on_state is not None:
            with self._callback_ready:
                self._latest_for_callback = state
                self._callback_ready.notify()

    def _notify(self) -> None:
        while True:
            with self._callback_ready:
                while self._latest_for_callback is None and not self._stopping:
                    self._callback_ready.wait()
                if self._stopping:
                    return
                state, self._latest_for_callback = self._latest_for_callback, None
            try:
                if state is not None and self._on_state is not None:  # both are, once woken to run
                    self._on_state(state)
            except Exception:  # a callback's bug must not stop the notifier
                log.exception("flight bridge: on_state callback failed")


def _camera_of(k: CameraIntrinsics) -> CameraModel:
    return CameraModel(fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy)


def flight_control_params(state: FlightState, component: str = "flight_control") -> dict[str, Any]:
    """Parameters of the ``flight_state`` write: the FlightControl component's run-time properties.

    ``autopilot_load_pct`` is the autopilot's main-loop load (SYS_STATUS.load), not the
    component's design-time ``cpu_load`` on the companion computer. Unknown figures go as
    None, and the writer removes them from the graph: no stale value stays there as current.
    """
    params = {
        "name": component, "time": state.time, "link": state.link, "armed": state.armed, "mode": state.mode,
        "landed_state": state.landed_state, "battery_pct": state.battery_pct, "battery_v": state.battery_v,
        "autopilot_load_pct": state.onboard_load, "last_heartbeat": state.last_heartbeat,
    }
    return params


class FlightControlWriter:
    """An ``on_state`` callback that writes the flight state into the graph through a KnowledgeClient.

    Writes at once when link, arming, mode or landed state change, else at most every
    ``min_period_s``; a failed write is logged (once per distinct error) and retried with the next state.
    """

    def __init__(self, client: Any, *, component: str = "flight_control", verb: str = "flight_state",
                 min_period_s: float = 1.0) -> None:
        self.client = client
        self.component = component
        self.verb = verb
        self.min_period_s = min_period_s
        self.written = 0
        self.failed = 0
        self._last: tuple[object, ...] | None = None
        self._last_at = -math.inf
        self._last_error: tuple[Any, ...] = ()  # the last failure's type and arguments: logged once

    def __call__(self, state: FlightState) -> None:
        now = time.monotonic()
        if state.discrete() == self._last and now - self._last_at < self.min_period_s:
            return
        try:
            self.client.write(self.verb, flight_control_params(state, self.component))
        except KgadaptError as exc:
            self.failed += 1
            if (type(exc), *exc.args) != self._last_error:
                self._last_error = (type(exc), *exc.args)
                log.warning("flight state not written to the graph: %s", exc)
            return
        self._last, self._last_at, self._last_error = state.discrete(), now, ()
        self.written += 1
