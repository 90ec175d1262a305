"""The marker-detector program: ``python -m kgadapt.onboard.perception.detector`` (what the deployer runs).

::

    python -m kgadapt.onboard.perception.detector --robot R --host H --instance I --config NAME --connect ENDPOINT [--camera cam0]
    python -m kgadapt.onboard.perception.detector ... --config-json '{"preprocess": [...], "parameters": {...}}'   # no store

It asks the knowledge service for its configuration (named query
``detector_config``), builds the pre-processing and ``cv2.aruco.ArucoDetector``
of it, subscribes to ``kgadapt/<R>/camera/<cam>/frame`` and publishes
``detections`` on ``kgadapt/<R>/detector/<I>/markers``; then announces it is
ready (kgadapt.shared.readiness: a line on stdout). SIGINT or SIGTERM stop it cleanly (status 0).

In-place reconfiguration: a detector started with ``--config`` also answers
``kgadapt/<R>/host/<H>/detector/<I>/configure`` (a ``configure_request``
naming another configuration). It takes the configuration from the graph,
checks there (named query ``in_place_change``) that its deployment may take
the new one's in place on this host, builds the new detector off the frame
path and swaps it in between two frames; the reply names the first frame
processed with it. It then prints ``<CONFIGURED_TOKEN> <config> <deployment>``
so its deployer's record (and a restart) follow. Anything refused leaves the
running configuration untouched.

Reflexes (kgadapt.onboard.perception.reflex): a detector configured from the graph also
fetches, once it has said it is ready (on a thread of its own, off the frame
path) and after each in-place change, the named query
``reflex_table`` (what it may take in place on this host, band by band, with
the bands' edges and margins and the feature's ms-per-frame budget), builds a
detector for every configuration in it beforehand, and per frame reads the
frame's light (the window-proof estimate, weighted around the markers it saw
within the last second). Ready means it detects with the configuration it was given;
its reflexes start with the first frame after the table is armed (a line on
stderr says when), and a change asked for before that builds its detector on
demand. On the evidence of a frame (its light past a band
edge by the margin, its detections collapsing, a hedge finding the markers
where the running configuration does not) it switches in place before the
next detection, with no round trip to the adaptation manager, puts a
``reflex`` message on ``kgadapt/<R>/detector/<I>/reflex`` and prints the
``<CONFIGURED_TOKEN>`` line. After a switch, and near a band edge, it also
runs a second configuration on a frame the running one found no marker on,
when both fit the budget, and publishes whichever found more markers (its
``config`` names it). The last reflex is put again about once a second, with
what hedging has cost so far (``frames``, ``hedged``, ``hedge_ms``).

Idle or active: a detector also answers ``kgadapt/<R>/host/<H>/detector/<I>/activity``
(an ``activity_request``, ``{"active": false}`` or ``true``). An idle detector stays
subscribed and publishes nothing: a warm standby the adaptation manager can make the
running detector with one request. It keeps the newest frame in its slot (each new one
replaces it, uncounted as a drop) and, once per configuration it may run, detects on a
frame without publishing, so that its first detection after activation runs warm. Made
active, it answers the frame it holds at once (captured within a frame period before the
activation; its detections carry its capture time) rather than waiting for the next one;
a frame held longer than ``HELD_FRAME_S`` (the camera stopped) is not answered.
A launcher's idle pool member holds its camera's newest frame the same way while it
waits (``pool_session``), and the detector it becomes answers that frame first.

Stale frames are dropped, never queued: the Zenoh callback only puts the
payload into a one-frame slot (replacing an unprocessed one) and a worker
thread takes the newest frame when it is free. Memory stays bounded whatever
the camera's rate.

Exit status: 0 stopped by a signal, 1 an error (message on stderr), 2 the
knowledge store does not know the configuration (the message names it).
"""

from __future__ import annotations

import argparse
import base64
import binascii
import enum
import logging
import os
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import msgspec

from kgadapt.shared import keys, messages, rpc
from kgadapt.shared.errors import (
    ConfigError,
    DeploymentError,
    KgadaptError,
    MessageError,
    RemoteError,
    RequestTimeout,
    TransportError,
)
from kgadapt.shared.readiness import (
    POOL_DEPLOYMENTS_ENV,
    READY_TOKEN,
    RESOLVED_CONFIG_ENV,
    START_IDLE_ENV,
    announce_configured,
    announce_ready,
    say_line,
)

log = logging.getLogger("kgadapt.onboard.perception.detector")

EXIT_UNKNOWN_CONFIG = 2
INLINE_CONFIG = "inline"
# An activated standby answers the frame it held only if it arrived this recently: older, the camera
# stopped, and the manager would take a stale answer for the first detection of its switch.
HELD_FRAME_S = 1.0
IDLE_WAKE_S = 0.5  # how often an idle worker looks at its stop flag and for a detector still cold


class UnknownConfiguration(KgadaptError):
    """The knowledge store has no detector configuration of that name."""


class LatestSlot:
    """Holds the newest item only: ``put`` replaces (and counts) an unprocessed one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.replaced = 0
        # ``replaced`` as it stood when the last item was taken. Every item replaced between two takes
        # is newer than the first taken and older than the second, so the difference between two takes'
        # counts is exactly the items lost between them; ``replaced`` read later (after the work on the
        # first) would count, against it, items lost after it.
        self.replaced_when_taken = 0

    def put(self, item: Any) -> None:
        with self._cond:  # held for a pointer swap only: fine in a Zenoh callback
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def peek(self) -> Any:
        """The item the slot holds, left in it (None when empty)."""
        with self._cond:
            return self._item

    def take(self, timeout: float | None = None) -> Any:
        """The newest item, waiting up to ``timeout``; None on timeout or close."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            if item is not None:
                self.replaced_when_taken = self.replaced
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass(frozen=True, kw_only=True)
class DetectorSettings:
    """Who this detector is and what it listens to."""

    robot: str
    host: str
    instance: str
    camera: str = "cam0"
    idle: bool = False  # start idle (a warm standby): no detection work until activated

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.host, "host name")
        keys.check_name(self.instance, "instance name")
        keys.check_name(self.camera, "camera name")


def fetch_config(session: Any, robot: str, name: str, *, wait_s: float = 10.0) -> Any:
    return fetch_config_row(session, robot, name, wait_s=wait_s)[0]


