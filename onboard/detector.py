"""The marker-detector program: ``python -m onboard.detector`` (what the deployer runs).

::

    python -m onboard.detector --robot R --host H --instance I --config NAME --connect ENDPOINT [--camera cam0]
    python -m onboard.detector ... --config-json '{"preprocess": [...], "parameters": {...}}'   # no store

It asks the knowledge service for its configuration (named query
``detector_config``), builds the pre-processing and ``cv2.aruco.ArucoDetector``
of it, subscribes to ``kgadapt/<R>/camera/<cam>/frame`` and publishes
``detections`` on ``kgadapt/<R>/detector/<I>/markers``; then prints
``KGADAPT_READY`` on stdout. SIGINT or SIGTERM stop it cleanly (status 0).

Stale frames are dropped, never queued: the Zenoh callback only puts the
payload into a one-frame slot (replacing an unprocessed one) and a worker
thread takes the newest frame when it is free. Memory stays bounded whatever
the camera's rate.

Exit status: 0 stopped by a signal, 1 an error (message on stderr), 2 the
knowledge store does not know the configuration (the message names it).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Sequence

from shared import keys, messages
from shared.errors import ConfigError, KgadaptError, MessageError, RequestTimeout, TransportError

log = logging.getLogger("onboard.detector")

READY_LINE = "KGADAPT_READY"
EXIT_UNKNOWN_CONFIG = 2
INLINE_CONFIG = "inline"


class UnknownConfiguration(KgadaptError):
    """The knowledge store has no detector configuration of that name."""


class LatestSlot:
    """Holds the newest item only: ``put`` replaces (and counts) an unprocessed one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.replaced = 0

    def put(self, item: Any) -> None:
        with self._cond:  # held for a pointer swap only: fine in a Zenoh callback
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float | None = None) -> Any:
        """The newest item, waiting up to ``timeout``; None on timeout or close."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
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

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        keys.check_name(self.host, "host name")
        keys.check_name(self.instance, "instance name")
        keys.check_name(self.camera, "camera name")


def fetch_config(session: Any, robot: str, name: str, *, wait_s: float = 10.0) -> Any:
    """The configuration ``name`` from the knowledge service, as a checked DetectorConfig.

    Retries while nothing answers (the service may be starting) for up to
    ``wait_s``; raises UnknownConfiguration when the store has no such
    configuration, RequestTimeout when no service answered in time.
    """
    from knowledge.client import KnowledgeClient
    from onboard.markers import parse_config

    keys.check_name(name, "configuration name")
    client = KnowledgeClient(session, robot, own=True)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            rows = client.query("detector_config", {"config": name})
            break
        except RequestTimeout:
            if time.monotonic() >= deadline:
                raise RequestTimeout(
                    f"no knowledge service of robot {robot!r} answered for detector configuration {name!r} "
                    f"within {wait_s:.0f} s"
                ) from None
            time.sleep(0.2)  # the service is not up yet; ask again
    if not rows:
        raise UnknownConfiguration(f"detector configuration {name!r} is not in the knowledge store")
    row = rows[0]
    if row.get("config_json") is None:
        raise ConfigError(f"detector configuration {name!r} has no config_json in the knowledge store")
    return parse_config(name, row["config_json"], dictionary=row.get("dictionary"))


class Detector:
    """Subscribes to frames, detects markers on a worker thread, publishes detections."""

    def __init__(self, settings: DetectorSettings, config: Any) -> None:
        from onboard.markers import MarkerDetector

        self.settings = settings
        self.config = config
        self.core = MarkerDetector(config)
        self.slot = LatestSlot()
        self.processed = 0
        self.malformed = 0
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._subscriber: Any = None
        self._publisher: Any = None
        self._token: Any = None

    def setup(self, session: Any) -> None:
        import zenoh

        s = self.settings
        try:
            self._publisher = session.declare_publisher(
                keys.detector_markers(s.robot, s.instance), congestion_control=zenoh.CongestionControl.DROP,
            )
            self._worker = threading.Thread(target=self._work, name="detector-worker", daemon=True)
            self._worker.start()
            self._subscriber = session.declare_subscriber(keys.camera_frame(s.robot, s.camera), self._on_frame)
            self._token = session.liveliness().declare_token(keys.detector_alive(s.robot, s.instance))
        except Exception as exc:
            self.shutdown()
            raise TransportError(f"detector {s.instance}: cannot declare on Zenoh: {exc}") from exc

    def _on_frame(self, sample: Any) -> None:
        # Zenoh callback: copy the payload and the arrival time, nothing else.
        self.slot.put((sample.payload.to_bytes(), time.time()))

    def _work(self) -> None:
        while not self._stop.is_set():
            item = self.slot.take(timeout=0.5)
            if item is None:
                continue
            try:
                self._process(*item)
            except MessageError as exc:
                self.malformed += 1
                log.warning("detector %s: dropped a frame: %s", self.settings.instance, exc)
            except Exception:  # keep detecting: one bad frame is not a reason to stop
                self.malformed += 1
                log.exception("detector %s: frame failed", self.settings.instance)

    def _process(self, payload: bytes, received: float) -> None:
        import cv2
        import numpy as np

        frame = messages.decode(payload, "frame")
        start = time.perf_counter()
        gray = cv2.imdecode(np.frombuffer(frame["jpeg"], np.uint8), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            raise MessageError(f"frame {frame['seq']} of camera {frame['camera']}: JPEG does not decode")
        decode_ms = (time.perf_counter() - start) * 1e3
        result = self.core.detect(gray)
        s = self.settings
        body = {
            "instance": s.instance, "config": self.config.name, "host": s.host, "seq": frame["seq"],
            "frame_time": frame["time"], "time": time.time(),
            "ids": result.ids, "corners": result.corners, "processing_ms": round(result.processing_ms, 3),
            "camera": frame["camera"], "received": received, "decode_ms": round(decode_ms, 3),
            "dropped": self.slot.replaced, "clean": result.clean,
        }
        if isinstance(frame.get("sent"), (int, float)):
            body["frame_sent"] = frame["sent"]
        self._publisher.put(messages.encode("detections", body))
        self.processed += 1

    def shutdown(self) -> None:
        for name in ("_token", "_subscriber"):
            thing = getattr(self, name)
            if thing is not None:
                try:
                    thing.undeclare()
                except Exception as exc:
                    log.debug("undeclare %s: %s", name, exc)
                setattr(self, name, None)
        self._stop.set()
        self.slot.close()
        if self._worker is not None:
            self._worker.join(timeout=5)
            self._worker = None
        if self._publisher is not None:
            try:
                self._publisher.undeclare()
            except Exception as exc:
                log.debug("undeclare publisher: %s", exc)
            self._publisher = None


def add_detector_arguments(parser: argparse.ArgumentParser) -> None:
    """The detector's flags (shared by ``python -m onboard.detector`` and ``kgadapt perception detect``)."""
    from shared.agent import DEFAULT_ROBOT
    from shared.session import add_arguments

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m onboard.detector",
        description="ArUco marker detector: frames in over Zenoh, detections out. Prints KGADAPT_READY when ready. "
                    "Exit status 2: the knowledge store does not know the configuration.",
    )
    add_detector_arguments(parser)
    parser.add_argument("--log-level", default="WARNING", help="DEBUG, INFO, WARNING (default) or ERROR")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    return run(args)


