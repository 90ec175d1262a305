"""``kgadapt bench starvation``: the robot's own knowledge path while other robots ask hostile questions.

The whole robot in real processes (kgadapt/operator/cluster.py). The robot's own
software asks ``placement`` on its own door (``knowledge/own/query``) every
50 ms, first for a quiet baseline, then while four outsiders (tests/security/
outsider.py, written from CONTRACTS.md) ask in parallel, without pause: heavy
cartesian Cypher, the paper's literal queries, nested literals, CALL and
LOAD CSV bypasses and a flood of cheap named queries. During the attack the
light goes dark, and the dark detector must still take over.

Results to ``bench/results/starvation.json``. Targets (issue 13): own
``placement`` p99 <= 50 ms and 0 unanswered under attack; the light change
still migrates. ``--attack literal``: the attackers ask only the paper's
literal queries (``fig4_literal``, 1,000 rows of deployments, and
``fig5_literal``) without pause; results to
``bench/results/starvation_literal.json``, target (issue 33): own
``placement`` p90 <= 3x its quiet p90 and <= 25 ms, 0 unanswered.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from kgadapt.bench.stats import format_table, machine_info, make_record, write_records
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.resources import results_dir
from kgadapt.shared.states import TriggerKind

RESULTS = results_dir() / "starvation.json"
LITERAL_RESULTS = results_dir() / "starvation_literal.json"
DARK = "marker_detection_dark"
HEAVY = "MATCH (a), (b), (c), (d), (e) RETURN count(*) AS n"


def register(bench_subparsers: Any) -> None:
    p = bench_subparsers.add_parser(
        "starvation", help="own placement latency while four outsiders ask hostile questions (real processes)",
        description=__doc__.split("\n\n")[1])
    p.add_argument("--seconds", type=float, default=60.0, help="attack duration (default 60)")
    p.add_argument("--baseline", type=float, default=15.0, help="quiet seconds measured first (default 15)")
    p.add_argument("--attackers", type=int, default=4, help="parallel hostile askers (default 4)")
    p.add_argument("--attack", choices=("mixed", "literal"), default="mixed",
                   help="mixed hostile questions (default), or only the paper's literal queries")
    p.add_argument("--out", default=None, help=f"results file (default {RESULTS}, {LITERAL_RESULTS} for literal)")
    p.add_argument("--json", action="store_true", help="print the records as JSON")
    p.set_defaults(func=run)


def _attacks(port: int) -> dict[str, Callable[[Any], Any]]:
    return {
        "heavy": lambda o: o.cypher(HEAVY),
        "literal": lambda o: o.query("fig5_literal"),
        "literal4": lambda o: o.query("fig4_literal", {"platform": "onboard"}),
        "nested": lambda o: o.cypher("RETURN " + "[" * 22 + "]" * 22 + " AS v"),
        "bypass": lambda o: o.cypher("WITH {as: 1} AS x ORDER BY x.as CALL db.labels() YIELD label RETURN label"),
        "load_csv": lambda o: o.cypher(f"LOAD CSV FROM 'http://127.0.0.1:{port}/x' AS r RETURN r"),
        "flood": lambda o: o.query("placement", {"config": DARK}),
    }


def _probe(client: Any, seconds: float) -> tuple[list[float], int]:
    """Own placement every 50 ms for ``seconds``: (latencies ms, unanswered)."""
    from kgadapt.shared.errors import KgadaptError

    latencies, unanswered = [], 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        try:
            client.query("placement", {"config": DARK})
        except KgadaptError:
            unanswered += 1
        else:
            latencies.append((time.perf_counter() - t0) * 1000.0)
        time.sleep(0.05)
    return latencies, unanswered


def _p90(samples: list[float]) -> float:
    if not samples:
        return float("nan")
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))]


def run(args: argparse.Namespace) -> int:
    import socket

    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.operator.cluster import ClusterSettings, WatchedRobot, write_profile
    from kgadapt.shared.session import ZenohSettings, open_session
    from tests.security.outsider import Outsider

    workdir = Path(tempfile.mkdtemp(prefix="kgadapt-bench-starvation-"))
    started = time.time()
    dark_at = args.baseline + 5.0 + args.seconds / 2  # mid-attack, seconds after the robot's start
    profile = write_profile(workdir / "profile.json", [[0, 120], [dark_at, 120], [dark_at + 0.3, 5], [3600, 5]])
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    listener.settimeout(0.2)
    connections = []
    answers: dict[str, list[Any]] = {}
    try:
        with WatchedRobot(ClusterSettings(workdir=workdir / "run", profile=profile, calibrate=False, fake_fc=False,
                                          log_level="WARNING")) as robot:
            robot.wait(lambda: robot.recorder.decisions, 30)
            own = KnowledgeClient(robot.session, DEFAULT_ROBOT, timeout=2.0, own=True)
            quiet, quiet_lost = _probe(own, args.baseline)
            quiet_load = os.getloadavg()[0]
            attacks = _attacks(listener.getsockname()[1])
            answers = {name: [] for name in attacks}
            stop = threading.Event()
            sessions = [open_session(ZenohSettings(mode="client", connect=(robot.cluster.endpoint,)))
                        for _ in range(args.attackers)]

            def attacker(i: int) -> None:
                outsider = Outsider(sessions[i], DEFAULT_ROBOT)
                names = (["literal4", "literal"] if args.attack == "literal" else
                         ["heavy", "literal", "nested", "heavy", "bypass", "literal4", "heavy", "load_csv", "flood"])
                k = i * 2
                while not stop.is_set():
                    name = names[k % len(names)]
                    answers[name].append(attacks[name](outsider))
                    k += 1

            def accept() -> None:
                while not stop.is_set():
                    try:
                        connections.append(listener.accept()[0])
                    except OSError:
                        continue

            threads = [threading.Thread(target=attacker, args=(i,), daemon=True) for i in range(args.attackers)]
            threads.append(threading.Thread(target=accept, daemon=True))
            attack_started = time.time()
            for t in threads:
                t.start()
            loud, loud_lost = _probe(own, args.seconds)
            stop.set()
            for t in threads:
                t.join(timeout=15)
            for s in sessions:
                s.close()
            migrated = [d for d in robot.recorder.decisions if d.kind == TriggerKind.BAND_CHANGED and d.time >= attack_started]
    finally:
        listener.close()
        shutil.rmtree(workdir, ignore_errors=True)
    store = "embedded (FalkorDB, fsync always)"
    counts = {name: len(a) for name, a in answers.items()}
    killed = sum(1 for a in answers.get("heavy", []) + answers.get("literal4", []) if "hard time limit" in a.error)
    literal = args.attack == "literal"
    records = [
        make_record(store=store, n=None, op="own_placement_quiet", samples_ms=quiet, unanswered=quiet_lost,
                    p90_ms=round(_p90(quiet), 4), load_average=quiet_load),
        make_record(store=store, n=None, op="own_placement_under_literal_flood" if literal else "own_placement_under_attack",
                    samples_ms=loud, unanswered=loud_lost, p90_ms=round(_p90(loud), 4),
                    target=("p90 <= 3x quiet p90 and <= 25 ms, 0 unanswered" if literal
                            else "p99 <= 50 ms, 0 unanswered"), attackers=args.attackers, attack_s=args.seconds,
                    attack_answers=counts, stopped_at_time_limit=killed, load_csv_connections=len(connections),
                    light_change_during_attack=[f"{d.config}@{d.host}: {d.outcome}" for d in migrated],
                    load_average=os.getloadavg()[0]),
    ]
    for r in records:
        r.update(machine_info(), measured_at=time.strftime("%Y-%m-%d %H:%M", time.gmtime(started)))
    out = args.out or str(LITERAL_RESULTS if literal else RESULTS)
    write_records(out, records)
    if args.json:
        print(json.dumps(records, indent=1))
    else:
        rows = [[r["op"], r["reps"], r["p50_ms"], r["p90_ms"], r["p99_ms"], r["max_ms"], r["unanswered"],
                 r["load_average"]] for r in records]
        print(format_table(rows, ["own placement", "n", "p50", "p90", "p99", "max", "unanswered", "load"]))
        print(f"attack answers {counts}; heavy questions stopped at their limit: {killed}; "
              f"LOAD CSV connections: {len(connections)}; light change during the attack: "
              f"{[f'{d.config}@{d.host}: {d.outcome}' for d in migrated] or 'none'}")
        print(f"wrote {out}")
    return 0