def fetch_config_row(session: Any, robot: str, name: str, *, wait_s: float = 10.0) -> tuple[Any, dict[str, Any]]:
    """The configuration ``name`` from the knowledge service, as a checked DetectorConfig.

    Asks again while nothing answers or the service refuses (it may be starting, or
    its store reloading) for up to ``wait_s``; raises UnknownConfiguration when the store has no such
    configuration, RequestTimeout when no service answered in time.
    """
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.onboard.perception.markers import parse_config

    keys.check_name(name, "configuration name")
    client = KnowledgeClient(session, robot, own=True)
    try:
        rows = client.query("detector_config", {"config": name}, wait_s=wait_s)
    except RequestTimeout:
        raise RequestTimeout(
            f"no knowledge service of robot {robot!r} answered for detector configuration {name!r} "
            f"within {wait_s:.0f} s"
        ) from None
    if not rows:
        raise UnknownConfiguration(f"detector configuration {name!r} is not in the knowledge store")
    row = rows[0]
    if row.get("config_json") is None:
        raise ConfigError(f"detector configuration {name!r} has no config_json in the knowledge store")
    return parse_config(name, row["config_json"], dictionary=row.get("dictionary")), row


def carried_config(name: str, environ: Mapping[str, str] = os.environ) -> tuple[Any, dict[str, Any]] | None:
    """Configuration ``name`` as the deployer resolved it from the graph for this start
    ($KGADAPT_RESOLVED_CONFIG, a ``resolved_config`` message), checked as a fetched one is; None when
    none was carried, or it names another configuration, or it does not check (then the graph is asked)."""
    from kgadapt.onboard.perception.markers import parse_config

    text = environ.get(RESOLVED_CONFIG_ENV)
    if not text:
        return None
    try:
        resolved = messages.decode_as(base64.b64decode(text, validate=True), messages.ResolvedConfig)
        if resolved.config != name:
            return None
        config = parse_config(name, resolved.config_json, dictionary=resolved.dictionary)
    except (binascii.Error, ValueError, KgadaptError) as exc:
        log.warning("the configuration carried by the start request is not usable (%s); asking the graph", exc)
        return None
    return config, {"config": name, "deployment": resolved.deployment, "digest": resolved.digest}


def fetch_reflex_table(session: Any, robot: str, *, deployment: str, host: str, wait_s: float = 2.0,
                       timeout: float = 2.0, stopping: Callable[[], bool] = lambda: False) -> Any:
    """The ``reflex_table`` of a detector of ``deployment`` on ``host``, compiled (kgadapt.onboard.perception.reflex).
    ``wait_s``: how long to ask again while no service answers; ``timeout``: how long one answer may take.
    None, not compiled, when ``stopping()`` says so once the answer is in."""
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.onboard.perception.markers import parse_config

    rows = KnowledgeClient(session, robot, own=True, timeout=timeout).query(
        "reflex_table", {"deployment": deployment, "host": host}, wait_s=wait_s)
    if stopping():
        return None
    from kgadapt.onboard.perception.reflex import ReflexTable  # 12 ms of imports on a plain start

    # Now: fresh live figures of this robot rank above calibration, as in the planner's ranking.
    return ReflexTable.from_rows(rows, parse=lambda name, raw, dictionary: parse_config(name, raw, dictionary=dictionary),
                                 now=time.time())


def build_cores(table: Any, *, built: Mapping[str, Any] | None = None,
                stopping: Callable[[], bool] = lambda: False) -> dict[str, Any] | None:
    """A detector for every configuration of the reflex ``table``, by name (those in ``built`` reused);
    None once ``stopping()`` says so, checked before each one is built."""
    from kgadapt.onboard.perception.markers import MarkerDetector

    built = built or {}
    cores: dict[str, Any] = {}
    for name, choice in table.choices().items():
        if name not in built and stopping():
            return None
        cores[name] = built[name] if name in built else MarkerDetector(choice.settings)
    return cores


@dataclass(frozen=True)
class WarmStart:
    """What a launcher's pool member prepared while it waited for a start (deploy/launcher.py): its
    Zenoh session, the reflex table of each deployment it may be started as (on ``host``), with
    every candidate's detector built once, and its camera's newest frame, held (``frames``, from
    ``frame_subscriber``, on ``camera``: (robot, camera)) so that its first detection need not wait
    for the camera's next frame; the argument parser, built and used once (a start only parses)."""

    session: Any
    host: str | None = None
    tables: Mapping[str, Any] = field(default_factory=dict)  # deployment -> its reflex table
    cores: dict[str, Any] = field(default_factory=dict)  # configuration -> its detector
    camera: tuple[str, str] | None = None
    frames: LatestSlot | None = None
    frame_subscriber: Any = None
    parser: argparse.ArgumentParser | None = None

    def armed(self, deployment: str | None, host: str) -> tuple[Any, dict[str, Any]] | None:
        """The table and detectors prepared for a start of ``deployment`` on ``host``; None if none was."""
        table = self.tables.get(deployment) if deployment and host == self.host else None
        if table is None:
            return None
        return table, {name: self.cores[name] for name in table.choices()}


_END = b""  # what ends the notifier's thread (no message is empty)


class ReflexNotifier:
    """Puts ``reflex`` messages from a thread of its own: the frame path only queues them (a blocked
    put waits for a congested manager there, not in the worker). At most ``depth`` wait; the oldest goes."""

    def __init__(self, publisher: Any, instance: str, *, again: Callable[[], bytes | None], again_s: float = 1.0,
                 depth: int = 32) -> None:
        import queue

        self._publisher = publisher
        self._instance = instance
        self._again, self._again_s = again, again_s
        self._queue: Any = queue.Queue(maxsize=depth)
        self._thread = threading.Thread(target=self._run, name="detector-reflex", daemon=True)
        self._thread.start()

    def put(self, payload: bytes) -> None:
        import queue

        while True:
            try:
                self._queue.put_nowait(payload)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass

    def _run(self) -> None:
        import queue

        while True:
            try:
                payload = self._queue.get(timeout=self._again_s)
            except queue.Empty:
                payload = self._again()  # the last one again: a receiver acts once per count
                if payload is None:
                    continue
            if payload is _END:
                return
            try:
                self._publisher.put(payload)
            except Exception as exc:  # noqa: BLE001 - put again within a second
                log.warning("detector %s: reflex not published: %s", self._instance, exc)

    def close(self) -> None:
        self.put(_END)
        self._thread.join(timeout=2)
        rpc.undeclare_quietly(self._publisher)


