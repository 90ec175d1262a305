"""Table I of the paper, reproduced: graph-store overhead as the knowledge grows.

The paper (section V, "Run-time Overhead") loads N = 10 ... 10,000 marker
detector models of about three nodes each into Neo4j 2.2 and times two
operations 100 times each: *insert* (a ProcessProfile next to the selected
detector) and *query* (the placement query of Fig. 5). We do the same on our
store and add what the paper leaves implicit:

``floor``         ``RETURN 1``: the round trip every operation pays
``disk_fsync``    a 128-byte append + fdatasync beside the durable store's AOF: what
                  its fsync costs on this disk at that moment (embedded store only)
``insert``        ``record_process_start``: a ProcessProfile PROFILE_OF the detector's
                  Deployment, RAN_ON a Platform (durable store: fsync on every write)
``insert_create`` the same profile as one plain ``CREATE`` with inline properties: the
                  least the store can do for it (the difference is the writer's own
                  checks and idempotence)
``sample``        ``record_process_sample``: the profile's memory figures (a ``SET``),
                  in a phase of its own after the interleaved ops
``sample_after_create``  the same right after a node was created: FalkorDB 4.16 makes
                  the first ``SET`` after any node creation pay a cost that grows with
                  the node count (~0.35 ms at 30,000 nodes, ~3 ms at 300,000)
``query``         the production placement query, sent with ``store.execute``
``query_named``   the same through ``run_named`` (validation included: our overhead)
``query_bare``    the same statement sent bare: the falkordb client's own ``ro_query`` on
                  the same server and graph (FalkorDB stores only), no layer of ours
``insert_bare``   ``record_process_start``'s statement for a new profile, sent bare the
                  same way: ``insert`` / ``insert_bare`` is what our store layer costs
``fig5_literal``  the paper's Fig. 5 text (unbounded ``<-[*]->``), with a timeout,
                  few repetitions, small N only
``bulk_load``     loading the N models (samples: one per ``UNWIND`` batch)

By default two embedded FalkorDB servers run side by side, one with
``appendfsync always`` (store ``embedded``), one without fsync
(``embedded-nofsync``); each repetition times every (store, op) pair in a
shuffled order, so that both see the same machine at the same moment.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from kgadapt.bench.stats import format_table, gc_paused, machine_info, make_record, read_records, time_once, write_records
from kgadapt.knowledge import queries, runtime
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.store import GraphStore, parse_store_url
from kgadapt.shared.errors import ConfigError, QueryError, StoreTimeout
from kgadapt.shared.resources import results_dir

log = logging.getLogger(__name__)

QUICK_NS = (10, 100, 1_000, 10_000)
FULL_NS = QUICK_NS + (100_000,)
DEFAULT_OUT = results_dir() / "table1.json"
DEFAULT_MARKDOWN = Path("docs/bench-table1.md")
BENCH_GRAPH = "kgadapt_bench_table1"

FEATURE = "MarkerDetection"
CAMERA = "camera"
# Shared platforms: design-time totals and run-time figures (late bound in
# real use; set here because the placement query needs them).
PLATFORMS = {
    "onboard": {"memory_total_mb": 2048, "memory_free_mb": 600.0, "cpu_cores": 4},
    "remote": {"memory_total_mb": 16384, "memory_free_mb": 9000.0, "cpu_cores": 8},
}

# Table I of the paper: (mean ms, sd ms) per N and operation.
PAPER = {
    10: {"insert": (26.861, 5.936), "query": (4.083, 1.274), "start": (1.491, 2.299), "stop": (0.066, 0.023)},
    100: {"insert": (27.766, 6.385), "query": (7.323, 3.198), "start": (1.602, 1.906), "stop": (0.072, 0.025)},
    1000: {"insert": (26.599, 5.942), "query": (8.443, 2.937), "start": (1.670, 2.731), "stop": (0.065, 0.021)},
    10000: {"insert": (26.308, 6.208), "query": (7.901, 2.476), "start": (1.651, 3.345), "stop": (0.074, 0.082)},
}

# Targets of the issue (embedded store, fsync on every write).
TARGET_INSERT_P50_MS = 0.6
TARGET_QUERY_P50_MS = 0.6
TARGET_QUERY_AT = (10_000, 100_000)
TARGET_LOAD_S = 10.0
TARGET_LOAD_N = 100_000
TARGET_LAYER_RATIO = 1.25  # issue 32: our store layer at most this over the same statement sent bare

# The profile record_process_start writes, as one plain CREATE with inline
# properties: the least the store can do for that write (op insert_create).
_CREATE_PROFILE = f"""
MATCH (d:{S.DEPLOYMENT} {{name: $deployment}}), (p:{S.PLATFORM} {{name: $host}}),
      (g:{S.PERCEPTION_GRAPH} {{name: $config}})
CREATE (r:{S.PROCESS_PROFILE} {{name: $run_id, run_id: $run_id, instance: $instance, deployment: $deployment,
                                config: $config, host: $host, pid: $pid, start_time: $start_time}})
CREATE (r)-[:{S.PROFILE_OF}]->(d), (r)-[:{S.RAN_ON}]->(p), (r)-[:{S.RAN_CONFIG}]->(g)
"""
_SHARED_NODES = f"""
CREATE (:{S.FEATURE} {{name: $feature, description: $description}})
CREATE (:{S.COMPONENT}:{S.SENSOR_COMPONENT}:{S.CAMERA} {{name: $camera, memory_demand_mb: $camera_mb,
        width: $width, height: $height, fps: $fps}})
