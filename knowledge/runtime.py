"""Late binding: run-time facts written into the knowledge graph.

The models create the nodes whose figures are unknown at design time
(``Platform``: free memory, CPU load, online); the agents, the deployer and
the adaptation manager fill them in through these writers. Only the models
add hosts: a write naming a host that no ``Platform`` of the models names is
refused with :class:`UnknownHost` and changes nothing. Each writer runs
parameterised statements only, idempotent where it can be (MERGE on name), all
through the store interface. The knowledge service exposes exactly
:data:`WRITERS` as its write verbs; :func:`run_write` checks a verb's
parameters (names and types) so a malformed request is refused with a
:class:`NamedQueryError` naming the verb and the parameter.

A model reload never touches what is written here (see knowledge/loader.py).
Units: memory in MiB, CPU in percent of one core, times in epoch seconds.
"""

from __future__ import annotations

import inspect
import math
from typing import Any, Callable, Mapping, Sequence

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.fleet_roster import forget_robot
from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import NamedQueryError, UnknownHost

_NUM = (int, float)
# Bounds of what a real host can report: a value outside them is a forgery or a bug, refused naming the field.
MAX_MEMORY_MB = 64 * 1024 * 1024  # 64 TiB
MAX_CORES = 4096
MAX_PID = 2**31 - 1


def _check(verb: str, **values: tuple[Any, tuple[type, ...], bool]) -> None:
    """Each value as (value, allowed types, may be None)."""
    for key, (value, types, optional) in values.items():
        if value is None:
            if optional:
                continue
            raise NamedQueryError(f"write {verb!r}: parameter {key!r} is missing")
        if isinstance(value, bool) and bool not in types:
            raise NamedQueryError(f"write {verb!r}: parameter {key!r} must be a number, not a bool")
        if not isinstance(value, types):
            names = " or ".join(t.__name__ for t in types)
            raise NamedQueryError(f"write {verb!r}: parameter {key!r} must be {names}, not {type(value).__name__}")
        if isinstance(value, float) and not math.isfinite(value):
            raise NamedQueryError(f"write {verb!r}: parameter {key!r} must be a finite number")
        if isinstance(value, str) and not value:
            raise NamedQueryError(f"write {verb!r}: parameter {key!r} is empty")


def _within(verb: str, **values: tuple[Any, float, float]) -> None:
    """Each value as (value, lowest, highest); None is not checked (checked for presence elsewhere)."""
    for key, (value, low, high) in values.items():
        if value is not None and not low <= value <= high:
            raise NamedQueryError(f"write {verb!r}: {key} {value!r} is not between {low:g} and {high:g}")


def unknown_host(verb: str, host: str) -> UnknownHost:
    return UnknownHost(host, f"write {verb!r}: host {host!r} is no Platform of the models; only the models add "
                             "hosts (kgadapt knowledge load)")


def is_known_host(store: GraphStore, host: str) -> bool:
    """Whether a Platform of the models is named ``host``."""
    rows = store.execute(f"MATCH (p:{S.PLATFORM} {{name: $name}}) RETURN count(p) AS n", {"name": host})
    return bool(rows and rows[0]["n"])


def update_platform(store: GraphStore, *, name: str, time: float, memory_total_mb: float | None = None,
                    memory_free_mb: float | None = None, cpu_load: float | None = None,
                    cpu_cores: int | None = None, online: bool | None = None) -> None:
    """A host's latest figures; UnknownHost for a host the models do not name."""
    figures = _platform_figures(store, name=name, time=time, memory_total_mb=memory_total_mb,
                                memory_free_mb=memory_free_mb, cpu_load=cpu_load, cpu_cores=cpu_cores, online=online)
    rows = store.execute(f"MATCH (p:{S.PLATFORM} {{name: $name}}) SET p += $figures, p.last_seen = $time "
                         "RETURN count(p) AS n", {"name": name, "figures": figures, "time": float(time)})
    if not rows or not rows[0]["n"]:
        raise unknown_host("platform", name)