class Detector:
    """Subscribes to frames, detects markers on a worker thread, publishes detections."""

    def __init__(self, settings: DetectorSettings, config: Any, *, deployment: str | None = None) -> None:
        from kgadapt.onboard.perception.markers import MarkerDetector

        self.settings = settings
        self.deployment = deployment  # of the configuration it runs, when it came from the graph
        # (configuration, its detector, generation): replaced whole, read once per frame by the worker,
        # so a reconfiguration lands between two frames.
        self._active = (config, MarkerDetector(config), 0)
        # (Reflex, detectors by configuration name): replaced whole by arm(), read once per frame.
        self._reflexes: tuple[Any, dict[str, Any]] | None = None
        # Held for a few assignments: the deployment and the reflex table armed for it change together.
        self._changing = threading.Lock()
        self._reflex_generation = 0  # the generation the reflex last knew of
        self._own_generations: set[int] = set()  # generations the reflex made (not the manager's)
        self.reflexes = 0  # reflexes so far: switches made on its own evidence, and bands it could not take
        self._hedge_ms: dict[str, float] = {}  # measured ms per frame of each configuration run as a hedge
        self.hedged = 0  # frames on which a hedge ran
        self.hedge_ms_total = 0.0
        self._last_reflex: messages.Reflex | None = None  # the last reflex message, put again now and then
        self._seen_markers: tuple[float, list[Any]] = (0.0, [])  # (time, corners) of the last markers found
        self._reflex_pub: Any = None
        self._first_frame: dict[int, int] = {}  # generation -> seq of the first frame it processed
        self._generation_seen = threading.Condition()
        self.slot = LatestSlot()
        self.processed = 0
        self.malformed = 0
        self._stop = threading.Event()
        self.active = threading.Event()  # cleared: idle (the newest frame held, nothing published)
        self._idle_replaced = 0  # frames that replaced each other in the slot while idle: no drops of ours
        self._warm: weakref.WeakSet[Any] = weakref.WeakSet()  # detectors that have run once (see _warm_up)
        if not settings.idle:
            self.active.set()
        self._worker: threading.Thread | None = None
        self._subscriber: Any = None
        self._publisher: Any = None
        self._token: Any = None

    @property
    def config(self) -> Any:
        return self._active[0]

    @property
    def core(self) -> Any:
        return self._active[1]

    def swap(self, config: Any, core: Any = None) -> int:
        """Take ``config`` from the next frame on (with ``core``, its detector built beforehand, when
        given); returns its generation (see ``first_frame``)."""
        from kgadapt.onboard.perception.markers import MarkerDetector

        if core is None:
            core = MarkerDetector(config)  # built here, off the frame path
        generation = self._active[2] + 1
        self._active = (config, core, generation)
        return generation

    def prepared(self, name: str) -> tuple[Any, str] | None:
        """The detector built beforehand for configuration ``name`` and its deployment, when the reflex
        table from the graph lets the running deployment take it in place on this host; else None."""
        armed = self._reflexes
        if armed is None:
            return None
        choice = armed[0].table.choices().get(name)
        core = armed[1].get(name)
        if choice is None or core is None:
            return None
        return core, choice.deployment

    def arm(self, table: Any, cores: dict[str, Any] | None = None, *, deployment: str | None = None) -> bool:
        """Hold the reflex ``table`` (kgadapt.onboard.perception.reflex.ReflexTable): its detectors are built here
        (or given, built beforehand: ``cores``), off the frame path, so a reflex costs the frame nothing.
        ``deployment``: the one the table was asked for; a table that arrives once the detector runs another
        deployment's configuration (changed in place while it was asked for) is dropped: False."""
        from kgadapt.onboard.perception.reflex import Reflex

        if cores is None:
            cores = build_cores(table)
            assert cores is not None  # nothing stops it here
        with self._changing:
            if deployment is not None and deployment != self.deployment:
                return False
            config, _core, generation = self._active
            # generation 0 is the start's configuration; a later one not made by the reflex, the manager's.
            reflex = Reflex(table=table, running=config.name,
                            follow_light=generation != 0 and generation not in self._own_generations)
            previous = self._reflexes
            if previous is not None:  # the band it believed in and the markers it saw carry over
                reflex.band, reflex.last_seen, reflex.seen_level = previous[0].band, previous[0].last_seen, \
                    previous[0].seen_level
            self._reflex_generation = generation
            self._reflexes = (reflex, cores)
        return True

    def take(self, config: Any, core: Any, deployment: str) -> int:
        """:meth:`swap` to ``config`` of ``deployment`` (a change asked of it); its generation."""
        with self._changing:  # a reflex table asked for the deployment it leaves is not armed after this
            generation = self.swap(config, core)
            self.deployment = deployment
        return generation

    def candidates(self) -> list[str]:
        """The configurations whose detectors the armed reflex table holds built (none before it is armed)."""
        armed = self._reflexes
        return sorted(armed[1]) if armed is not None else []

    def first_frame(self, generation: int, timeout: float) -> int | None:
        """The sequence number of the first frame processed with ``generation``, waiting up to ``timeout``."""
        with self._generation_seen:
            self._generation_seen.wait_for(lambda: generation in self._first_frame, timeout)
            return self._first_frame.get(generation)

    def take_frames(self, slot: LatestSlot, subscriber: Any) -> None:
        """Before :meth:`setup`: take the camera subscription a pool member declared while it waited
        (``subscriber`` putting into ``slot``), so the first frame answered is the one it holds (at most a
        frame period old; older than ``HELD_FRAME_S`` it is not answered) instead of the camera's next."""
        self.slot, self._subscriber = slot, subscriber
        self._idle_replaced = slot.replaced  # frames that replaced each other before the start: no drops of ours

    def setup(self, session: Any) -> None:
        import zenoh

        s = self.settings
        try:
            self._publisher = session.declare_publisher(
                keys.detector_markers(s.robot, s.instance), congestion_control=zenoh.CongestionControl.DROP,
            )
            # BLOCK, from a thread of its own (ReflexNotifier): a stopped or slow manager gets the message
            # when it can take it, and never holds up the frames; put again once a second, a message lost
            # all the same (a stopped manager's link dropped) still arrives.
            self._reflex_pub = ReflexNotifier(session.declare_publisher(
                keys.detector_reflex(s.robot, s.instance), congestion_control=zenoh.CongestionControl.BLOCK,
            ), s.instance, again=self._reflex_again)
            self._worker = threading.Thread(target=self._work, name="detector-worker", daemon=True)
            self._worker.start()
            if self._subscriber is None:  # else the pool member's, holding its newest frame (take_frames)
                self._subscriber = session.declare_subscriber(keys.camera_frame(s.robot, s.camera), self._on_frame)
            self._token = session.liveliness().declare_token(keys.detector_alive(s.robot, s.instance))
        except Exception as exc:  # whatever zenoh raises: translated here
            self.shutdown()
            raise TransportError(f"detector {s.instance}: cannot declare on Zenoh: {exc}") from exc

    def _on_frame(self, sample: Any) -> None:
        # Zenoh callback: copy the payload and the arrival time, nothing else.
        self.slot.put((sample.payload.to_bytes(), time.time()))

    def _work(self) -> None:
        slot = self.slot
        while not self._stop.is_set():
            if not self.active.is_set():
                self._idle()
                continue
            item = slot.take(timeout=IDLE_WAKE_S)
            if item is None or not self.active.is_set() or self._stop.is_set():
                continue  # idled (or stopping) while it waited: the next frame is held for the activation
            if time.time() - item[1] > HELD_FRAME_S:
                continue  # held while idle and the camera stopped since: not an answer to give now
            try:
                self._process(*item, dropped=slot.replaced_when_taken - self._idle_replaced)
            except MessageError as exc:
                self.malformed += 1
                log.warning("detector %s: dropped a frame: %s", self.settings.instance, exc)
            except Exception:  # keep detecting: one bad frame is not a reason to stop
                self.malformed += 1
                log.exception("detector %s: frame failed", self.settings.instance)

    def _idle(self) -> None:
        """Wait, idle, until made active (or a second look is due), leaving the newest frame in the
        slot; warm up a detector that has not run yet on it first."""
        before = self.slot.replaced
        cold = self._warm_up()
        # Event.wait returns as soon as the activity switch sets it: the held frame is taken at once.
        self.active.wait(0.1 if cold else IDLE_WAKE_S)
        self._idle_replaced += self.slot.replaced - before

    def _warm_up(self) -> bool:
        """Run one detector that has not run yet (the active one first, then the reflex table's) on the
        held frame, publishing nothing: a first detection costs about twice a steady one (measured 43-59
        against 23 ms), which an activated standby would otherwise pay on its first answer. True while
        one is still cold (waiting for a frame)."""
        cores = [self._active[1]] + list((self._reflexes or (None, {}))[1].values())
        cold = [core for core in cores if core not in self._warm]
        if not cold:
            return False
        item = self.slot.peek()
        if item is None:
            return True
        import cv2
        import numpy as np

        core = cold[0]
        self._warm.add(core)  # once, even if this frame does not decode
        try:
            frame = messages.decode_as(item[0], messages.Frame)
            gray = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
            if gray is not None:
                if self._reflexes is not None:
                    self._light(gray, float(frame.time))
                core.detect(gray)
        except Exception as exc:  # noqa: BLE001 - a warm-up only: the frame's own answer reports it
            log.debug("detector %s: warm-up on a held frame failed: %s", self.settings.instance, exc)
        return len(cold) > 1

    def _process(self, payload: bytes, received: float, *, dropped: int) -> None:
        import cv2
        import numpy as np

        frame = messages.decode_as(payload, messages.Frame)
        start = time.perf_counter()
        gray = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise MessageError(f"frame {frame.seq} of camera {frame.camera}: JPEG does not decode")
        decode_ms = (time.perf_counter() - start) * 1e3
        config, core, generation = self._active
        armed = self._reflexes
        level = None
        hedge: tuple[str, Any, float] | None = None  # (configuration, its result, ms)
        # This frame's reflexes, carried out at once and told, in their order, once its detections are out:
        # the message, the log line and the deployer's record wake other threads and processes, which on two
        # cores took the CPU from the very frame the reflex was for. A band nothing here takes in place is told
        # after them too: the manager starts the band's configuration as a new process at once, and on two
        # cores that start took the CPU from this frame (the running dark configuration's detection of the
        # first day frame 15-19 ms told before, 7-8 told after; bench adaptation --changes new-process,
        # traced). Where the running configuration sees in the new light, this frame is the pilot's fix; where
        # it does not, it found nothing fast (about 1 ms for the day configuration on a dark frame).
        tells: list[tuple[Any, messages.Reflex, bool]] = []
        if armed is not None:
            reflex, cores = armed
            if generation != self._reflex_generation:
                if generation not in self._own_generations:
                    reflex.taken(config.name)  # the manager changed it: follow, do not fight
                self._reflex_generation = generation
            level = self._light(gray, float(frame.time))
            swap = reflex.on_light(level)
            if swap is not None:
                tells.append(self._reflex_take(swap, cores, frame))
                if swap.config is not None:
                    config, core, generation = self._active
        try:
            result = core.detect(gray)
            if armed is not None:
                reflex, cores = armed
                found = result.clean_count
                # Only a frame the running configuration found nothing on can be won by the hedge: the others
                # are published at once, without its cost; but a try after a fall of the count is judged on
                # what both find on the same frames (reflex.comparing).
                hedge = None if found and not reflex.comparing else \
                    self._hedge(reflex, cores, gray, level, result.processing_ms)
                swap = reflex.on_result(found, time.time(), hedge=hedge[0] if hedge else None,
                                        hedge_found=hedge[1].clean_count if hedge else 0, level=level)
                if hedge is not None and hedge[1].clean_count > found:
                    config, result = cores[hedge[0]].config, hedge[1]  # keep whichever finds the markers
                if swap is not None:
                    tells.append(self._reflex_take(swap, cores, frame))
            s = self.settings
            detections = messages.Detections(
                instance=s.instance, config=config.name, host=s.host, seq=frame.seq,
                frame_time=frame.time, time=time.time(),
                ids=result.ids, corners=result.corners, processing_ms=round(result.processing_ms, 3),
                camera=frame.camera, received=received, decode_ms=round(decode_ms, 3),
                dropped=dropped, clean=result.clean, frame_sent=frame.sent,
            )
            if hedge is not None:
                self.hedged += 1
                self.hedge_ms_total += hedge[2]
            if result.ids:
                self._seen_markers = (float(frame.time), result.corners)
            self._publisher.put(messages.encode(detections))
            self.processed += 1
        finally:  # told even when this frame's detection failed: the swap was carried out
            for told in tells:
                self._reflex_tell(*told)
        if generation not in self._first_frame:
            with self._generation_seen:
                self._first_frame[generation] = int(frame.seq)
                self._generation_seen.notify_all()

    def _hedging(self, reflex: messages.Reflex, *, again: bool | None = None) -> messages.Reflex:
        """``reflex`` with the hedging figures so far."""
        return msgspec.structs.replace(reflex, again=again, frames=self.processed, hedged=self.hedged,
                                       hedge_ms=round(self.hedge_ms_total, 3))

    def _reflex_again(self) -> bytes | None:
        """The last reflex again, with the hedging figures so far (None before the first reflex)."""
        last = self._last_reflex
        return None if last is None else messages.encode(self._hedging(last, again=True))

    def _light(self, gray: Any, frame_time: float) -> float | None:
        """This frame's light, weighted around the markers found within the last second (a window or a
        lamp in view does not fool it; kgadapt.onboard.perception.illumination.estimate_light)."""
        from kgadapt.onboard.perception.illumination import estimate_light

        at, corners = self._seen_markers
        try:
            return estimate_light(gray, corners if frame_time - at <= 1.0 else ()).level
        except KgadaptError as exc:
            log.debug("detector %s: no light estimate: %s", self.settings.instance, exc)
            return None

    def _hedge(self, reflex: Any, cores: dict[str, Any], gray: Any, level: float | None,
               spent_ms: float) -> tuple[str, Any, float] | None:
        """Run the reflex's hedge on this frame too, if it fits the graph's ms-per-frame budget."""
        name = reflex.hedge_for(level)
        budget = reflex.table.budget_ms
        if name is None or budget is None or name not in cores:
            return None
        choice = reflex.table.choices().get(name)
        cost = self._hedge_ms.get(name, choice.ms_per_frame if choice and choice.ms_per_frame else spent_ms)
        if spent_ms + cost > budget:
            return None
        start = time.perf_counter()
        result = cores[name].detect(gray)
        ms = (time.perf_counter() - start) * 1e3
        self._hedge_ms[name] = ms if name not in self._hedge_ms else 0.8 * self._hedge_ms[name] + 0.2 * ms
        return name, result, ms

    def _reflex_take(self, swap: Any, cores: dict[str, Any], frame: messages.Frame) -> tuple[Any, messages.Reflex, bool]:
        """Carry a reflex out between two frames: what :meth:`_reflex_tell` then tells (the swap, its message,
        whether this detector took a configuration)."""
        active = self._active
        self.reflexes += 1  # switches and reports alike: the manager counts them
        took = swap.config is not None and swap.config in cores
        if took:
            core = cores[swap.config]
            active = (core.config, core, active[2] + 1)
            self._own_generations.add(active[2])
            self._reflex_generation = active[2]
            self._active = active
            if swap.deployment:
                with self._changing:
                    self.deployment = swap.deployment
        s = self.settings
        body = self._hedging(messages.Reflex(
            instance=s.instance, host=s.host, config=swap.config, previous=swap.previous,
            deployment=swap.deployment, elsewhere=swap.elsewhere, band=swap.band,
            from_band=swap.from_band, evidence=swap.evidence,
            level=None if swap.level is None else round(swap.level, 2), seq=int(frame.seq),
            frame_time=float(frame.time), time=time.time(), count=self.reflexes))  # when it was carried out
        return swap, body, took

    def _reflex_tell(self, swap: Any, body: messages.Reflex, took: bool) -> None:
        """Tell the deployer (its record), the manager and the log of a reflex carried out."""
        if took and swap.deployment:
            announce_configured(swap.config, swap.deployment)  # the deployer's record
        self._last_reflex = body
        self._reflex_pub.put(messages.encode(body))
        log.info("detector %s: reflex (%s, light %s): %s -> %s", self.settings.instance, swap.evidence, body.level,
                 swap.previous, swap.config or f"nothing here for band {swap.band}")

    def shutdown(self) -> None:
        for name in ("_token", "_subscriber"):
            thing = getattr(self, name)
            if thing is not None:
                rpc.undeclare_quietly(thing)
                setattr(self, name, None)
        self._stop.set()
        self.active.set()  # wakes an idle worker at once (it looks at _stop before taking a frame)
        self.slot.close()
        if self._worker is not None:
            self._worker.join(timeout=5)
            self._worker = None
        if self._reflex_pub is not None:
            self._reflex_pub.close()
            self._reflex_pub = None
        if self._publisher is not None:
            rpc.undeclare_quietly(self._publisher)
            self._publisher = None