"""
_SHARED_VALUES = {"feature": FEATURE, "description": "Detect ArUco markers for landing and localisation",
                  "camera": CAMERA, "camera_mb": 16.0, "width": 640, "height": 480, "fps": 30}
_PLATFORM = f"""
CREATE (:{S.PLATFORM} {{name: $name, memory_total_mb: $memory_total_mb, cpu_cores: $cpu_cores,
        memory_free_mb: $memory_free_mb, cpu_load: $cpu_load, online: $online, last_seen: $now}})
"""
# One statement per batch of models: the shared nodes are matched once, then
# every model adds its PerceptionGraph, its detector and its Deployment.
_LOAD_BATCH = f"""
MATCH (f:{S.FEATURE} {{name: $feature}}), (cam:{S.COMPONENT} {{name: $camera}}),
      (onboard:{S.PLATFORM} {{name: $onboard}}), (remote:{S.PLATFORM} {{name: $remote}})
UNWIND $models AS m
CREATE (g:{S.PERCEPTION_GRAPH} {{name: m.config, description: m.description}})
CREATE (c:{S.COMPONENT}:{S.PROCESSING_COMPONENT} {{name: m.component, memory_demand_mb: m.demand_mb,
        dictionary: m.dictionary, config_json: m.config_json}})
CREATE (d:{S.DEPLOYMENT}:{S.SYSTEMD_SERVICE_FILE} {{name: m.deployment, kind: m.kind,
        executable: m.executable, arguments: m.arguments}})
CREATE (g)-[:{S.REALIZES}]->(f), (g)-[:{S.CONTAINS}]->(c), (g)-[:{S.CONTAINS}]->(cam),
       (d)-[:{S.DEPLOYS}]->(g), (d)-[:{S.EXECUTABLE_ON}]->(onboard), (d)-[:{S.EXECUTABLE_ON}]->(remote)
"""

SAMPLED_RUN = "sampled"  # the profile that ``sample`` updates

OPS = ("floor", "disk_fsync", "insert", "insert_create", "query", "query_named",  # interleaved, side by side
       "query_bare", "insert_bare",
       "sample", "sample_after_create",  # property updates, a phase of their own
       "fig5_literal", "bulk_load")


@dataclass(frozen=True, kw_only=True)
class Table1Settings:
    """What one run measures. ``store_url`` None: the two embedded servers."""

    ns: tuple[int, ...] = QUICK_NS
    reps: int = 100
    warmup: int = 10
    batch: int | None = None  # models per UNWIND statement; None: 1000 (4 over bolt://)
    fig5_reps: int = 3
    fig5_max_n: int = 100
    fig5_timeout_ms: int = 1000
    store_url: str | None = None
    allow_clear: bool = False
    data_dir: Path | None = None
    seed: int = 1
    mode: str = "quick"

    def __post_init__(self) -> None:
        if not self.ns:
            raise ConfigError("no N to measure; give --n with a positive number of models")
        bad = [n for n in self.ns if n < 1]
        if bad:
            raise ConfigError(f"--n {bad[0]}: the number of detector models must be at least 1")
        if self.reps < 2:
            raise ConfigError(f"--reps {self.reps}: need at least 2 repetitions for a standard deviation")
        if self.warmup < 0 or self.fig5_reps < 0:
            raise ConfigError("--warmup and --fig5-reps cannot be negative")
        if self.batch is not None and self.batch < 1:
            raise ConfigError(f"--batch {self.batch}: must be at least 1")
        if self.fig5_timeout_ms < 1:
            raise ConfigError(f"--fig5-timeout-ms {self.fig5_timeout_ms}: must be at least 1")


# --------------------------------------------------------------------------- workload


def model_rows(first: int, count: int, rng: random.Random) -> list[dict[str, Any]]:
    """Parameters of ``count`` detector models numbered from ``first``.

    Each differs in its detector parameters and memory demand, as the
    paper's "potential marker detectors, all of them varying in different
    configuration properties".
    """
    rows = []
    for i in range(first, first + count):
        window = rng.choice((23, 33, 43, 53, 63))
        constant = rng.choice((3, 5, 7, 9))
        config_json = json.dumps(
            {
                "dictionary": "DICT_4X4_50",
                "preprocess": [{"op": "gamma", "gamma": round(rng.uniform(0.4, 1.0), 2)}] if i % 3 == 0 else [],
                "parameters": {"adaptiveThreshWinSizeMax": window, "adaptiveThreshConstant": constant},
            },
            separators=(",", ":"),
        )
        rows.append(
            {
                "config": config_name(i),
                "description": f"marker detector variant {i}",
                "component": f"aruco_{i:06d}",
                "demand_mb": float(rng.randrange(40, 900)),
                "dictionary": "DICT_4X4_50",
                "config_json": config_json,
                "deployment": deployment_name(i),
                "kind": "systemd",
                "executable": "{python}",
                "arguments": ["-m", "kgadapt.onboard.perception.detector", "--config", config_name(i)],
            }
        )
    return rows


def config_name(i: int) -> str:
    return f"detector_{i:06d}"


def deployment_name(i: int) -> str:
    return f"deploy_detector_{i:06d}"


def load_models(store: GraphStore, n: int, *, batch: int, seed: int) -> list[float]:
    """Load the shared nodes and ``n`` detector models into an empty graph.

    Returns one duration (ms) per statement: the shared nodes first, then
    one per ``UNWIND`` batch.
    """
    rng = random.Random(seed)
    now = time.time()
    durations = [time_once(lambda: store.execute(_SHARED_NODES, _SHARED_VALUES))]
    for name, figures in PLATFORMS.items():
        values = {"name": name, "now": now, "cpu_load": 0.0, "online": True, **figures}
        durations[0] += time_once(lambda: store.execute(_PLATFORM, values))
    names = {"feature": FEATURE, "camera": CAMERA, "onboard": "onboard", "remote": "remote"}
    for first in range(0, n, batch):
        models = model_rows(first, min(batch, n - first), rng)
        durations.append(time_once(lambda: store.execute(_LOAD_BATCH, {**names, "models": models})))
    return durations


def count_graph(store: GraphStore) -> tuple[int, int]:
    """(nodes, relationships) in the graph."""
    nodes = store.execute("MATCH (n) RETURN count(n) AS c", read_only=True)[0]["c"]
    rels = store.execute("MATCH ()-[r]->() RETURN count(r) AS c", read_only=True)[0]["c"]
    return int(nodes), int(rels)


# --------------------------------------------------------------------------- operations


@dataclass(frozen=True)
class Sources:
    """The texts measured: the project's named queries (knowledge/queries.py)."""

    placement: str  # the text run_named sends when a config is given
    fig5: str
    fig5_params: tuple[str, ...]