def update_platforms(store: GraphStore, statuses: Sequence[Mapping[str, Any]]) -> dict[str, NamedQueryError]:
    """Several hosts' latest figures in one store call (``UNWIND``), each checked as :func:`update_platform`
    checks it; at most one per host (the last of a host wins). Returns the refused ones, by host, with why
    (UnknownHost for a host the models do not name: the batch only updates Platforms, never adds one).

    Not a write verb: the knowledge service's status worker writes a batch of host statuses with it.
    """
    rows: dict[str, dict[str, Any]] = {}
    refused: dict[str, NamedQueryError] = {}
    for status in statuses:
        name = status.get("name")
        try:
            figures = _platform_figures(store, load_by_graph=False, **status)
        except NamedQueryError as exc:
            refused[str(name)] = exc
            rows.pop(str(name), None)
            continue
        refused.pop(str(name), None)
        # A load given without cores is bounded by the host's cores in the graph, in the write itself (no read
        # per status on the status worker's path); a host not written is looked up below.
        unbounded = figures.get("cpu_load") if "cpu_cores" not in figures else None
        rows[str(name)] = {"name": name, "figures": figures, "time": float(status["time"]), "load": unbounded}
    if rows:
        written = store.execute(
            f"UNWIND $rows AS row MATCH (p:{S.PLATFORM} {{name: row.name}}) "
            "WITH p, row WHERE row.load IS NULL OR row.load <= 100.0 * coalesce(p.cpu_cores, $max_cores) "
            "SET p += row.figures, p.last_seen = row.time RETURN p.name AS name",
            {"rows": list(rows.values()), "max_cores": MAX_CORES})
        missing = sorted(set(rows) - {str(row["name"]) for row in written})
        if missing:
            cores = {str(r["name"]): r["cores"] for r in store.execute(
                f"UNWIND $names AS name MATCH (p:{S.PLATFORM} {{name: name}}) RETURN p.name AS name, "
                "p.cpu_cores AS cores", {"names": missing})}
            for name in missing:
                if name not in cores:
                    refused[name] = unknown_host("platform", name)
                    continue
                try:
                    _within("platform", cpu_load=(rows[name]["load"], 0, 100 * (cores[name] or MAX_CORES)))
                except NamedQueryError as exc:
                    refused[name] = exc
    return refused


def _platform_figures(store: GraphStore, *, name: str, time: float, memory_total_mb: float | None = None,
                      memory_free_mb: float | None = None, cpu_load: float | None = None,
                      cpu_cores: int | None = None, online: bool | None = None,
                      load_by_graph: bool = True) -> dict[str, Any]:
    """The checked figures of one host's status (NamedQueryError naming the field), None ones left out.

    ``load_by_graph``: a load without cores is checked here against the host's cores in the graph; False:
    the caller bounds it in its own statement (:func:`update_platforms`).
    """
    _check("platform", name=(name, (str,), False), time=(time, _NUM, False),
           memory_total_mb=(memory_total_mb, _NUM, True), memory_free_mb=(memory_free_mb, _NUM, True),
           cpu_load=(cpu_load, _NUM, True), cpu_cores=(cpu_cores, (int,), True), online=(online, (bool,), True))
    _within("platform", time=(time, 0, math.inf), memory_total_mb=(memory_total_mb, 1, MAX_MEMORY_MB),
            cpu_cores=(cpu_cores, 1, MAX_CORES), cpu_load=(cpu_load, 0, 100 * (cpu_cores or MAX_CORES)))
    if memory_free_mb is not None:
        _within("platform", memory_free_mb=(memory_free_mb, 0, memory_total_mb or MAX_MEMORY_MB))
    # A figure given without the one that bounds it is bounded by what the graph holds of the host: free
    # memory by its total, CPU load by its cores (the models' or the last reported).
    load_unbounded = load_by_graph and cpu_load is not None and cpu_cores is None
    if (memory_free_mb is not None and memory_total_mb is None) or load_unbounded:
        rows = store.execute(f"MATCH (p:{S.PLATFORM} {{name: $name}}) "
                             "RETURN p.memory_total_mb AS total, p.cpu_cores AS cores", {"name": name})
        if not rows:
            raise unknown_host("platform", name)
        total, cores = rows[0]["total"], rows[0]["cores"]
        if memory_total_mb is None:
            _within("platform", memory_free_mb=(memory_free_mb, 0, MAX_MEMORY_MB if total is None else total))
        if cpu_cores is None and isinstance(cores, int) and cores >= 1:
            _within("platform", cpu_load=(cpu_load, 0, 100 * cores))
    return {k: v for k, v in {"memory_total_mb": memory_total_mb, "memory_free_mb": memory_free_mb,
                              "cpu_load": cpu_load, "cpu_cores": cpu_cores, "online": online}.items()
            if v is not None}