class ActivitySwitch:
    """Answers idle/active requests for one detector, from a :class:`kgadapt.shared.rpc.Server` worker
    (nothing is answered inside a Zenoh callback)."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        instance = detector.settings.instance
        self._server = rpc.Server(f"detector {instance} activity", workers=1, max_pending=8,
                                  prefix=f"detector {instance}: ")

    def setup(self, session: Any) -> None:
        s = self.detector.settings
        self._server.setup()
        try:
            self._server.serve(session, keys.detector_activity(s.robot, s.host, s.instance), self._answer,
                               what="activity")
        except BaseException:
            self._server.shutdown()
            raise

    def _answer(self, request: rpc.Request) -> rpc.Reply:
        # A MessageError (not an activity_request) is answered with reply_err by the server.
        d = self.detector
        active = messages.decode_as(request.payload or b"", messages.ActivityRequest).active
        if active:
            d.active.set()
        else:
            d.active.clear()
        log.info("detector %s: %s", d.settings.instance, "active" if active else "idle")
        return rpc.Reply(key=request.key, payload=messages.encode(
            messages.ActivityReply(instance=d.settings.instance, active=active, processed=d.processed)))

    def shutdown(self) -> None:
        self._server.shutdown()


def set_active(session: Any, robot: str, host: str, instance: str, active: bool, *,
               timeout: float = 2.0) -> messages.ActivityReply:
    """Make the running detector ``instance`` on ``host`` idle or active; its reply (instance, active, processed).

    No reply at once means no matching queryable is known yet: a detector's
    deployer says it is ready before every session has its declaration (a
    standby idled right after its start found none under load). Nobody got the
    request, so it is sent again until ``timeout`` (``rpc.call``'s ``resend_for``):
    RequestTimeout (NoResponder) then; a refusal is a DeploymentError.
    """
    key = keys.detector_activity(robot, host, instance)
    payload = messages.encode(messages.ActivityRequest(active=bool(active)))
    try:
        return rpc.call(session, key, payload, lambda data: messages.decode_as(data, messages.ActivityReply),
                        timeout=timeout, resend_for=timeout)
    except RequestTimeout as exc:
        raise RequestTimeout(f"detector {instance} on host {host} did not answer its activity switch "
                             f"within {timeout:g} s") from exc
    except RemoteError as exc:
        raise DeploymentError(f"activity of {instance} on {host}: {exc}") from exc
    except MessageError as exc:
        raise DeploymentError(f"activity of {instance} on {host}: bad reply: {exc}") from exc


class Armed(enum.Enum):
    """What :func:`arm` did."""

    ARMED = "armed"
    NO_TABLE = "no table"  # none from the graph (no answer, a bad row), or no deployment to ask for
    DROPPED = "dropped"  # the detector took another deployment's configuration while its table was asked for
    STOPPED = "stopped"  # the detector was told to stop first: the work left was not done


def arm(detector: Detector, session: Any, *, wait_s: float = 2.0, timeout: float = 2.0,
        stopping: Callable[[], bool] = lambda: False) -> Armed:
    """Give ``detector`` its reflex table from the graph, for the deployment it runs; without one (no
    answer, a bad row) it keeps the one it has, or runs without reflexes: the manager's loop still adapts
    it. ``wait_s`` and ``timeout``: :func:`fetch_reflex_table`'s. Once ``stopping()`` says so, what is
    left (compiling the table, building its detectors) is not done: that work would compete with the
    stop for the interpreter."""
    s = detector.settings
    deployment = detector.deployment
    if deployment is None:
        return Armed.NO_TABLE
    try:
        table = fetch_reflex_table(session, s.robot, deployment=deployment, host=s.host, wait_s=wait_s,
                                   timeout=timeout, stopping=stopping)
    except KgadaptError as exc:
        log.warning("detector %s: no reflex table (%s); the adaptation manager alone changes it", s.instance, exc)
        return Armed.NO_TABLE
    if table is None:
        return Armed.STOPPED
    cores = build_cores(table, stopping=stopping)
    if cores is None:
        return Armed.STOPPED
    return Armed.ARMED if detector.arm(table, cores, deployment=deployment) else Armed.DROPPED


def arm_after_ready(detector: Detector, session: Any, *,
                    stopping: Callable[[], bool] = lambda: False) -> threading.Thread:
    """:func:`arm` ``detector`` on a thread of its own, once it is ready: a start says ready when it detects
    with the configuration it was given, and the reflex table (a question to the graph: the first one on a
    new session waits for the service's declaration, 35 ms of a 63 ms forked start) and its candidates'
    detectors follow, off the frame path. A change asked for meanwhile builds its detector on demand
    (:class:`Reconfigurer`). Its record line says when the candidates were ready. ``stopping``: true
    once the detector is told to stop; the arming then gives way (a stop at ready took 33-49 ms p50
    while the arming's 21 ms of imports and builds ran beside it, 24 ms when stopped 0.3 s later)."""

    def run() -> None:
        started = time.perf_counter()
        deployment = detector.deployment
        try:
            # Patient: nothing waits for it (a question answered late still arms; a start's 2 s would not).
            armed = arm(detector, session, wait_s=10.0, timeout=5.0, stopping=stopping)
        except Exception as exc:  # noqa: BLE001 - whatever a closing session raises: the detector is stopping
            log.debug("detector %s: reflex table not armed: %s", detector.settings.instance, exc)
            return
        ms = (time.perf_counter() - started) * 1e3
        if armed is Armed.ARMED:
            say_line(f"detector {detector.settings.instance}: reflex table of {deployment} armed after ready: "
                     f"{len(detector.candidates())} candidate configurations in {ms:.1f} ms", sys.stderr)
        elif armed is Armed.DROPPED:  # the change's own table (Reconfigurer) is the one to hold
            say_line(f"detector {detector.settings.instance}: reflex table of {deployment} dropped after {ms:.1f} ms: "
                     f"it runs {detector.deployment} now", sys.stderr)

    thread = threading.Thread(target=run, name="detector-arm", daemon=True)
    thread.start()
    return thread


class Reconfigurer:
    """Answers in-place reconfiguration requests for one detector (see the module's docstring).

    Served by one :class:`kgadapt.shared.rpc.Server` worker: it asks the graph, builds
    and swaps, and replies, so nothing blocks inside Zenoh.
    """

    def __init__(self, detector: Detector, *, first_frame_s: float = 2.0) -> None:
        self.detector = detector
        self.first_frame_s = first_frame_s
        instance = detector.settings.instance
        self._server = rpc.Server(f"detector {instance}", workers=1, max_pending=8, prefix=f"detector {instance}: ")
        self._session: Any = None

    def setup(self, session: Any) -> None:
        s = self.detector.settings
        self._session = session
        self._server.setup()
        try:
            self._server.serve(session, keys.detector_configure(s.robot, s.host, s.instance), self._answer,
                               what="reconfigure")
        except BaseException:
            self._server.shutdown()
            raise

    def _answer(self, request: rpc.Request) -> rpc.Reply:
        # A KgadaptError (refused: nothing changed) or a bug is answered with reply_err by the server.
        reply = self.handle(request.payload or b"")
        return rpc.Reply(key=request.key, payload=messages.encode(reply))

    def handle(self, payload: bytes) -> messages.ConfigureReply:
        """Check, build, swap; the reply body. Raises KgadaptError (nothing changed) when refused."""
        from kgadapt.knowledge.client import KnowledgeClient

        d, s = self.detector, self.detector.settings
        name = messages.decode_as(payload, messages.ConfigureRequest).config
        keys.check_name(name, "configuration name")
        previous = d.config.name
        started = time.perf_counter()
        # The reflex table (the graph's in-place rule, fetched at the start and after each change) already
        # holds a built detector for every configuration this one may take here: then the swap asks the
        # graph nothing and builds nothing, so it lands on the next frame. Otherwise ask and build.
        ready = d.prepared(name)
        core = None
        if ready is not None:
            core, target = ready
            config = core.config
        else:
            config, row = fetch_config_row(self._session, s.robot, name, wait_s=1.0)
            target = str(row.get("deployment") or "")
            if not target:
                raise DeploymentError(f"configuration {name!r} has no deployment in the knowledge graph")
            running = d.deployment
            if target != running:
                rows = KnowledgeClient(self._session, s.robot, own=True).query(
                    "in_place_change", {"from": running, "to": target, "host": s.host})
                if not rows:
                    raise DeploymentError(f"the knowledge graph does not let deployment {running} take "
                                          f"{target} ({name}) in place on host {s.host}: start a new detector")
        check_ms = (time.perf_counter() - started) * 1e3
        built = time.perf_counter()
        generation = d.take(config, core, str(target))
        build_ms = (time.perf_counter() - built) * 1e3
        announce_configured(name, str(target))  # the deployer's record follows
        log.info("detector %s: %s -> %s in place", s.instance, previous, name)
        swapped = time.perf_counter()
        first = d.first_frame(generation, self.first_frame_s)
        arm(d, self._session)  # what it may take in place from the new deployment
        return messages.ConfigureReply(
            instance=s.instance, config=name, previous=previous, deployment=str(target),
            check_ms=round(check_ms, 3), build_ms=round(build_ms, 3), first_seq=first,
            first_frame_ms=None if first is None else round((time.perf_counter() - swapped) * 1e3, 3))

    def shutdown(self) -> None:
        self._server.shutdown()


def add_detector_arguments(parser: argparse.ArgumentParser) -> None:
    """The detector's flags (shared by ``python -m kgadapt.onboard.perception.detector`` and ``kgadapt perception detect``)."""
    from kgadapt.shared.agent import DEFAULT_ROBOT
    from kgadapt.shared.session import add_arguments

    parser.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")
    parser.add_argument("--host", required=True, help="name of the host this runs on (reported in detections)")
    parser.add_argument("--instance", required=True, help="instance name: detections go to .../detector/<instance>/markers")
    parser.add_argument("--camera", default="cam0", help="camera whose frames to detect in (default cam0)")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--config", help="detector configuration (PerceptionGraph name) to fetch from the knowledge store")
    which.add_argument("--config-json", metavar="JSON", help="configuration given inline (no store needed)")
    parser.add_argument("--config-wait", type=float, default=10.0, metavar="S",
                        help="how long to wait for the knowledge service to answer (default 10 s)")
    add_arguments(parser)


# Built once in a launcher before it forks (:func:`prefork`): a forked detector parses with it.
_PARSER: argparse.ArgumentParser | None = None


def prefork() -> None:
    """What a launcher (deploy/launcher.py) does once, before it forks detectors, so that no forked start
    does it for the first time: build the argument parser and read a made-up carried configuration
    (:func:`rehearse_carried`). Starts no thread."""
    global _PARSER
    _PARSER = build_parser()
    rehearse_carried()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m kgadapt.onboard.perception.detector",
        description=f"ArUco marker detector: frames in over Zenoh, detections out. Prints {READY_TOKEN} when ready. "
                    "Exit status 2: the knowledge store does not know the configuration.",
    )
    add_detector_arguments(parser)
    parser.add_argument("--log-level", default="WARNING", help="DEBUG, INFO, WARNING (default) or ERROR")
    return parser


def main(argv: Sequence[str] | None = None, *, session: Any = None, adoption: Callable[[], None] | None = None) -> int:
    """``session``: one already open (a launcher's pool member opened it while it waited; closed at the end);
    ``adoption``: the pool member's wait to become its agent's child, called before it says it is ready
    (deploy/launcher.py), so that its own setup runs meanwhile."""
    parser = session.parser if isinstance(session, WarmStart) and session.parser is not None else \
        _PARSER or build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    return run(args, session=session, adoption=adoption)


def _zenoh_settings(args: argparse.Namespace) -> Any:
    """The detector's session: by default a client of the router it connects to, which it talks to alone, as
    in the shipped configurations. A peer's close took about 43 ms in one close in five (Zenoh's, from the
    direct links peers make), and that close is most of a detector's stop; a client's closed in under 5 ms
    (docs/reliability.md)."""
    from kgadapt.shared.session import DEFAULT_ENDPOINT, settings_from_args

    return settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])