def find_sources() -> Sources:
    named = queries.QUERIES["placement"]
    literal = queries.QUERIES["fig5_literal"]
    return Sources(named.text_for({"config": "given"}), literal.cypher, tuple(literal.params))


@dataclass
class Probe:
    """One store under measurement and the operations timed on it."""

    name: str
    store: GraphStore
    durable: bool | None
    disk_probe: int | None = None  # fd of a file beside the store's AOF, for disk_fsync
    bare: Any = None  # the falkordb client's own Graph on the same server and graph (query_bare, insert_bare)


Op = Callable[[int | str, int], Any]


def _operations(probe: Probe, sources: Sources, n: int) -> tuple[dict[str, Op], Op, Op]:
    """Each op as ``fn(rep, model)``: one call against ``probe.store``.

    Returns the interleaved Table I ops, then ``sample`` and ``insert_create``
    for the separate property-update phase.
    """
    store = probe.store

    def params(model: int) -> dict[str, Any]:
        return {"feature": FEATURE, "config": config_name(model)}

    def run_id(rep: int | str) -> str:
        return f"bench-{probe.name}-{n}-{rep}"

    def profile(rep: int | str, model: int, suffix: str = "") -> dict[str, Any]:
        return {
            "run_id": run_id(rep) + suffix,
            "instance": f"detector-{rep}",
            "deployment": deployment_name(model),
            "config": config_name(model),
            "host": "remote" if isinstance(rep, int) and rep % 2 else "onboard",
            "pid": 10_000 + rep if isinstance(rep, int) else 9_999,
            "start_time": time.time(),
        }

    def insert(rep: int | str, model: int) -> None:
        runtime.record_process_start(store, **profile(rep, model))

    def insert_create(rep: int | str, model: int) -> None:
        store.execute(_CREATE_PROFILE, profile(rep, model, "-create"))

    def sample(rep: int | str, model: int) -> None:
        # Always the one profile made for this phase; the figures vary so
        # that every call really writes (and fsyncs).
        rep = rep if isinstance(rep, int) else 0
        fields = {"run_id": run_id(SAMPLED_RUN), "rss_mb_last": 48.0 + rep % 7, "rss_mb_mean": 47.9,
                  "rss_mb_max": 49.2 + rep, "cpu_percent_mean": 35.0}
        runtime.record_process_sample(store, **fields)

    ops: dict[str, Op] = {
        "floor": lambda rep, model: store.execute("RETURN 1 AS one", read_only=True),
        "insert": insert,
        "insert_create": insert_create,
        "query": lambda rep, model: store.execute(sources.placement, params(model), read_only=True),
        "query_named": lambda rep, model: queries.run_named(store, "placement", params(model)),
    }
    if probe.disk_probe is not None:
        ops["disk_fsync"] = lambda rep, model: _append_and_sync(probe.disk_probe)
    if probe.bare is not None:
        bare = probe.bare

        def insert_bare(rep: int | str, model: int) -> None:
            bare.query(runtime.START_NEW_PROFILE, profile(rep, model, "-bare"))

        ops["query_bare"] = lambda rep, model: bare.ro_query(sources.placement, params(model)).result_set
        ops["insert_bare"] = insert_bare
    return ops, sample, insert_create


def _append_and_sync(fd: int) -> None:
    """What the server's fsync costs on this disk: a small append, then fdatasync (as redis does)."""
    os.write(fd, b"x" * 128)
    os.fdatasync(fd)


def _check_placement(probe: Probe, sources: Sources, model: int) -> None:
    """Refuse to time a query that answers nothing: the workload would be wrong."""
    rows = probe.store.execute(sources.placement, {"feature": FEATURE, "config": config_name(model)}, read_only=True)
    if not rows:
        raise QueryError(f"placement query found no platform for {config_name(model)} on {probe.name}; "
                         "the generated workload does not match the query")