def set_platform_online(store: GraphStore, *, name: str, online: bool, time: float) -> None:
    """A host came or went (liveliness; the ``platform_online`` write verb). ``last_seen`` moves only when it
    is online."""
    set_platform_liveliness(store, name=name, online=online, time=time)


def set_platform_liveliness(store: GraphStore, *, name: str, online: bool, time: float,
                            heard: float | None = None) -> None:
    """:func:`set_platform_online` for the knowledge service, which also knows when the host's last status was
    heard: a lost host's ``last_seen`` becomes ``heard`` if that is later than what the graph holds (a status
    within the deadband waits for the refresh, and a lost host's waiting status is not written)."""
    _check("platform_online", name=(name, (str,), False), online=(online, (bool,), False), time=(time, _NUM, False),
           heard=(heard, _NUM, True))
    _within("platform_online", time=(time, 0, math.inf), heard=(heard, 0, math.inf))
    rows = store.execute(
        f"MATCH (p:{S.PLATFORM} {{name: $name}}) "
        "SET p.online = $online, p.online_since = $time, "
        "p.last_seen = CASE WHEN $online THEN $time WHEN $heard > coalesce(p.last_seen, 0.0) THEN $heard "
        "ELSE p.last_seen END RETURN count(p) AS n",
        {"name": name, "online": online, "time": float(time), "heard": None if heard is None else float(heard)})
    if not rows or not rows[0]["n"]:
        raise unknown_host("platform_online", name)


def record_process_start(store: GraphStore, *, run_id: str, instance: str, deployment: str, config: str | None,
                         host: str, pid: int, start_time: float) -> None:
    """A started process: its ProcessProfile, PROFILE_OF its deployment, RAN_ON its host, RAN_CONFIG its configuration.

    Relations to a deployment or configuration the graph does not know are left
    out (the profile still records their names); a host the models do not name is
    refused (UnknownHost) and nothing is written.
    """
    _check("process_start", run_id=(run_id, (str,), False), instance=(instance, (str,), False),
           deployment=(deployment, (str,), False), config=(config, (str,), True), host=(host, (str,), False),
           pid=(pid, (int,), False), start_time=(start_time, _NUM, False))
    _within("process_start", pid=(pid, 1, MAX_PID), start_time=(start_time, 0, math.inf))
    params = {"run_id": run_id, "instance": instance, "deployment": deployment, "config": config, "host": host,
              "pid": pid, "start_time": float(start_time)}
    # The common case in one cheap statement: everything it links to is known and the
    # profile is new (MERGE of relations costs about a third more here). Anything
    # else -- a retried start, an unknown host, deployment or configuration -- takes
    # the general, idempotent statement.
    created = store.execute(START_NEW_PROFILE, params)
    if not created or not created[0]["created"]:
        if not is_known_host(store, host):
            raise unknown_host("process_start", host)
        store.execute(_START_ANY, params)


_PROFILE_PROPS = ("run_id: $run_id, instance: $instance, deployment: $deployment, config: $config, "
                  "host: $host, pid: $pid, start_time: $start_time")