def pool_session(argv: Sequence[str]) -> WarmStart:
    """What a launcher's pool member prepares while it waits for a start like ``argv`` (deploy/launcher.py):
    the Zenoh session such a detector would open (a start's own flags name the same settings), and, for
    each deployment it may be started as (``$KGADAPT_POOL_DEPLOYMENTS``, set by its deployer; else the
    one of the configuration its spec carried), the reflex table with every candidate configuration's
    detector built once. A start of another deployment asks the graph for its own table. It keeps the
    parser it parsed ``argv`` with (a start parses with it) and reads a made-up carried configuration
    (:func:`rehearse_carried`), so that the start does neither for the first time in this process."""
    from kgadapt.shared.session import open_session

    parser = build_parser()
    args = parser.parse_args(argv)
    rehearse_carried()
    session = open_session(_zenoh_settings(args))
    deployments = [d for d in os.environ.get(POOL_DEPLOYMENTS_ENV, "").split(",") if d]
    if not deployments:
        carried = carried_config(args.config) if args.config else None
        deployments = [str(carried[1]["deployment"])] if carried and carried[1].get("deployment") else []
    tables: dict[str, Any] = {}
    cores: dict[str, Any] = {}
    for deployment in deployments:
        try:
            table = fetch_reflex_table(session, args.robot, deployment=deployment, host=args.host)
        except KgadaptError as exc:
            log.info("pool member: no reflex table for %s yet (%s)", deployment, exc)
            continue
        tables[deployment] = table
        built = build_cores(table, built=cores)
        assert built is not None  # nothing stops it here
        for name, core in built.items():
            cores.setdefault(name, core)
    warm_up(cores.values())
    frames = LatestSlot()
    try:  # the newest frame, held for the start (a pointer swap per frame in the callback)
        subscriber = session.declare_subscriber(keys.camera_frame(args.robot, args.camera),
                                                lambda sample: frames.put((sample.payload.to_bytes(), time.time())))
    except Exception as exc:  # noqa: BLE001 - whatever zenoh raises: the start declares its own then
        log.info("pool member: no camera subscription held (%s)", exc)
        return WarmStart(session, args.host, tables, cores, parser=parser)
    return WarmStart(session, args.host, tables, cores, camera=(args.robot, args.camera), frames=frames,
                     frame_subscriber=subscriber, parser=parser)


