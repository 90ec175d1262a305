"""Timing helpers shared by every benchmark: samples, summaries, records, tables.

A benchmark times one operation many times with :func:`time_calls` (or
collects its own samples in milliseconds), turns the samples into a record
with :func:`make_record`, and writes the records with :func:`write_records`.
Records are flat dicts so that any bench's JSON reads the same way::

    {"store": ..., "n": ..., "op": ..., "mean_ms": ..., "sd_ms": ...,
     "p50_ms": ..., "p99_ms": ..., "reps": ..., ...extra fields}
"""

from __future__ import annotations

import gc
import json
import math
import os
import platform
import statistics
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

from kgadapt.shared.errors import ConfigError

RECORD_KEYS = ("store", "n", "op", "mean_ms", "sd_ms", "p50_ms", "p99_ms")


@dataclass(frozen=True, kw_only=True)
class Summary:
    """Mean, sample standard deviation and percentiles of timings in ms."""

    count: int
    mean_ms: float
    sd_ms: float
    p50_ms: float
    p99_ms: float
    min_ms: float
    max_ms: float


def percentile(samples: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0..100) with linear interpolation between ranks."""
    if not samples:
        raise ValueError("percentile of no samples")
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile {q} is outside 0..100")
    ordered = sorted(samples)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def summarize(samples_ms: Sequence[float]) -> Summary:
    """Summarize timings (ms). One sample has a standard deviation of 0."""
    if not samples_ms:
        raise ValueError("no samples to summarize")
    return Summary(
        count=len(samples_ms),
        mean_ms=statistics.fmean(samples_ms),
        sd_ms=statistics.stdev(samples_ms) if len(samples_ms) > 1 else 0.0,
        p50_ms=percentile(samples_ms, 50),
        p99_ms=percentile(samples_ms, 99),
        min_ms=min(samples_ms),
        max_ms=max(samples_ms),
    )


def time_once(fn: Callable[[], Any]) -> float:
    """Milliseconds one call of ``fn`` took (monotonic clock)."""
    start = time.perf_counter_ns()
    fn()
    return (time.perf_counter_ns() - start) / 1e6


def time_calls(fn: Callable[[], Any], reps: int, *, warmup: int = 3) -> list[float]:
    """Call ``fn`` ``warmup`` times untimed, then ``reps`` times timed; return ms samples.

    The garbage collector is paused while timing (as ``timeit`` does) so that
    a collection triggered by the harness does not land in one sample.
    """
    if reps < 1:
        raise ConfigError(f"repetitions must be at least 1, not {reps}")
    for _ in range(warmup):
        fn()
    with gc_paused():
        return [time_once(fn) for _ in range(reps)]


@contextmanager
def gc_paused() -> Iterator[None]:
    """Pause automatic garbage collection inside the block (restored after)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def make_record(*, store: str, n: int | None, op: str, samples_ms: Sequence[float], **extra: Any) -> dict[str, Any]:
    """A result record for one (store, n, op) from its samples; ``extra`` fields are added."""
    s = summarize(samples_ms)
    record: dict[str, Any] = {
        "store": store,
        "n": n,
        "op": op,
        "mean_ms": round(s.mean_ms, 4),
        "sd_ms": round(s.sd_ms, 4),
        "p50_ms": round(s.p50_ms, 4),
        "p99_ms": round(s.p99_ms, 4),
        "min_ms": round(s.min_ms, 4),
        "max_ms": round(s.max_ms, 4),
        "reps": s.count,
    }
    record.update(extra)
    return record


def machine_info() -> dict[str, Any]:
    """What the figures were measured on (goes beside the records)."""
    return {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "system": f"{platform.system()} {platform.release()}",
        "cpus": os.cpu_count(),
    }


def write_records(path: Path | str, records: Iterable[Mapping[str, Any]]) -> Path:
    """Write records as a JSON list, atomically (a reader never sees half a file)."""
    path = Path(path)
    records = [dict(r) for r in records]
    for record in records:
        missing = [k for k in RECORD_KEYS if k not in record]
        if missing:
            raise ValueError(f"record {record.get('op')!r} lacks {', '.join(missing)}")
    return write_json(path, records)


def write_json(path: Path | str, document: Any) -> Path:
    """Write ``document`` as indented JSON, atomically (a reader never sees half a file)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(document, indent=1) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"cannot write results to {path}: {exc}") from exc
    return path


def read_records(path: Path | str) -> list[dict[str, Any]]:
    """Read records written by :func:`write_records`; raise ConfigError naming the file."""
    path = Path(path)
    try:
        records = json.loads(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read results {path}: {exc}") from exc
    except ValueError as exc:
        raise ConfigError(f"results {path} are not JSON: {exc}") from exc
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise ConfigError(f"results {path}: expected a JSON list of records")
    return records


def format_table(rows: Sequence[Sequence[Any]], header: Sequence[str], *, markdown: bool = False) -> str:
    """Rows as an aligned plain-text table, or as a Markdown table."""
    cells = [[_cell(v) for v in row] for row in rows]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if i else "---" for i in range(len(header))) + "|"]
        lines += ["| " + " | ".join(row) + " |" for row in cells]
        return "\n".join(lines)
    widths = [max([len(h), *(len(row[i]) for row in cells)]) for i, h in enumerate(header)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(header, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.rjust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if value == 0:
            return "0"
        if abs(value) >= 100:
            return f"{value:,.0f}"
        if abs(value) >= 10:
            return f"{value:.1f}"
        return f"{value:.3f}" if abs(value) >= 0.001 else f"{value:.2g}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)