START_NEW_PROFILE = f"""MATCH (d:{S.DEPLOYMENT} {{name: $deployment}}), (p:{S.PLATFORM} {{name: $host}}),
      (g:{S.PERCEPTION_GRAPH} {{name: $config}})
OPTIONAL MATCH (old:{S.PROCESS_PROFILE} {{name: $run_id}})
WITH d, p, g WHERE old IS NULL
CREATE (r:{S.PROCESS_PROFILE} {{name: $run_id, {_PROFILE_PROPS}}})
CREATE (r)-[:{S.PROFILE_OF}]->(d), (r)-[:{S.RAN_ON}]->(p), (r)-[:{S.RAN_CONFIG}]->(g)
RETURN count(r) AS created"""
_START_ANY = f"""MERGE (r:{S.PROCESS_PROFILE} {{name: $run_id}})
SET r += {{{_PROFILE_PROPS}}}
WITH r
MATCH (p:{S.PLATFORM} {{name: $host}})
MERGE (r)-[:{S.RAN_ON}]->(p)
WITH r
OPTIONAL MATCH (d:{S.DEPLOYMENT} {{name: $deployment}})
FOREACH (x IN CASE WHEN d IS NULL THEN [] ELSE [d] END | MERGE (r)-[:{S.PROFILE_OF}]->(x))
WITH r
OPTIONAL MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}})
FOREACH (x IN CASE WHEN g IS NULL THEN [] ELSE [g] END | MERGE (r)-[:{S.RAN_CONFIG}]->(x))"""


def record_process_sample(store: GraphStore, *, run_id: str, rss_mb_last: float, rss_mb_mean: float,
                          rss_mb_max: float, cpu_percent_mean: float, received: float | None = None) -> None:
    """A process's memory and CPU figures so far (MERGE: a sample may arrive before its start).

    ``received``: when the knowledge service received the sample (it sets it, over any
    client's value). A sample received after its host was lost means the process outlived
    a partition and reopens its profile; one received before (and applied late, e.g.
    queued while the store restarted) does not: the soak saw such a sample reopen the
    profile of a detector that had died with its agent, for good.
    """
    _check("process_sample", run_id=(run_id, (str,), False), rss_mb_last=(rss_mb_last, _NUM, False),
           rss_mb_mean=(rss_mb_mean, _NUM, False), rss_mb_max=(rss_mb_max, _NUM, False),
           cpu_percent_mean=(cpu_percent_mean, _NUM, False), received=(received, _NUM, True))
    _within("process_sample", received=(received, 0, math.inf), rss_mb_last=(rss_mb_last, 0, MAX_MEMORY_MB),
            rss_mb_mean=(rss_mb_mean, 0, MAX_MEMORY_MB), rss_mb_max=(rss_mb_max, 0, MAX_MEMORY_MB),
            cpu_percent_mean=(cpu_percent_mean, 0, 100 * MAX_CORES))
    store.execute(
        f"MERGE (r:{S.PROCESS_PROFILE} {{name: $run_id}}) "
        "WITH r, (r.end_reason = 'host_lost' AND ($received IS NULL OR r.end_time < $received)) AS reopen "
        "SET r.rss_mb_last = $rss_mb_last, r.rss_mb_mean = $rss_mb_mean, r.rss_mb_max = $rss_mb_max, "
        "r.cpu_percent_mean = $cpu_percent_mean, "
        "r.end_time = CASE WHEN reopen THEN null ELSE r.end_time END, "
        "r.end_reason = CASE WHEN reopen THEN null ELSE r.end_reason END",
        {"run_id": run_id, "rss_mb_last": float(rss_mb_last), "rss_mb_mean": float(rss_mb_mean),
         "rss_mb_max": float(rss_mb_max), "cpu_percent_mean": float(cpu_percent_mean),
         "received": None if received is None else float(received)})


