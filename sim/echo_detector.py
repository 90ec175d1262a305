"""A stand-in detector: answers every camera frame with an empty ``detections`` message.

It speaks the detector's contract (docs/CONTRACTS.md) without OpenCV or a
detector configuration: same arguments, its readiness line once subscribed,
``detections`` on ``kgadapt/<robot>/detector/<instance>/markers`` carrying the
frame's sequence number. Use it to try a deployment, a migration or a Zenoh
configuration on real hosts before the camera and the models are in place,
and in the deployer's tests and benchmark::

    python -m kgadapt.sim.echo_detector --robot quad1 --host remote --instance echo1 \\
        --config marker_detection_day --connect tcp/127.0.0.1:7447

``--tick HZ`` publishes on its own clock when no camera runs.
"""

from __future__ import annotations

import argparse
import queue
import signal
import sys
import time


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kgadapt.sim.echo_detector", description=__doc__.splitlines()[0])
    parser.add_argument("--robot", required=True)
    parser.add_argument("--host", required=True)
    parser.add_argument("--instance", required=True)
    parser.add_argument("--config", required=True)
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint (repeatable)")
    parser.add_argument("--camera", default="*", help="camera name (default: every camera)")
    parser.add_argument("--tick", type=float, default=0.0, metavar="HZ", help="publish on a clock instead of frames")
    args = parser.parse_args(argv)
    # A signal raises Stopped in the main thread, which interrupts its blocking wait at once --
    # if the kernel delivers the signal to the main thread. A process-directed signal goes to
    # any thread that does not block it, Zenoh's included, and then the main thread would
    # sleep on. So block them before Zenoh starts its threads (which inherit the mask) and
    # unblock them in the main thread only.
    stop_signals = {signal.SIGINT, signal.SIGTERM}
    for sig in stop_signals:
        signal.signal(sig, _raise_stopped)
    signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
    try:
        return _serve(args, lambda: signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals))
    except Stopped:
        return 0


class Stopped(Exception):
    """SIGINT or SIGTERM arrived."""


def _raise_stopped(*_: object) -> None:
    raise Stopped()


def _serve(args: argparse.Namespace, unblock_signals) -> int:
    from kgadapt.shared import keys, messages
    from kgadapt.shared.errors import KgadaptError
    from kgadapt.shared.readiness import announce_ready
    from kgadapt.shared.session import open_session, settings_from_env

    try:
        # Mode and TLS come from $KGADAPT_ZENOH_MODE / _CONFIG when the deployer passes them on.
        session = open_session(settings_from_env(connect=tuple(args.connect)).with_defaults(mode="peer"))
    except KgadaptError as exc:
        print(f"echo detector {args.instance}: {exc}", file=sys.stderr)
        return 1
    finally:
        unblock_signals()
    frames: queue.Queue = queue.Queue(maxsize=64)
    try:
        publisher = session.declare_publisher(keys.detector_markers(args.robot, args.instance))
        _token = session.liveliness().declare_token(keys.detector_alive(args.robot, args.instance))  # held while we run
        if args.tick <= 0:
            # The callback only queues: no Zenoh call inside it.
            def on_frame(sample) -> None:
                try:
                    frames.put_nowait((sample.payload.to_bytes(), time.time()))
                except queue.Full:
                    pass

            _subscriber = session.declare_subscriber(keys.camera_frame(args.robot, args.camera), on_frame)  # held
        announce_ready(instance=args.instance)
        seq = 0
        while True:
            if args.tick > 0:
                time.sleep(1.0 / args.tick)
                seq += 1
                frame_time = received = time.time()
            else:
                payload, received = frames.get()
                try:
                    frame = messages.decode(payload, "frame")
                except KgadaptError as exc:
                    print(f"dropped a malformed frame: {exc}", file=sys.stderr, flush=True)
                    continue
                seq, frame_time = frame["seq"], frame["time"]
            publisher.put(messages.encode("detections", {
                "instance": args.instance, "config": args.config, "host": args.host, "seq": seq,
                "frame_time": frame_time, "time": time.time(), "ids": [], "corners": [],
                "processing_ms": (time.time() - received) * 1000.0,
            }))
    finally:
        session.close()  # undeclares the subscriber, token and publisher


if __name__ == "__main__":
    sys.exit(main())