def measure_n(probes: Sequence[Probe], sources: Sources, n: int, settings: Table1Settings,
              rng: random.Random) -> list[dict[str, Any]]:
    """Load N models into every probe's store and time every op, interleaved."""
    records: list[dict[str, Any]] = []
    for probe in probes:
        probe.store.clear()
        S.ensure_indexes(probe.store)
        batch = _batch_for(probe.store, settings)
        started = time.perf_counter()
        durations = load_models(probe.store, n, batch=batch, seed=settings.seed)
        total_s = time.perf_counter() - started  # generating the models included
        nodes, rels = count_graph(probe.store)
        records.append(make_record(
            store=probe.name, n=n, op="bulk_load", samples_ms=durations[1:] or durations,
            total_s=round(total_s, 3), store_s=round(sum(durations) / 1000, 3), models_per_s=round(n / total_s),
            batch=batch, nodes=nodes, relationships=rels, durable=probe.durable,
        ))
        log.info("%s: loaded %d models (%d nodes, %d relationships) in %.2f s", probe.name, n, nodes, rels, total_s)
    # The literal query walks every path, so it runs on the graph of the N
    # models alone, before the timed inserts add profiles (and paths) to it.
    if n <= _fig5_max_n(probes[0].store, settings) and settings.fig5_reps:
        records.append(measure_fig5(probes[0], sources, n, settings))
    operations = {probe.name: _operations(probe, sources, n) for probe in probes}
    plan = [(probe, op, fn) for probe in probes for op, fn in operations[probe.name][0].items()]
    for probe in probes:
        _check_placement(probe, sources, rng.randrange(n))
    # Warm up: plan caches and connections, with run ids that do not collide.
    for w in range(settings.warmup):
        model = rng.randrange(n)
        for probe, op, fn in plan:
            fn(-1 - w, model)
    samples: dict[tuple[str, str], list[float]] = {(p.name, op): [] for p, op, _ in plan}
    with gc_paused():
        for rep in range(settings.reps):
            model = rng.randrange(n)  # the detector selected in this repetition
            rng.shuffle(plan)
            for probe, op, fn in plan:
                samples[(probe.name, op)].append(time_once(lambda: fn(rep, model)))
    for probe in probes:
        ops, sample, insert_create = operations[probe.name]
        samples.update(measure_updates(probe, ops["insert"], sample, insert_create, n, settings, rng))
    for probe in probes:
        for (name, op), values in samples.items():
            if name == probe.name:
                records.append(make_record(store=name, n=n, op=op, samples_ms=values,
                                           warmup=settings.warmup, durable=probe.durable))
    return records


def measure_updates(probe: Probe, insert: Op, sample: Op, insert_create: Op, n: int, settings: Table1Settings,
                    rng: random.Random) -> dict[tuple[str, str], list[float]]:
    """Property updates on their own: ``sample`` alone, and right after a node was created.

    Kept out of the interleaved loop: in FalkorDB 4.16 the first SET after a
    node creation pays a cost that grows with the node count, and that cost
    would land on whichever op followed.
    """
    insert(SAMPLED_RUN, rng.randrange(n))
    for w in range(settings.warmup):
        sample(-1 - w, 0)
    alone, after_create = [], []
    with gc_paused():
        for rep in range(settings.reps):
            alone.append(time_once(lambda: sample(rep, 0)))
        for rep in range(settings.reps):
            insert_create(f"update-{rep}", rng.randrange(n))
            after_create.append(time_once(lambda: sample(rep, 0)))
    return {(probe.name, "sample"): alone, (probe.name, "sample_after_create"): after_create}


def _batch_for(store: GraphStore, settings: Table1Settings) -> int:
    if settings.batch:
        return settings.batch
    # FalkorDB's Bolt listener crashed on parameters above ~4 KB (measured with
    # FalkorDB 4.16); four models are ~1.7 KB.
    return 4 if store.settings.kind == "bolt" else 1000


def _fig5_max_n(store: GraphStore, settings: Table1Settings) -> int:
    if store.capabilities.timeouts:
        return settings.fig5_max_n
    # A store that cannot stop a query at timeout_ms (FalkorDB's Bolt listener) could run the
    # unbounded query for minutes: keep it to graphs where it ends in well under a second.
    limit = min(settings.fig5_max_n, 10)
    if settings.fig5_max_n > limit:
        log.warning("%s does not enforce query timeouts: Fig. 5 literal only up to N=%d", store.url, limit)
    return limit


def measure_fig5(probe: Probe, sources: Sources, n: int, settings: Table1Settings) -> dict[str, Any]:
    """The paper's literal query, a few times, each bounded by a timeout."""
    params = {"feature": FEATURE, "config": config_name(0)}
    params = {k: v for k, v in params.items() if k in sources.fig5_params}
    values, timeouts, rows = [], 0, None
    for _ in range(settings.fig5_reps):
        start = time.perf_counter_ns()
        try:
            rows = len(probe.store.execute(sources.fig5, params, read_only=True, timeout_ms=settings.fig5_timeout_ms))
        except StoreTimeout:
            timeouts += 1
        values.append((time.perf_counter_ns() - start) / 1e6)
    log.info("%s: fig5_literal at N=%d: %d of %d timed out", probe.name, n, timeouts, len(values))
    return make_record(store=probe.name, n=n, op="fig5_literal", samples_ms=values,
                       timeouts=timeouts, timeout_ms=settings.fig5_timeout_ms, rows=rows, durable=probe.durable)


# --------------------------------------------------------------------------- run


