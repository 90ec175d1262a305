"""``kgadapt bench store-layer``: what the project's store API adds to one call, part by part.

On one embedded FalkorDB (fsync on every write, as the robot runs it) holding
Table I's N detector models (``--n``, default 10,000), each repetition times,
in a shuffled order so that all see the same machine at the same moment:

``query_bare``        the placement statement sent with the falkordb client's own ``ro_query``
``query_execute``     the same through ``GraphStore.execute(read_only=True)``
``query_named``       the same through ``queries.run_named`` (the named query's parameter check too)
``insert_bare``       ``record_process_start``'s statement for a new profile, falkordb client
``insert``            ``runtime.record_process_start`` (its checks, then ``GraphStore.execute``)

and then, alone and without the store, each part the layer does per call:
the named query's parameter check, the graph-value check (``params.check_params``),
FalkorDB's parameter header, the read-only guard as it was (tokenizing the
text every call) and as it is (its verdict kept per statement text), the
row conversion, and the writer's own checks (``record_process_start`` less the
store call). The retry and LOADING paths cost nothing until the store answers
LOADING or drops the connection (a ``try`` around the call).

Records go to ``bench/results/store_layer.json``.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from kgadapt.bench.stats import gc_paused, machine_info, make_record, time_once, write_json
from kgadapt.shared.resources import results_dir

DEFAULT_OUT = results_dir() / "store_layer.json"
TARGET_RATIO = 1.25


class _NoStore:
    """Stands for the store when timing a writer's own checks: what it is asked is not run."""

    def execute(self, cypher: str, params: Any = None, **_: Any) -> list[dict[str, Any]]:
        return [{"created": 1}]


def run(args: argparse.Namespace) -> int:
    from falkordb import FalkorDB

    from kgadapt.bench import table1 as T
    from kgadapt.knowledge import queries, runtime
    from kgadapt.knowledge import schema as S
    from kgadapt.knowledge.cypher_guard import writing_clause
    from kgadapt.knowledge.embedded import EmbeddedServer
    from kgadapt.knowledge.falkordb_store import FalkorDBStore, _plain, params_header
    from kgadapt.knowledge.params import check_params
    from kgadapt.knowledge.store import assert_read_only, parse_store_url

    load_before = os.getloadavg()
    rng = random.Random(args.seed)
    records: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="kgadapt-store-layer-") as tmp:
        server = EmbeddedServer(Path(tmp), fsync_always=True)
        store = FalkorDBStore(parse_store_url(f"embedded:{tmp}"), server=server)
        store.setup()
        try:
            store.clear()
            S.ensure_indexes(store)
            T.load_models(store, args.n, batch=1000, seed=args.seed)
            bare = FalkorDB(unix_socket_path=server.ensure().unix_socket).select_graph(store.settings.graph)
            placement = T.find_sources().placement

            def params(model: int) -> dict[str, Any]:
                return {"feature": T.FEATURE, "config": T.config_name(model)}

            def profile(rep: int, model: int, kind: str) -> dict[str, Any]:
                return {"run_id": f"layer-{kind}-{rep}", "instance": f"detector-{rep}",
                        "deployment": T.deployment_name(model), "config": T.config_name(model),
                        "host": "remote" if rep % 2 else "onboard", "pid": 10_000 + rep, "start_time": time.time()}

            ops: dict[str, Callable[[int, int], Any]] = {
                "query_bare": lambda rep, model: bare.ro_query(placement, params(model)).result_set,
                "query_execute": lambda rep, model: store.execute(placement, params(model), read_only=True),
                "query_named": lambda rep, model: queries.run_named(store, "placement", params(model)),
                "insert_bare": lambda rep, model: bare.query(runtime.START_NEW_PROFILE, profile(rep, model, "bare")),
                "insert": lambda rep, model: runtime.record_process_start(store, **profile(rep, model, "api")),
            }
            for w in range(args.warmup):
                for fn in ops.values():
                    fn(-1 - w, rng.randrange(args.n))
            samples: dict[str, list[float]] = {op: [] for op in ops}
            plan = list(ops.items())
            with gc_paused():
                for rep in range(args.reps):
                    model = rng.randrange(args.n)
                    rng.shuffle(plan)
                    for op, fn in plan:
                        samples[op].append(time_once(lambda: fn(rep, model)))
            for op, values in samples.items():
                records.append(make_record(store="embedded", n=args.n, op=op, samples_ms=values))
            # The parts, each alone (no store round trip), in microseconds.
            model_params = params(7)
            result = bare.ro_query(placement, model_params)
            columns = [name for _, name in result.header]
            no_store: Any = _NoStore()
            parts: dict[str, Callable[[], Any]] = {
                "named query parameter check (queries.check_params)": lambda: queries.check_params(
                    "placement", model_params),
                "graph-value check (params.check_params)": lambda: check_params(model_params),
                "FalkorDB parameter header (params_header)": lambda: params_header(model_params),
                "read-only guard, tokenized every call (before)": lambda: writing_clause(placement),
                "read-only guard, verdict kept per text (now)": lambda: assert_read_only(placement),
                "row conversion (_plain)": lambda: [{c: _plain(v) for c, v in zip(columns, row)}
                                                    for row in result.result_set],
                "writer checks (record_process_start without the store)": lambda: runtime.record_process_start(
                    no_store, **profile(0, 7, "checks")),
            }
            part_us = {}
            for name, fn in parts.items():
                for _ in range(50):
                    fn()
                values = [time_once(fn) * 1000 for _ in range(args.reps * 5)]
                part_us[name] = round(statistics.median(values), 2)
        finally:
            store.shutdown()
    p50 = {r["op"]: r["p50_ms"] for r in records}
    ratios = {"query_named/query_bare": round(p50["query_named"] / p50["query_bare"], 3),
              "query_execute/query_bare": round(p50["query_execute"] / p50["query_bare"], 3),
              "insert/insert_bare": round(p50["insert"] / p50["insert_bare"], 3)}
    write_json(args.out, {"machine": {**machine_info(), "load_avg_1_5_15_before": load_before,
                                      "load_avg_1_5_15_after": os.getloadavg()},
                          "settings": {"n": args.n, "reps": args.reps, "warmup": args.warmup, "seed": args.seed},
                          "records": records, "parts_us_p50": part_us, "ratios_p50": ratios,
                          "target_ratio": TARGET_RATIO})
    for r in records:
        print(f"{r['op']:15s} p50 {r['p50_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms")
    for name, us in part_us.items():
        print(f"  {name}: {us} us")
    for name, ratio in ratios.items():
        print(f"{name} = {ratio} (target <= {TARGET_RATIO}: {'met' if ratio <= TARGET_RATIO else 'NOT MET'})")
    print(f"load average before {load_before[0]:.2f}, after {os.getloadavg()[0]:.2f}")
    print(f"results: {args.out}")
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    """Add ``kgadapt bench store-layer``."""
    p = bench_sub.add_parser("store-layer", help="what the store API adds per call, part by part (issue 32)",
                             description=__doc__.split("\n\n")[1] if __doc__ else None)
    p.add_argument("--n", type=int, default=10_000, help="detector models in the graph (default 10,000)")
    p.add_argument("--reps", type=int, default=200, help="timed repetitions per op (default 200)")
    p.add_argument("--warmup", type=int, default=20, help="untimed repetitions first (default 20)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"result file (default {DEFAULT_OUT})")
    p.set_defaults(func=run)