def record_process_reconfigured(store: GraphStore, *, run_id: str, config: str, deployment: str,
                                time: float) -> None:
    """A running process took another configuration in place: its profile now RAN_CONFIG that one
    (and is PROFILE_OF its deployment); ``reconfigured_at`` says since when. Unknown names link nothing."""
    _check("process_reconfigured", run_id=(run_id, (str,), False), config=(config, (str,), False),
           deployment=(deployment, (str,), False), time=(time, _NUM, False))
    _within("process_reconfigured", time=(time, 0, math.inf))
    params = {"run_id": run_id, "config": config, "deployment": deployment, "time": float(time)}
    store.execute(
        f"MATCH (r:{S.PROCESS_PROFILE} {{name: $run_id}}) "
        "SET r.config = $config, r.deployment = $deployment, r.reconfigured_at = $time "
        f"WITH r OPTIONAL MATCH (r)-[e:{S.RAN_CONFIG}|{S.PROFILE_OF}]->() DELETE e", params)
    store.execute(
        f"MATCH (r:{S.PROCESS_PROFILE} {{name: $run_id}}) "
        f"OPTIONAL MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}}) "
        f"FOREACH (x IN CASE WHEN g IS NULL THEN [] ELSE [g] END | MERGE (r)-[:{S.RAN_CONFIG}]->(x)) "
        f"WITH r OPTIONAL MATCH (d:{S.DEPLOYMENT} {{name: $deployment}}) "
        f"FOREACH (x IN CASE WHEN d IS NULL THEN [] ELSE [d] END | MERGE (r)-[:{S.PROFILE_OF}]->(x))", params)


def close_host_profiles(store: GraphStore, *, name: str, time: float) -> None:
    """Host ``name``'s liveliness was lost at ``time``: the profiles it had open then end (``end_reason``
    'host_lost', no exit status).

    Not a write verb: the knowledge service calls it on the token's loss, late if the
    store was away then; a process started after ``time`` (the host back) keeps its
    profile. A process that outlived a partition reopens its profile with its next sample.
    """
    _check("close_host_profiles", name=(name, (str,), False), time=(time, _NUM, False))
    store.execute(
        f"MATCH (r:{S.PROCESS_PROFILE})-[:{S.RAN_ON}]->(:{S.PLATFORM} {{name: $name}}) WHERE r.end_time IS NULL "
        "AND (r.start_time IS NULL OR r.start_time <= $time) SET r.end_time = $time, r.end_reason = 'host_lost'",
        {"name": name, "time": float(time)})


def held_by_processes(store: GraphStore, *, host: str) -> float:
    """The RSS (MiB) the open profiles of ``host``'s processes last recorded; 0 when none."""
    rows = store.execute(
        f"MATCH (r:{S.PROCESS_PROFILE})-[:{S.RAN_ON}]->(:{S.PLATFORM} {{name: $host}}) "
        "WHERE r.end_time IS NULL AND r.rss_mb_last IS NOT NULL RETURN sum(r.rss_mb_last) AS used",
        {"host": host})
    return float(rows[0]["used"] or 0.0) if rows else 0.0


def held_by_processes_of(store: GraphStore, hosts: Sequence[str]) -> dict[str, float]:
    """:func:`held_by_processes` of several hosts in one store call: host -> MiB (0 when none)."""
    rows = store.execute(
        f"UNWIND $hosts AS host MATCH (r:{S.PROCESS_PROFILE})-[:{S.RAN_ON}]->(:{S.PLATFORM} {{name: host}}) "
        "WHERE r.end_time IS NULL AND r.rss_mb_last IS NOT NULL RETURN host, sum(r.rss_mb_last) AS used",
        {"hosts": list(hosts)})
    used = {host: 0.0 for host in hosts}
    used.update({row["host"]: float(row["used"] or 0.0) for row in rows})
    return used


def record_process_end(store: GraphStore, *, run_id: str, end_time: float, exit_status: int | None) -> None:
    """A process ended (``exit_status`` negative for a signal, None when unknown)."""
    _check("process_end", run_id=(run_id, (str,), False), end_time=(end_time, _NUM, False),
           exit_status=(exit_status, (int,), True))
    _within("process_end", end_time=(end_time, 0, math.inf), exit_status=(exit_status, -255, 255))
    store.execute(
        f"MERGE (r:{S.PROCESS_PROFILE} {{name: $run_id}}) SET r.end_time = $end_time, r.exit_status = $exit_status, "
        "r.end_reason = 'exited'",
        {"run_id": run_id, "end_time": float(end_time), "exit_status": exit_status})