def rehearse_carried() -> None:
    """Read a made-up carried configuration once, so that a pool member's start does not do it for the
    first time in this process: in a fork of the launcher the first touch of a page copies it, and
    msgspec builds its checks for a message type on its first use (with base64, then imported from disk,
    that was the 1.4-6 ms "configuration carried" step of a pooled start; 0.5 ms with it, load 10-20;
    parsing the arguments with a parser built and used while idle: 0.9 -> 0.15 ms)."""
    made_up = messages.ResolvedConfig(config="rehearsal", config_json="{}", resolved_at=0.0, digest="-")
    carried_config("rehearsal", {RESOLVED_CONFIG_ENV: base64.b64encode(messages.encode(made_up)).decode("ascii")})


def warm_up(cores: Any) -> None:
    """Run each of ``cores`` once on a made-up frame with markers, so that a pool member's first real
    frame does not pay the first detection of the process (measured 60-440 ms cold against 15-40 warm on
    a loaded machine, 23 ms quiet); what a failover without a standby waits for."""
    import cv2
    import numpy as np

    frame = np.full((480, 640), 200, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    for i, (x, y) in enumerate([(60, 60), (300, 200), (480, 320)]):
        frame[y:y + 80, x:x + 80] = cv2.aruco.generateImageMarker(dictionary, i, 80)
    for core in cores:
        try:
            core.detect(frame)
        except Exception as exc:  # noqa: BLE001 - a warm-up only: the first real frame reports its own failure
            log.debug("pool member: warm-up detection failed: %s", exc)


def run(args: argparse.Namespace, *, session: Any = None, adoption: Callable[[], None] | None = None) -> int:
    """Run the detector until SIGINT or SIGTERM; return the exit status. ``adoption``: see :func:`main`."""
    from kgadapt.shared.agent import StopSignals
    from kgadapt.shared.session import open_session

    warm = session if isinstance(session, WarmStart) else None
    if warm is not None:
        session = warm.session
    detector: Detector | None = None
    reconfigurer: Reconfigurer | None = None
    switch: ActivitySwitch | None = None
    with StopSignals() as stop:
        try:
            # A standby starts idle: active until the manager's first request, it would publish detections.
            settings = DetectorSettings(robot=args.robot, host=args.host, instance=args.instance, camera=args.camera,
                                        idle=os.environ.get(START_IDLE_ENV) == "1")
            if args.config_json is not None:
                from kgadapt.onboard.perception.markers import parse_config

                config = parse_config(INLINE_CONFIG, args.config_json)
            if session is None:
                session = open_session(_zenoh_settings(args))
            row: dict[str, Any] = {}
            source = "given inline"
            if args.config is not None:
                # Carried by the start request (resolved by the deployer): no second question to the graph.
                carried = carried_config(args.config)
                source = "carried by the start request" if carried is not None else "asked of the knowledge service"
                config, row = carried if carried is not None else fetch_config_row(
                    session, args.robot, args.config, wait_s=args.config_wait)
            detector = Detector(settings, config, deployment=str(row["deployment"]) if row.get("deployment") else None)
            prepared = warm.armed(detector.deployment, settings.host) if warm is not None else None
            if warm is not None and warm.frames is not None and warm.camera == (args.robot, args.camera):
                detector.take_frames(warm.frames, warm.frame_subscriber)  # its newest frame, held
            elif warm is not None and warm.frame_subscriber is not None:
                rpc.undeclare_quietly(warm.frame_subscriber)  # another camera's: the detector declares its own
            if prepared is not None:
                detector.arm(*prepared)  # fetched and built while the pool member waited
            # For the record (the deployer keeps a process's last lines): what this start asked the graph.
            table = ("prepared in the launcher's pool" if prepared is not None else
                     "asked of the knowledge service after ready" if detector.deployment is not None else "none")
            print(f"detector {args.instance}: configuration {config.name} {source}; reflex table {table}",
                  file=sys.stderr, flush=True)
            detector.setup(session)
            switch = ActivitySwitch(detector)
            switch.setup(session)
            if row.get("deployment"):  # only a configuration from the graph can be changed from the graph
                reconfigurer = Reconfigurer(detector)
                reconfigurer.setup(session)
            if adoption is not None:
                adoption()
            announce_ready(instance=args.instance, config=config.name)
            if prepared is None and detector.deployment is not None:
                arm_after_ready(detector, session, stopping=stop.event.is_set)
            log.info("detector %s ready: config %s, camera %s", args.instance, config.name, args.camera)
            stop.wait()
            log.info("detector %s: signal %s, stopping after %d frames", args.instance, stop.received, detector.processed)
            return 0
        except UnknownConfiguration as exc:
            print(f"kgadapt.onboard.perception.detector: error: {exc}", file=sys.stderr, flush=True)
            return EXIT_UNKNOWN_CONFIG
        except KgadaptError as exc:
            print(f"kgadapt.onboard.perception.detector: error: {exc}", file=sys.stderr, flush=True)
            return 1
        finally:
            if reconfigurer is not None:
                reconfigurer.shutdown()
            if switch is not None:
                switch.shutdown()
            if detector is not None:
                detector.shutdown()
            if session is not None:
                try:
                    session.close()
                except Exception as exc:  # noqa: BLE001 - exiting: the session may be closed already
                    log.debug("session close: %s", exc)


if __name__ == "__main__":
    sys.exit(main())