def run_table1(settings: Table1Settings, *, progress: Callable[[str], None] = lambda line: None) -> list[dict[str, Any]]:
    """Measure every N of ``settings``; return the records (not yet written)."""
    from kgadapt.knowledge.embedded import EmbeddedServer
    from kgadapt.knowledge.falkordb_store import FalkorDBStore
    from kgadapt.knowledge.store import open_store

    sources = find_sources()
    rng = random.Random(settings.seed)
    started = time.monotonic()
    run_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
    load_before = round(os.getloadavg()[0], 2)  # other work on the machine shows in the figures
    probes: list[Probe] = []
    with tempfile.TemporaryDirectory(prefix="kgadapt-table1-", dir=settings.data_dir) as tmp:
        try:
            if settings.store_url:
                store = _open_foreign(settings, open_store)
                probes.append(Probe(_store_label(settings.store_url), store, None))
            else:
                for name, fsync in (("embedded", True), ("embedded-nofsync", False)):
                    data_dir = Path(tmp) / name
                    server = EmbeddedServer(data_dir, fsync_always=fsync)
                    store = FalkorDBStore(parse_store_url(f"embedded:{data_dir}"), server=server)
                    probes.append(Probe(name, store, fsync))
                    store.setup()
                    probes[-1].bare = _bare_graph(server.ensure().unix_socket, store.settings.graph)
                    if fsync:
                        probes[-1].disk_probe = os.open(data_dir / "disk-probe.bin",
                                                        os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            records: list[dict[str, Any]] = []
            for n in settings.ns:
                t0 = time.monotonic()
                found = measure_n(probes, sources, n, settings, rng)
                records.extend(found)
                progress(f"N={n:,}: done in {time.monotonic() - t0:.1f} s")
        finally:
            for probe in probes:
                if probe.disk_probe is not None:
                    os.close(probe.disk_probe)
                try:
                    if settings.store_url:
                        probe.store.clear()  # leave no benchmark graph behind on someone's server
                finally:
                    probe.store.shutdown()
    wall_s = round(time.monotonic() - started, 1)
    common = {"run_at": run_at, "mode": settings.mode, "wall_s": wall_s,
              "loadavg_1m": [load_before, round(os.getloadavg()[0], 2)],
              "data_fs": _filesystem(settings.data_dir or Path(tempfile.gettempdir())) if not settings.store_url else None,
              **machine_info()}
    return [{**r, **common} for r in records]


def _bare_graph(unix_socket: str, graph: str) -> Any:
    """The falkordb client's own Graph, for the same statements sent without our store layer."""
    from falkordb import FalkorDB

    return FalkorDB(unix_socket_path=unix_socket).select_graph(graph)


def _open_foreign(settings: Table1Settings, open_store: Callable[..., GraphStore]) -> GraphStore:
    """A store given by URL: a graph of our own on FalkorDB, else the whole (cleared) graph."""
    parsed = parse_store_url(settings.store_url)
    if parsed.kind == "embedded":
        raise ConfigError(f"--store {settings.store_url}: the embedded store is the default; "
                          "give a falkordb://, bolt:// or memgraph:// URL for another backend")
    if parsed.kind == "falkordb":
        store = open_store(settings.store_url, graph=BENCH_GRAPH)
    elif not settings.allow_clear:
        raise ConfigError(f"--store {settings.store_url}: this server has one graph and the benchmark "
                          "deletes everything in it; add --allow-clear if that is what you want")
    else:
        store = open_store(settings.store_url)
    store.setup()
    return store


def _store_label(url: str) -> str:
    s = parse_store_url(url)
    where = s.unix_socket or f"{s.host}:{s.port}"
    return f"{s.kind}://{where}"


def _filesystem(path: Path) -> str:
    """The file system type holding ``path`` (fsync on tmpfs would cost nothing)."""
    best, kind = "", "unknown"
    try:
        target = str(path.resolve())
        for line in Path("/proc/mounts").read_text().splitlines():
            _, mount, fstype, *_ = line.split()
            if target.startswith(mount) and len(mount) > len(best):
                best, kind = mount, fstype
    except OSError:
        pass
    return kind


# --------------------------------------------------------------------------- reports


def _index(records: Sequence[Mapping[str, Any]]) -> dict[tuple[str, int, str], Mapping[str, Any]]:
    return {(r["store"], r["n"], r["op"]): r for r in records}


def _stores(records: Sequence[Mapping[str, Any]]) -> list[str]:
    seen: list[str] = []
    for r in records:
        if r["store"] not in seen:
            seen.append(r["store"])
    return seen


def _ns(records: Sequence[Mapping[str, Any]]) -> list[int]:
    return sorted({r["n"] for r in records})


def _get(ix: Mapping, key: tuple, field_: str) -> float | None:
    record = ix.get(key)
    return None if record is None else record.get(field_)


def _fig5_cell(record: Mapping[str, Any] | None) -> str:
    if record is None:
        return "-"
    if record.get("timeouts"):
        return f"timeout {record['timeouts']}/{record['reps']} (>{record['timeout_ms']} ms)"
    return f"{record['p50_ms']:.2f}"


def summary_tables(records: Sequence[Mapping[str, Any]], *, markdown: bool = False) -> str:
    """Our figures (p50 / p99) and the paper's beside ours (means, ratio)."""
    ix = _index(records)
    stores = _stores(records)
    main, other = stores[0], (stores[1] if len(stores) > 1 else None)
    ours_rows, paper_rows = [], []
    for n in _ns(records):
        def p(op: str, store: str | None = main, f: str = "p50_ms") -> float | None:
            return None if store is None else _get(ix, (store, n, op), f)

        load = _get(ix, (main, n, "bulk_load"), "total_s")
        ours_rows.append([
            n, p("floor"), p("disk_fsync"), p("insert"), p("insert", f="p99_ms"), p("insert", other), p("insert_create"),
            p("sample"), p("sample_after_create"),
            p("query"), p("query_named"), p("query_named", f="p99_ms"),
            _fig5_cell(ix.get((main, n, "fig5_literal"))), load,
        ])
        paper = PAPER.get(n)
        q_op = "query_named" if (main, n, "query_named") in ix else "query"
        our_insert, our_query = p("insert", f="mean_ms"), p(q_op, f="mean_ms")
        paper_rows.append([
            n,
            paper["insert"][0] if paper else None, our_insert,
            _ratio(paper["insert"][0], our_insert) if paper else None,
            paper["query"][0] if paper else None, our_query,
            _ratio(paper["query"][0], our_query) if paper else None,
            p("insert"), p(q_op),
        ])
    fsync = "fsync" if ix and next(iter(ix.values())).get("durable") else "store"
    other_label = f"insert p50 ({other})" if other else "insert p50 (other)"
    ours = format_table(ours_rows, [
        "N", "floor p50", "disk fsync p50", f"insert p50 ({fsync})", "insert p99", other_label, "CREATE-only p50", "sample p50",
        "sample after CREATE p50",
        "query p50", "named p50", "named p99", "Fig. 5 literal p50", "bulk load s",
    ], markdown=markdown)
    paper = format_table(paper_rows, [
        "N", "paper insert mean", "our insert mean", "ratio", "paper query mean", "our query mean", "ratio",
        "our insert p50", "our query p50",
    ], markdown=markdown)
    return f"{ours}\n\n{paper}"


def _ratio(paper: float, ours: float | None) -> str | None:
    return None if not ours else f"{paper / ours:.0f}x"


def target_lines(records: Sequence[Mapping[str, Any]]) -> list[str]:
    """Each target of the issue with the measured figure; a missed one with the figures that explain it."""
    ix = _index(records)
    if "embedded" not in _stores(records):
        return ["targets apply to the embedded store with fsync; not measured in this run"]
    ns = _ns(records)
    lines = []

    def verdict(ok: bool) -> str:
        return "met" if ok else "NOT MET"

    for n in ns:
        r = ix.get(("embedded", n, "insert"))
        if r is not None:
            ok = r["p50_ms"] <= TARGET_INSERT_P50_MS
            lines.append(f"insert p50 <= {TARGET_INSERT_P50_MS} ms (fsync always) at N={n:,}: {r['p50_ms']:.3f} ms "
                         f"-> {verdict(ok)}" + ("" if ok else _insert_limit(ix, n, r["p50_ms"])))
    for n in TARGET_QUERY_AT:
        if ("embedded", n, "query") not in ix:
            lines.append(f"query p50 <= {TARGET_QUERY_P50_MS} ms at N={n:,}: not measured (run --full)")
            continue
        for op in ("query", "query_named"):
            r = ix.get(("embedded", n, op))
            if r is not None:
                ok = r["p50_ms"] <= TARGET_QUERY_P50_MS
                lines.append(f"{op} p50 <= {TARGET_QUERY_P50_MS} ms at N={n:,}: {r['p50_ms']:.3f} ms -> {verdict(ok)}"
                             + ("" if ok else _query_limit(ix, n, op, ns[0])))
    for n in ns:
        for op, bare in (("query_named", "query_bare"), ("insert", "insert_bare")):
            ours, alone = _get(ix, ("embedded", n, op), "p50_ms"), _get(ix, ("embedded", n, bare), "p50_ms")
            if ours is not None and alone:
                ok = ours <= TARGET_LAYER_RATIO * alone
                lines.append(f"{op} through the store API within {TARGET_LAYER_RATIO}x of the statement sent bare at "
                             f"N={n:,}: {ours:.3f} / {alone:.3f} ms = {ours / alone:.2f}x -> {verdict(ok)}")
    load = ix.get(("embedded", TARGET_LOAD_N, "bulk_load"))
    if load is None:
        lines.append(f"bulk load of {TARGET_LOAD_N:,} models <= {TARGET_LOAD_S:.0f} s: not measured (run --full)")
    else:
        lines.append(f"bulk load of {TARGET_LOAD_N:,} models <= {TARGET_LOAD_S:.0f} s: {load['total_s']:.2f} s "
                     f"-> {verdict(load['total_s'] <= TARGET_LOAD_S)}")
    return lines


def _insert_limit(ix: Mapping, n: int, insert: float) -> str:
    """The same run's figures that split a missed insert into its parts."""
    nofsync = _get(ix, ("embedded-nofsync", n, "insert"), "p50_ms")
    create = _get(ix, ("embedded", n, "insert_create"), "p50_ms")
    floor = _get(ix, ("embedded", n, "floor"), "p50_ms")
    disk = _get(ix, ("embedded", n, "disk_fsync"), "p50_ms")
    parts = [f"RETURN 1 {floor:.3f} ms"] if floor is not None else []
    if disk is not None:
        parts.append(f"bare disk fdatasync {disk:.3f} ms")
    if nofsync is not None:
        parts.append(f"same write without fsync {nofsync:.3f} ms (fsync adds {insert - nofsync:.3f})")
    if create is not None:
        parts.append(f"one CREATE with inline properties, fsynced, {create:.3f} ms "
                     f"(the writer's statement adds {insert - create:.3f})")
    return f" (same run: {'; '.join(parts)})" if parts else ""


def _query_limit(ix: Mapping, n: int, op: str, smallest: int) -> str:
    floor = _get(ix, ("embedded", n, "floor"), "p50_ms")
    small = _get(ix, ("embedded", smallest, op), "p50_ms")
    parts = [f"RETURN 1 {floor:.3f} ms"] if floor is not None else []
    if small is not None and smallest != n:
        parts.append(f"the same query at N={smallest:,} {small:.3f} ms")
    return f" (same run: {'; '.join(parts)})" if parts else ""


def plot(records: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """A PNG: latency (p50, p99 as whiskers) against N, the paper's means dashed; load time."""
    from kgadapt.shared.extras import require

    matplotlib = require("matplotlib", extra="plots", what="the Table I plot")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ix = _index(records)
    stores = _stores(records)
    ns = _ns(records)
    fig, (ax, ax_load) = plt.subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [2, 1]})
    series = [(stores[0], "floor", "RETURN 1"), (stores[0], "disk_fsync", "disk fdatasync alone"),
              (stores[0], "insert", f"insert ({stores[0]})"),
              (stores[0], "query", "placement query (store)"), (stores[0], "query_named", "placement query (run_named)")]
    if len(stores) > 1:
        series.insert(2, (stores[1], "insert", f"insert ({stores[1]})"))
    for store, op, label in series:
        xs = [n for n in ns if (store, n, op) in ix]
        if not xs:
            continue
        p50 = [ix[(store, n, op)]["p50_ms"] for n in xs]
        p99 = [ix[(store, n, op)]["p99_ms"] for n in xs]
        ax.errorbar(xs, p50, yerr=[[0] * len(xs), [b - a for a, b in zip(p50, p99)]], marker="o", capsize=3,
                    label=f"{label}: p50, whisker p99")
    fig5 = [(n, ix[(stores[0], n, "fig5_literal")]) for n in ns if (stores[0], n, "fig5_literal") in ix]
    if fig5:
        ax.scatter([n for n, _ in fig5], [r["p50_ms"] for _, r in fig5], marker="x", color="black", zorder=5,
                   label="Fig. 5 literal (x; timed out if at the limit)")
    paper_ns = [n for n in sorted(PAPER) if n <= max(ns)] or sorted(PAPER)
    for op, style in (("insert", "--"), ("query", ":")):
        ax.plot(paper_ns, [PAPER[n][op][0] for n in paper_ns], style, color="grey",
                label=f"paper {op} (Neo4j 2.2, mean)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("N detector models")
    ax.set_ylabel("ms per operation")
    ax.set_title("Table I workload: graph-store operations")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    for store in stores:
        xs = [n for n in ns if (store, n, "bulk_load") in ix]
        ax_load.plot(xs, [ix[(store, n, "bulk_load")]["total_s"] for n in xs], marker="o", label=store)
    ax_load.axhline(TARGET_LOAD_S, color="red", linestyle="--", linewidth=0.8, label=f"target {TARGET_LOAD_S:.0f} s")
    ax_load.set_xscale("log")
    ax_load.set_yscale("log")
    ax_load.set_xlabel("N detector models")
    ax_load.set_ylabel("s")
    ax_load.set_title("bulk load (UNWIND batches)")
    ax_load.grid(True, which="both", alpha=0.3)
    ax_load.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _loads(record: Mapping[str, Any]) -> str:
    loads = record.get("loadavg_1m")
    return f"{loads[0]} at the start, {loads[1]} at the end" if loads else "?"


def markdown_report(records: Sequence[Mapping[str, Any]], *, json_path: Path, png_path: Path,
                    markdown_path: Path) -> str:
    """The README section: generated from the records, never edited by hand."""
    first = records[0] if records else {}
    image = os.path.relpath(png_path.absolute(), markdown_path.absolute().parent)
    tables = summary_tables(records, markdown=True)
    targets = "\n".join(f"- {line}" for line in target_lines(records))
    paper_ops = format_table(
        [[n, v["start"][0], v["stop"][0]] for n, v in sorted(PAPER.items())],
        ["N", "paper start mean ms", "paper stop mean ms"], markdown=True)
    return f"""# Table I: graph-store overhead (generated by `kgadapt bench table1`)

<!-- Generated from {json_path} by `kgadapt bench table1 --from-json {json_path}`; do not edit. -->

Run {first.get('run_at', '?')}, mode `{first.get('mode', '?')}`, wall time {first.get('wall_s', '?')} s,
{first.get('cpus', '?')} CPUs, Python {first.get('python', '?')}, store data on `{first.get('data_fs', '?')}`,
1-minute load average {_loads(first)} (other work on the machine at the same time shows in the figures).
Queries from `knowledge/queries.py` (named query `placement`, `fig5_literal`); writes from `knowledge/runtime.py`.

What is measured (each N = a fresh graph of N detector models: a `PerceptionGraph` that CONTAINS its
own ArUco `ProcessingComponent` and the shared camera, REALIZES `MarkerDetection`, DEPLOYED by one
`Deployment` EXECUTABLE_ON the two shared platforms; loaded in `UNWIND` batches with parameters):

- **floor**: `RETURN 1` round trip; every other operation pays it. **disk fsync**: a 128-byte append and
  `fdatasync` on a file beside the durable store's append-only file, what its fsync costs on this disk
  at that moment (no store involved).
- **insert**: `record_process_start`, a `ProcessProfile` next to the selected detector (PROFILE_OF its
  Deployment, RAN_ON a Platform). On `embedded` every write is fsynced (`appendfsync always`) before
  the reply; `embedded-nofsync` is the same server without fsync, timed in the same run.
- **CREATE-only**: the same profile as one plain `CREATE` with its properties inline, fsynced: the least
  the store can do for this write; the difference to insert is the writer's own checks and idempotence.
- **sample**: `record_process_sample`, the profile's memory figures (a `SET`, fsynced too), timed in a
  phase of its own after the interleaved ops. **sample after CREATE**: the same, each time right after a
  node was created. FalkorDB 4.16 makes the first `SET` after any node creation pay a cost that grows
  with the number of nodes (fsync or not; reads, creations and relation-only writes do not pay it). In
  the interleaved loop that cost landed on whichever write came next, so updates are timed apart.
- **query** / **named**: the production `placement` query through `store.execute`, and through
  `run_named` (parameter validation included). Anchored on the selected `PerceptionGraph`, directed,
  bounded: its cost does not depend on N.
- **Fig. 5 literal**: the paper's query as printed (unbounded `<-[*]->` from the shared Feature),
  few repetitions with a per-query timeout, small N only. FalkorDB honours read timeouts late, so a
  timed-out sample shows how long the caller waited.
- **bulk load**: wall time to generate and load the N models (1,000 per `UNWIND` statement, fsynced
  on `embedded`), indexes created first.
- Each repetition picks a random detector and times every (store, op) pair in a shuffled order:
  figures in one row were measured side by side. Samples are single calls (no batching), timed from
  Python around the whole call; the garbage collector is paused while timing.

Milliseconds; ratio = paper mean / our mean.

{tables}

The paper's adaptation operations for scale (our deployer bench measures ours):

{paper_ops}

## Targets (embedded store, fsync on every write)

{targets}

A missed target is split with figures from the same run: what fsync adds (the same write on
`embedded-nofsync`), what the writer's statement adds (one `CREATE` with inline properties), and what
the machine gave every operation (`RETURN 1`; the load average above: this 2-core machine is shared,
and two servers plus the client already compete for its cores).

![Table I plot]({image})

Plot: `{png_path}`; records: `{json_path}` (one per store, N and op: mean, sd, p50, p99 in ms).
"""


# --------------------------------------------------------------------------- command


def register(bench_sub: argparse._SubParsersAction) -> None:
    """Add ``kgadapt bench table1``."""
    p = bench_sub.add_parser(
        "table1",
        help="reproduce the paper's Table I (insert and placement-query latency as N grows)",
        description="Reproduce Table I of the paper on our store: N detector models, insert and "
                    "placement-query latency (mean, sd, p50, p99) beside the paper's figures. "
                    f"Quick by default (N = {', '.join(f'{n:,}' for n in QUICK_NS)}); --full adds 100,000.",
    )
    p.add_argument("--full", action="store_true", help="every N, up to 100,000 models")
    p.add_argument("--n", type=int, action="append", metavar="N",
                   help="measure this N (repeatable); overrides --full")
    p.add_argument("--reps", type=int, default=100, help="timed repetitions per op and N (default 100)")
    p.add_argument("--warmup", type=int, default=10, help="untimed repetitions first (default 10)")
    p.add_argument("--batch", type=int, default=None, help="models per UNWIND statement (default 1000; 4 over bolt://)")
    p.add_argument("--fig5-reps", type=int, default=3, help="repetitions of the literal Fig. 5 query (default 3)")
    p.add_argument("--fig5-max-n", type=int, default=100, help="largest N for the literal Fig. 5 query (default 100)")
    p.add_argument("--fig5-timeout-ms", type=int, default=1000, help="its per-query timeout (default 1000)")
    p.add_argument("--store", metavar="URL", default=None,
                   help="run against this store instead of the two embedded servers "
                        "(falkordb://, bolt://, memgraph://)")
    p.add_argument("--allow-clear", action="store_true",
                   help="let the benchmark empty a bolt:// or memgraph:// server's graph")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the embedded servers keep their temporary data (default: the temp dir)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the workload and the selections")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"records as JSON (default {DEFAULT_OUT}); "
                   "the plot goes beside it (.png)")
    p.add_argument("--markdown", type=Path, default=DEFAULT_MARKDOWN,
                   help=f"the generated README table (default {DEFAULT_MARKDOWN}); '-' for none")
    p.add_argument("--from-json", type=Path, default=None, metavar="FILE",
                   help="do not measure: regenerate tables, plot and Markdown from FILE")
    p.add_argument("--json", action="store_true", help="print the records as JSON instead of tables")
    p.set_defaults(func=command)