SYNTHETIC_SOURCE = "synthetic"  # calibration figures from the synthetic scene; a recording's are frames:NAME


def record_calibration(store: GraphStore, *, config: str, band: str, detection_rate: float,
                       ms_per_frame: float, time: float, condition: str = "all",
                       false_per_frame: float | None = None, false_per_reported: float | None = None,
                       false_rate: float | None = None, source: str = "synthetic") -> None:
    """How well a configuration detected markers in a band and condition: one CALIBRATED relation each, replaced.

    ``source`` says what the figures were measured on: ``synthetic`` (the
    calibration scene) or ``frames:NAME`` (a recording); each source has its own
    relations, side by side.

    False detections have two named figures: ``false_per_frame`` (false markers
    per frame) and ``false_per_reported`` (false markers per marker reported).
    ``false_rate`` is the old name of ``false_per_reported``. ``condition`` is
    ``all`` for the band as a whole, else clean, blur, uneven, window, small.
    """
    _check("calibration", false_rate=(false_rate, _NUM, True), false_per_frame=(false_per_frame, _NUM, True),
           false_per_reported=(false_per_reported, _NUM, True))
    if false_per_reported is None:
        false_per_reported = 0.0 if false_rate is None else false_rate
    if false_per_frame is None:
        false_per_frame = 0.0
    _check("calibration", config=(config, (str,), False), band=(band, (str,), False),
           condition=(condition, (str,), False), source=(source, (str,), False),
           detection_rate=(detection_rate, _NUM, False),
           false_per_frame=(false_per_frame, _NUM, False), false_per_reported=(false_per_reported, _NUM, False),
           ms_per_frame=(ms_per_frame, _NUM, False), time=(time, _NUM, False))
    _within("calibration", ms_per_frame=(ms_per_frame, 0, 3_600_000), time=(time, 0, math.inf))
    for key, rate in (("detection_rate", detection_rate), ("false_rate", false_per_reported),
                      ("false_per_reported", false_per_reported)):
        if not 0.0 <= rate <= 1.0:
            raise NamedQueryError(f"write 'calibration': {key} {rate} is not between 0 and 1")
    if not 0.0 <= false_per_frame <= 1000.0:
        raise NamedQueryError(f"write 'calibration': false_per_frame {false_per_frame} is not between 0 and 1000")
    if not source:
        raise NamedQueryError("write 'calibration': source must not be empty (synthetic or frames:NAME)")
    # Relations written before sources were named are synthetic ones: name them first, so that a synthetic
    # write replaces them and a recording's is written beside them. (Readers take an unnamed one as any source.)
    store.execute(
        f"MATCH (:{S.PERCEPTION_GRAPH} {{name: $config}})-[c:{S.CALIBRATED} {{condition: $condition}}]->"
        f"(:{S.ILLUMINATION_BAND} {{name: $band}}) WHERE c.source IS NULL SET c.source = $synthetic",
        {"config": config, "band": band, "condition": condition, "synthetic": SYNTHETIC_SOURCE})
    rows = store.execute(
        f"MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}}), (b:{S.ILLUMINATION_BAND} {{name: $band}}) "
        f"MERGE (g)-[c:{S.CALIBRATED} {{condition: $condition, source: $source}}]->(b) "
        "SET c.detection_rate = $detection_rate, c.false_per_frame = $false_per_frame, "
        "c.false_per_reported = $false_per_reported, c.ms_per_frame = $ms_per_frame, "
        "c.at = $time RETURN count(c) AS n",
        {"config": config, "band": band, "condition": condition, "source": source,
         "detection_rate": float(detection_rate),
         "false_per_frame": float(false_per_frame), "false_per_reported": float(false_per_reported),
         "ms_per_frame": float(ms_per_frame), "time": float(time)})
    if not rows or not rows[0]["n"]:
        raise NamedQueryError(f"write 'calibration': no detector configuration {config!r} "
                              f"or no illumination band {band!r} in the graph")


MAX_LIVE_FRAMES = 10**9  # a live window's frame counts: beyond any real run


