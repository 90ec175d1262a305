"""``kgadapt demo``: the adaptation scenario end to end, or (``--queries``) the paper's queries.

The scenario (the default, what ``make demo`` runs) is in :func:`run_scenario`:
on one machine and the embedded store, the knowledge service, a remote agent,
the onboard agent with the synthetic camera (day, dusk, dark, flicker, day)
and a fake flight controller, plus a scripted memory squeeze on the onboard
host. It prints a live timeline and ends with a summary table and a PNG.

``--queries`` loads ``knowledge/models`` into an embedded store of its own (``./var/demo-store``,
emptied first, so it never touches the user's store), writes the run-time
facts an agent would write (live platform figures with the onboard computer's
memory squeezed, a past detector run, a calibration), and prints the answers
to the paper's queries as tables, each with its latency.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

DEMO_STORE = "embedded:var/demo-store"

# (title, query name, parameters)
QUESTIONS: list[tuple[str, str, dict[str, Any]]] = [
    ("Fig. 4: deployments for MarkerDetection executable on the remote host",
     "feature_deployments", {"feature": "MarkerDetection", "platform": "remote"}),
    ("Fig. 5 / placement: where each detector configuration fits in free memory now",
     "placement", {"feature": "MarkerDetection"}),
    ("Fig. 5 as the paper wrote it (unbounded <-[*]->): sums every component reachable, flight control included",
     "fig5_literal", {"feature": "MarkerDetection"}),
    ("Components for MarkerDetection that are also deployable on the remote host",
     "deployable_components", {"feature": "MarkerDetection", "platform": "remote"}),
    ("Can MarkerDetection be realised with cameras of different resolutions? (one row per resolution)",
     "camera_resolutions", {"feature": "MarkerDetection"}),
    ("Components that ran before with an average memory usage below 100 MiB",
     "low_memory_components", {"feature": "MarkerDetection", "threshold_mb": 100.0}),
    ("Would the CPU load exceed 80 % of the onboard computer with detector and flight control together?",
     "cpu_overload", {"platform": "onboard", "limit_pct": 80.0}),
    ("Detector configurations and the illumination bands they are for",
     "detector_configs", {"feature": "MarkerDetection"}),
]


def register(subparsers: Any) -> None:
    """Add ``kgadapt demo``."""
    parser = subparsers.add_parser(
        "demo", help="run the adaptation scenario (or, with --queries, answer the paper's queries)",
        description="Run the robot on this machine through day, dusk, dark, flicker and day with a memory "
                    "squeeze, printing what changed, what was decided and how long it took; ends with a "
                    "summary table and a PNG timeline (var/demo/timeline.png). With --queries: load "
                    "knowledge/models into a demo store and print the answers to the paper's queries.")
    parser.add_argument("--queries", action="store_true", help="only answer the paper's queries (a few seconds)")
    parser.add_argument("--store", metavar="URL", default=DEMO_STORE,
                        help=f"--queries: store to use (default {DEMO_STORE}); it is emptied first")
    parser.add_argument("--models", metavar="DIR", default=None, help="model directory (default: the shipped models)")
    parser.add_argument("--workdir", default="var/demo", help="scenario: logs, store and plots (default var/demo)")
    parser.add_argument("--duration", type=float, default=62.0, metavar="S", help="scenario length (default 62)")
    parser.add_argument("--speed", type=float, default=1.0, help="scenario seconds per second (default 1)")
    parser.add_argument("--squeeze", default="350M", metavar="SIZE",
                        help="memory reserved on the onboard host in the dark phase (default 350M)")
    parser.add_argument("--json", action="store_true", help="scenario: print the summary as JSON at the end")
    parser.set_defaults(func=run)


def _facts(store: Any) -> list[str]:
    """What the agents would have written by now; returns a line per fact, for the reader."""
    from kgadapt.knowledge import runtime as R

    now = time.time()
    R.update_platform(store, name="onboard", time=now, memory_total_mb=1024.0, memory_free_mb=220.0,
                      cpu_load=95.0, cpu_cores=4, online=True)
    R.update_platform(store, name="remote", time=now, memory_total_mb=8192.0, memory_free_mb=3100.0,
                      cpu_load=240.0, cpu_cores=8, online=True)
    R.record_process_start(store, run_id="demo-run-1", instance="detector-1", deployment="detector_day",
                           config="marker_detection_day", host="onboard", pid=4242, start_time=now - 600)
    R.record_process_sample(store, run_id="demo-run-1", rss_mb_last=51.0, rss_mb_mean=49.5, rss_mb_max=53.0,
                            cpu_percent_mean=41.0)
    R.record_process_end(store, run_id="demo-run-1", end_time=now - 300, exit_status=0)
    R.record_process_start(store, run_id="demo-run-2", instance="detector-2", deployment="detector_dusk",
                           config="marker_detection_dusk", host="remote", pid=5151, start_time=now - 300)
    R.record_process_sample(store, run_id="demo-run-2", rss_mb_last=118.0, rss_mb_mean=112.0, rss_mb_max=121.0,
                            cpu_percent_mean=88.0)
    R.record_calibration(store, config="marker_detection_day", band="day", detection_rate=1.0, false_rate=0.0,
                         ms_per_frame=3.8, time=now)
    return [
        "onboard: online, 220 of 1024 MiB free (squeezed), CPU 95 % of one core",
        "remote:  online, 3100 of 8192 MiB free, CPU 240 % of one core",
        "a past run of detector_day onboard (49.5 MiB on average), detector_dusk running on remote (112 MiB)",
        "calibration: marker_detection_day detects 100 % of markers in daylight at 3.8 ms per frame",
    ]


def run(args: argparse.Namespace) -> int:
    if args.queries:
        return run_queries(args)
    from kgadapt.operator.demo_scenario import run_scenario

    return run_scenario(args)


def run_queries(args: argparse.Namespace) -> int:
    from kgadapt.knowledge.loader import load_models
    from kgadapt.knowledge.queries import run_named
    from kgadapt.knowledge.store import open_store, rows_as_table
    from kgadapt.shared.resources import models

    folder = args.models or str(models())
    started = time.perf_counter()
    with open_store(args.store) as store:
        store.clear()
        t0 = time.perf_counter()
        report = load_models(store, [folder])
        load_ms = (time.perf_counter() - t0) * 1000
        nodes = sum(report.as_dict()["labels"].get(label, 0) for label in
                    ("Feature", "IlluminationBand", "PerceptionGraph", "Component", "Port", "Deployment", "Platform"))
        print(f"Loaded {len(report.files)} model files from {folder}: {nodes} nodes, "
              f"{sum(report.relations.values())} relations in {load_ms:.0f} ms (store {store.url}).")
        print("\nRun-time facts, as the agents would write them:")
        for line in _facts(store):
            print(f"  - {line}")
        for title, name, params in QUESTIONS:
            t0 = time.perf_counter()
            rows = run_named(store, name, params)
            ms = (time.perf_counter() - t0) * 1000
            shown = ", ".join(f"{k}={v}" for k, v in params.items())
            print(f"\n{title}\n  query {name}({shown})  {len(rows)} rows in {ms:.1f} ms")
            if name == "fig5_literal":
                rows = [{"platform": r["p"].get("name"), "memory_free_mb": r["p"].get("memory_free_mb")}
                        for r in rows]
            print("  " + rows_as_table(rows).replace("\n", "\n  "))
    print(f"\nDone in {time.perf_counter() - started:.1f} s. Try: kgadapt knowledge queries; "
          f"kgadapt knowledge query placement --store {args.store}")
    return 0