def command(args: argparse.Namespace) -> int:
    """Run (or re-report) Table I and write the JSON, the PNG and the Markdown."""
    if args.from_json:
        records = read_records(args.from_json)
        out = args.from_json
    else:
        ns = tuple(sorted(set(args.n))) if args.n else (FULL_NS if args.full else QUICK_NS)
        settings = Table1Settings(
            ns=ns, reps=args.reps, warmup=args.warmup, batch=args.batch, fig5_reps=args.fig5_reps,
            fig5_max_n=args.fig5_max_n, fig5_timeout_ms=args.fig5_timeout_ms, store_url=args.store,
            allow_clear=args.allow_clear, data_dir=args.data_dir, seed=args.seed,
            mode="full" if args.full and not args.n else ("custom" if args.n else "quick"),
        )
        def progress(line: str) -> None:
            print(line, file=sys.stderr, flush=True)

        records = run_table1(settings, progress=progress)
        out = args.out
        write_records(out, records)
    png = Path(out).with_suffix(".png")
    plot(records, png)
    if str(args.markdown) != "-":
        try:
            args.markdown.parent.mkdir(parents=True, exist_ok=True)
            args.markdown.write_text(markdown_report(records, json_path=Path(out), png_path=png,
                                                     markdown_path=args.markdown))
        except OSError as exc:
            raise ConfigError(f"cannot write {args.markdown}: {exc}") from exc
    if args.json:
        print(json.dumps(records, indent=1))
        return 0
    print(summary_tables(records))
    print()
    for line in target_lines(records):
        print(line)
    print(f"\nrecords: {out}\nplot:    {png}" + ("" if str(args.markdown) == "-" else f"\nreport:  {args.markdown}"))
    return 0