def record_live_rate(store: GraphStore, *, config: str, band: str, detection_rate: float, frames: int,
                     frames_expected: int, frames_seen: int, since: float, time: float, condition: str = "all",
                     run_id: str | None = None, host: str | None = None) -> None:
    """What the running detector of ``config`` finds in ``band`` on this robot: one LIVE_RATE relation per
    configuration, band and condition, replaced by each write (never appended).

    ``frames``: frames of ``config`` in ``band`` the adaptation manager saw; ``frames_expected``: those of
    the window with markers expected (seen within the last second, or the pad in view in final descent);
    ``frames_seen``: of these, those with markers found; ``detection_rate``: markers found per marker
    expected over the window; ``since``..``time``: the window. ``run_id``/``host``: the process measured.
    """
    _check("live_rate", config=(config, (str,), False), band=(band, (str,), False),
           condition=(condition, (str,), False), detection_rate=(detection_rate, _NUM, False),
           frames=(frames, (int,), False), frames_expected=(frames_expected, (int,), False),
           frames_seen=(frames_seen, (int,), False), since=(since, _NUM, False), time=(time, _NUM, False),
           run_id=(run_id, (str,), True), host=(host, (str,), True))
    _within("live_rate", detection_rate=(detection_rate, 0.0, 1.0), frames=(frames, 0, MAX_LIVE_FRAMES),
            frames_expected=(frames_expected, 0, frames), frames_seen=(frames_seen, 0, frames_expected),
            since=(since, 0, time), time=(time, 0, math.inf))
    rows = store.execute(
        f"MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}}), (b:{S.ILLUMINATION_BAND} {{name: $band}}) "
        f"MERGE (g)-[l:{S.LIVE_RATE} {{condition: $condition}}]->(b) "
        "SET l.detection_rate = $detection_rate, l.frames = $frames, l.frames_expected = $frames_expected, "
        "l.frames_seen = $frames_seen, l.since = $since, l.at = $time, l.run_id = $run_id, l.host = $host "
        "RETURN count(l) AS n",
        {"config": config, "band": band, "condition": condition, "detection_rate": float(detection_rate),
         "frames": frames, "frames_expected": frames_expected, "frames_seen": frames_seen,
         "since": float(since), "time": float(time), "run_id": run_id, "host": host})
    if not rows or not rows[0]["n"]:
        raise NamedQueryError(f"write 'live_rate': no detector configuration {config!r} "
                              f"or no illumination band {band!r} in the graph")


def record_decision(store: GraphStore, *, name: str, time: float, trigger: str, inputs_json: str | None = None,
                    query: str | None = None, config: str | None = None, host: str | None = None,
                    duration_ms: float | None = None, outcome: str | None = None) -> None:
    """An adaptation decision: what triggered it, what it chose (CHOSE the configuration, PLACED_ON the host).

    ``host``, when given, must be a Platform of the models (else UnknownHost). Through the knowledge
    service ``time`` is the service's receive time, not the sender's clock."""
    _check("decision", name=(name, (str,), False), time=(time, _NUM, False), trigger=(trigger, (str,), False),
           inputs_json=(inputs_json, (str,), True), query=(query, (str,), True), config=(config, (str,), True),
           host=(host, (str,), True), duration_ms=(duration_ms, _NUM, True), outcome=(outcome, (str,), True))
    _within("decision", time=(time, 0, math.inf), duration_ms=(duration_ms, 0, math.inf))
    if host is not None and not is_known_host(store, host):
        raise unknown_host("decision", host)
    store.execute(
        f"""MERGE (a:{S.ADAPTATION_DECISION} {{name: $name}})
SET a.time = $time, a.trigger = $trigger, a.inputs_json = $inputs_json, a.query = $query,
    a.config = $config, a.host = $host, a.duration_ms = $duration_ms, a.outcome = $outcome
WITH a
OPTIONAL MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}})
FOREACH (x IN CASE WHEN g IS NULL THEN [] ELSE [g] END | MERGE (a)-[:{S.CHOSE}]->(x))
WITH a
OPTIONAL MATCH (p:{S.PLATFORM} {{name: $host}})
FOREACH (x IN CASE WHEN p IS NULL THEN [] ELSE [p] END | MERGE (a)-[:{S.PLACED_ON}]->(x))""",
        {"name": name, "time": float(time), "trigger": trigger, "inputs_json": inputs_json, "query": query,
         "config": config, "host": host, "duration_ms": None if duration_ms is None else float(duration_ms),
         "outcome": outcome})