def run(args: argparse.Namespace) -> int:
    """Run the detector until SIGINT or SIGTERM; return the exit status."""
    from shared.agent import StopSignals
    from shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

    session = None
    detector: Detector | None = None
    with StopSignals() as stop:
        try:
            settings = DetectorSettings(robot=args.robot, host=args.host, instance=args.instance, camera=args.camera)
            if args.config_json is not None:
                from onboard.markers import parse_config

                config = parse_config(INLINE_CONFIG, args.config_json)
            zenoh_settings = settings_from_args(args).with_defaults(mode="peer", connect=[DEFAULT_ENDPOINT])
            session = open_session(zenoh_settings)
            if args.config is not None:
                config = fetch_config(session, args.robot, args.config, wait_s=args.config_wait)
            detector = Detector(settings, config)
            detector.setup(session)
            print(READY_LINE, flush=True)
            log.info("detector %s ready: config %s, camera %s", args.instance, config.name, args.camera)
            stop.wait()
            log.info("detector %s: signal %s, stopping after %d frames", args.instance, stop.received, detector.processed)
            return 0
        except UnknownConfiguration as exc:
            print(f"onboard.detector: error: {exc}", file=sys.stderr, flush=True)
            return EXIT_UNKNOWN_CONFIG
        except KgadaptError as exc:
            print(f"onboard.detector: error: {exc}", file=sys.stderr, flush=True)
            return 1
        finally:
            if detector is not None:
                detector.shutdown()
            if session is not None:
                try:
                    session.close()
                except Exception as exc:
                    log.debug("session close: %s", exc)


if __name__ == "__main__":
    sys.exit(main())