def update_flight_control(store: GraphStore, *, name: str, time: float, link: bool, armed: bool | None = None,
                          mode: str | None = None, landed_state: str | None = None,
                          battery_pct: float | None = None, battery_v: float | None = None,
                          autopilot_load_pct: float | None = None, last_heartbeat: float | None = None) -> None:
    """The flight controller's state onto the FlightControl component (its run-time properties).

    ``autopilot_load_pct`` is the autopilot's own main-loop load, not the
    component's design-time ``cpu_load`` on the companion computer. A figure
    given as None is unknown now (its stream stopped, the link is lost): its
    property is removed, so the graph never shows a stale value as current.
    """
    _check("flight_state", name=(name, (str,), False), time=(time, _NUM, False), link=(link, (bool,), False),
           armed=(armed, (bool,), True), mode=(mode, (str,), True), landed_state=(landed_state, (str,), True),
           battery_pct=(battery_pct, _NUM, True), battery_v=(battery_v, _NUM, True),
           autopilot_load_pct=(autopilot_load_pct, _NUM, True), last_heartbeat=(last_heartbeat, _NUM, True))
    _within("flight_state", time=(time, 0, math.inf), battery_pct=(battery_pct, 0, 100), battery_v=(battery_v, 0, 1000),
            autopilot_load_pct=(autopilot_load_pct, 0, 100), last_heartbeat=(last_heartbeat, 0, math.inf))
    # null in SET += removes the property (FalkorDB, Neo4j and Memgraph alike)
    figures = {"link": link, "armed": armed, "mode": mode, "landed_state": landed_state,
               "battery_pct": battery_pct, "battery_v": battery_v,
               "autopilot_load_pct": autopilot_load_pct, "last_heartbeat": last_heartbeat}
    # MERGE on the primary label (names are unique per label), then mark it flight control.
    store.execute(f"MERGE (c:{S.COMPONENT} {{name: $name}}) SET c:{S.FLIGHT_CONTROL}, c += $figures, "
                  "c.last_seen = $time", {"name": name, "figures": figures, "time": float(time)})


WRITERS: dict[str, Callable[..., None]] = {
    "platform": update_platform,
    "platform_online": set_platform_online,
    "process_start": record_process_start,
    "process_sample": record_process_sample,
    "process_end": record_process_end,
    "process_reconfigured": record_process_reconfigured,
    "calibration": record_calibration,
    "live_rate": record_live_rate,
    "decision": record_decision,
    "flight_state": update_flight_control,
    "fleet_forget": forget_robot,  # the fleet roster (knowledge/fleet_roster.py)
}


def writer_params(verb: str) -> dict[str, bool]:
    """The parameters of write ``verb``: name -> required."""
    fn = _writer(verb)
    return {p.name: p.default is inspect.Parameter.empty
            for p in inspect.signature(fn).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY}


def run_write(store: GraphStore, verb: str, params: Mapping[str, Any]) -> None:
    """Call write ``verb`` with ``params`` after checking their names (types are checked by the writer)."""
    expected = writer_params(verb)
    for key in params:
        if key not in expected:
            raise NamedQueryError(f"write {verb!r} has no parameter {key!r} (parameters: {', '.join(expected)})")
    for key, required in expected.items():
        if required and key not in params:
            raise NamedQueryError(f"write {verb!r} needs parameter {key!r}")
    WRITERS[verb](store, **params)


def _writer(verb: str) -> Callable[..., None]:
    try:
        return WRITERS[verb]
    except KeyError:
        raise NamedQueryError(f"unknown write {verb!r} (known: {', '.join(WRITERS)})") from None
