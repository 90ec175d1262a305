"""Cypher injection is inert: every value a caller or a model gives is stored and matched verbatim.

A corpus of hostile strings goes through every string parameter of every
named query (knowledge/queries.py), every run-time write verb
(knowledge/runtime.py) and every text field of the model notations
(knowledge/importers/). The oracle is differential: a hostile string must
behave exactly like a plain placeholder in the same place (the same rows,
the same graph change with the placeholder replaced by the string, stored
byte for byte), or be refused with a KgadaptError that leaves the graph as
it was. Named queries and writes run on every backend (FalkorDB over RESP
and over Bolt; Memgraph when given); FalkorDB's Bolt listener splices string
parameters into the query text, so the Bolt store refuses values with a
quote or a backslash: that refusal, too, must leave the graph unchanged.
"""

from __future__ import annotations

import inspect
import json
import shlex
from pathlib import Path
from typing import Any, Callable

import pytest

from kgadapt.knowledge import queries, runtime
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.loader import load_models
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import KgadaptError, ModelError, NamedQueryError, StoreError
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.security.conftest import wait_for

CORPUS = [
    "'",
    '"',
    "\\",
    "' OR 1=1 //",
    '" OR "1"="1',
    "x'}) DETACH DELETE n //",
    "}) DETACH DELETE n //",
    'x"}) MATCH (m) DETACH DELETE m //',
    "') MATCH (m) SET m.pwned = true RETURN m //",
    "\\' OR 1=1 --",
    '\\"}) CREATE (:Evil) //',
    "a\\\\'b\\",
    "$name",
    "$feature $config {name: $name}",
    "`n`) DETACH DELETE n //",
    "` OR 1=1 `",
    "line one\nMATCH (n) DETACH DELETE n",
    "tab\there\r\nCR",
    "名前 ünïcødé ☃ 🚁",
    "\u202e\u200b bidi and zero-width",
    "/* comment */ RETURN 1 //",
    "UNION MATCH (n) DETACH DELETE n RETURN n",
    "; CREATE (:Evil)",
    "CALL db.labels()",
    "{python} $(touch /tmp/kgadapt-pwned) `id`",
    "a" * 2000 + "') DETACH DELETE n //",
]
NUL = "nul\x00byte"  # FalkorDB reads query text as a C string: a NUL ends it (tests of their own below)
PLAIN = "zz_plain_value"


def splices(store: GraphStore) -> bool:
    return bool(getattr(store, "_splices_params", False))


def backend_refuses(store: GraphStore, value: str) -> bool:
    """The Bolt stand-in splices parameters into the query text, so its store refuses ' and \\."""
    return splices(store) and ("'" in value or "\\" in value)


def snapshot(store: GraphStore) -> list[str]:
    """The whole graph, canonical: nodes with labels and properties, relations with their ends' names."""
    nodes = store.execute("MATCH (n) RETURN labels(n) AS l, properties(n) AS p", read_only=True)
    relations = store.execute("MATCH (a)-[r]->(b) RETURN labels(a) AS al, a.name AS a, type(r) AS t, "
                              "properties(r) AS p, labels(b) AS bl, b.name AS b", read_only=True)
    return sorted(_canonical(row) for row in nodes + relations)


def _canonical(value: Any) -> str:
    return json.dumps(_parsed(value), sort_keys=True, ensure_ascii=False)


def _parsed(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: (_parsed(json.loads(v)) if k == "config_json" and isinstance(v, str) else _parsed(v))
                for k, v in value.items()}
    if isinstance(value, list):
        return [_parsed(v) for v in value]
    return value


def substituted(value: Any, plain: str, hostile: str) -> Any:
    """``value`` with ``plain`` replaced by ``hostile`` in every string (also map keys; names made of names)."""
    if isinstance(value, str):
        return value.replace(plain, hostile)
    if isinstance(value, list):
        return [substituted(v, plain, hostile) for v in value]
    if isinstance(value, dict):
        return {substituted(k, plain, hostile): substituted(v, plain, hostile) for k, v in value.items()}
    return value


def substituted_snapshot(store_rows: list[str], plain: str, hostile: str) -> list[str]:
    return sorted(json.dumps(substituted(json.loads(row), plain, hostile), sort_keys=True, ensure_ascii=False)
                  for row in store_rows)


def outcome(call: Callable[[], Any]) -> tuple[str, Any]:
    try:
        return "ok", call()
    except KgadaptError as exc:
        return "refused", exc


# -- named queries ---------------------------------------------------------------------------------------

MODELS = Path(__file__).resolve().parents[2] / "knowledge" / "models"


@pytest.fixture
def known_graph(store):
    """The shipped models plus run-time facts, so that every query has something it could leak."""
    load_models(store, [MODELS])
    runtime.update_platform(store, name="onboard", time=1.0, memory_total_mb=1024.0, memory_free_mb=900.0,
                            cpu_load=10.0, online=True)
    runtime.record_process_start(store, run_id="run1", instance="i1", deployment="detector_day",
                                 config="marker_detection_day", host="onboard", pid=42, start_time=1.0)
    runtime.record_process_sample(store, run_id="run1", rss_mb_last=50.0, rss_mb_mean=40.0, rss_mb_max=60.0,
                                  cpu_percent_mean=20.0)
    runtime.record_decision(store, name="dec1", time=2.0, trigger="startup", config="marker_detection_day",
                            host="onboard")
    runtime.record_calibration(store, config="marker_detection_day", band="day", detection_rate=0.9,
                               ms_per_frame=5.0, time=2.0)
    runtime.record_live_rate(store, config="marker_detection_day", band="day", detection_rate=0.5, frames=40,
                             frames_expected=30, frames_seen=20, since=1.0, time=2.0, run_id="run1", host="onboard")
    return store


# Values the shipped models know, so a query's other parameters are not what keeps its answer empty.
REAL = {"feature": "MarkerDetection", "platform": "remote", "config": "marker_detection_day", "name": "detector_day",
        "threshold_mb": 1000.0, "limit": 20, "limit_pct": 80.0, "condition": "all", "band": "day", "penalty": 1.0,
        "max_ms": 1000.0, "from": "detector_day", "to": "detector_dark", "host": "onboard",
        "standby": "standby", "run_id": "r1", "camera": "camera", "site": "demo-hall", "announce": "quad2",
        "zid": "ab12", "routers": "ab12,cd34", "source": "synthetic", "deployment": "detector_day", "whole": "all",
        "blur": "blur"}


def string_params() -> list[tuple[str, str]]:
    return [(q.name, p) for q in queries.QUERIES.values() for p, spec in q.params.items() if spec.type == "str"]


def test_every_named_query_has_string_parameters_to_attack():
    covered = {name for name, _ in string_params()}
    assert len(string_params()) >= 15
    assert covered == {q.name for q in queries.QUERIES.values() if any(p.type == "str" for p in q.params.values())}


def test_hostile_strings_in_every_named_query_parameter_behave_like_an_unknown_name(known_graph):
    store = known_graph
    before = snapshot(store)
    answered = 0
    for name, param in string_params():
        base = {p: REAL[p] for p in queries.QUERIES[name].params}
        expected = queries.run_named(store, name, {**base, param: PLAIN})
        for value in CORPUS:
            kind, result = outcome(lambda: queries.run_named(store, name, {**base, param: value}))
            if kind == "refused":
                assert backend_refuses(store, value), f"{name}.{param}={value!r:.60} refused: {result}"
                assert isinstance(result, StoreError)
            else:
                assert result == expected, f"{name}.{param}={value!r:.60} found rows a plain name does not"
                answered += 1
    assert snapshot(store) == before
    assert answered == len(string_params()) * sum(not backend_refuses(store, v) for v in CORPUS)


def test_a_node_named_with_a_hostile_string_is_found_by_exactly_that_string(store):
    for i, value in enumerate(CORPUS):
        params = {"name": value, "config": f"{value}-graph"}
        kind, result = outcome(lambda: store.execute(
            f"CREATE (:{S.DEPLOYMENT} {{name: $name, executable: $name, arguments: [$name], environment: []}})"
            f"-[:{S.DEPLOYS}]->(:{S.PERCEPTION_GRAPH} {{name: $config}})", params))
        if kind == "refused":
            assert backend_refuses(store, value), result
            continue
        rows = queries.run_named(store, "deployment", {"name": value})
        assert rows == [{"name": value, "kind": None, "executable": value, "arguments": [value], "environment": [],
                         "platforms": [], "deploys": [f"{value}-graph"]}]
        assert queries.run_named(store, "detector_config", {"config": f"{value}-graph"})[0]["deployment"] == value
    count = store.execute("MATCH (n) RETURN count(n) AS n", read_only=True)[0]["n"]
    assert count == 2 * sum(not backend_refuses(store, v) for v in CORPUS)


# -- run-time writes ---------------------------------------------------------------------------------------

NUMBERS = {"time": 5.0, "memory_total_mb": 100.0, "memory_free_mb": 50.0, "cpu_load": 3.0, "cpu_cores": 2,
           "pid": 4242, "start_time": 6.0, "rss_mb_last": 1.0, "rss_mb_mean": 2.0, "rss_mb_max": 3.0,
           "cpu_percent_mean": 4.0, "end_time": 7.0, "exit_status": 0, "detection_rate": 0.5, "false_rate": 0.1,
           "false_per_frame": 0.2, "false_per_reported": 0.1,
           "ms_per_frame": 8.0, "duration_ms": 9.0, "battery_pct": 80.0, "battery_v": 12.0,
           "autopilot_load_pct": 30.0, "last_heartbeat": 10.0, "received": 11.0,
           "frames": 12, "frames_expected": 10, "frames_seen": 5, "since": 4.0}
FLAGS = {"online": True, "link": True, "armed": False}


def writer_arguments(verb: str, value: str) -> dict[str, Any]:
    """Every parameter of ``verb``: strings all ``value``, numbers and flags fixed."""
    params: dict[str, Any] = {}
    for p in inspect.signature(runtime.WRITERS[verb]).parameters.values():
        if p.kind is not inspect.Parameter.KEYWORD_ONLY:
            continue
        params[p.name] = NUMBERS[p.name] if p.name in NUMBERS else FLAGS[p.name] if p.name in FLAGS else value
    return params


def graph_named(store: GraphStore, value: str) -> None:
    """One node of every label a writer may link to, each named ``value``."""
    store.execute(
        f"CREATE (:{S.DEPLOYMENT} {{name: $v}}), (:{S.PERCEPTION_GRAPH} {{name: $v}}), (:{S.PLATFORM} {{name: $v}}), "
        f"(:{S.ILLUMINATION_BAND} {{name: $v}}), (:{S.COMPONENT} {{name: 'camera'}}), "
        f"(:{S.PLATFORM} {{name: 'other'}})", {"v": value})


def write_effect(store: GraphStore, verb: str, value: str) -> tuple[str, Any, list[str]]:
    store.clear()
    graph_named(store, value)
    kind, result = outcome(lambda: runtime.run_write(store, verb, writer_arguments(verb, value)))
    return kind, result, snapshot(store)


@pytest.mark.parametrize("verb", sorted(runtime.WRITERS))
def test_hostile_strings_in_every_write_verb_are_stored_verbatim_and_change_nothing_else(store, verb):
    kind, result, plain_graph = write_effect(store, verb, PLAIN)
    assert kind == "ok", result
    stored = 0
    for value in CORPUS:
        if backend_refuses(store, value):
            store.clear()
            store.execute(f"CREATE (:{S.PLATFORM} {{name: 'sentinel'}})")
            before = snapshot(store)
            kind, result = outcome(lambda: runtime.run_write(store, verb, writer_arguments(verb, value)))
            assert kind == "refused" and isinstance(result, StoreError), f"{verb} took {value!r:.60}"
            assert snapshot(store) == before
            continue
        kind, result, graph = write_effect(store, verb, value)
        assert kind == "ok", f"{verb} with {value!r:.60}: {result}"
        assert graph == substituted_snapshot(plain_graph, PLAIN, value), f"{verb} with {value!r:.60}"
        stored += 1
    assert stored == sum(not backend_refuses(store, v) for v in CORPUS)


@pytest.mark.parametrize("verb", sorted(runtime.WRITERS))
def test_a_hostile_string_where_a_write_expects_a_number_is_refused_naming_the_parameter(resp_store, verb):
    graph_named(resp_store, PLAIN)
    before = snapshot(resp_store)
    numeric = [p for p in writer_arguments(verb, PLAIN) if p in NUMBERS or p in FLAGS]
    assert numeric or verb == "fleet_forget"  # its one parameter is a robot's name
    for param in numeric:
        with pytest.raises(NamedQueryError, match=repr(param)):
            runtime.run_write(resp_store, verb, {**writer_arguments(verb, PLAIN), param: "1; DETACH DELETE n"})
    with pytest.raises(NamedQueryError, match="no parameter"):
        runtime.run_write(resp_store, verb, {**writer_arguments(verb, PLAIN), "name}) DETACH DELETE n //": 1})
    assert snapshot(resp_store) == before


# -- NUL: FalkorDB reads the query text as a C string ------------------------------------------------------


def test_a_nul_byte_in_a_query_or_write_value_is_refused_and_changes_nothing(store):
    store.execute(f"CREATE (:{S.PLATFORM} {{name: 'sentinel'}})")
    before = snapshot(store)
    outcomes = {verb: outcome(lambda: runtime.run_write(store, verb, writer_arguments(verb, NUL)))
                for verb in sorted(runtime.WRITERS)}
    outcomes["query deployment"] = outcome(lambda: queries.run_named(store, "deployment", {"name": NUL}))
    accepted = sorted(what for what, (kind, _) in outcomes.items() if kind == "ok")
    unchanged = snapshot(store) == before
    assert accepted == []
    assert all(isinstance(result, StoreError) for _, result in outcomes.values())
    assert unchanged


def test_a_model_the_store_refuses_half_way_through_the_batch_is_not_loaded_at_all(resp_store, tmp_path):
    assert write_models(tmp_path, "unit_environment", NUL)
    resp_store.execute(f"CREATE (:{S.PLATFORM} {{name: 'sentinel'}})")
    before = snapshot(resp_store)
    with pytest.raises(KgadaptError):
        load_models(resp_store, [tmp_path])
    assert snapshot(resp_store) == before


# -- the same over the wire ------------------------------------------------------------------------------


def test_hostile_strings_sent_over_zenoh_to_the_knowledge_service_come_back_verbatim(resp_store):
    S.ensure_indexes(resp_store)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(ZenohSettings(mode="router", listen=(endpoint,)))
    service = KnowledgeService(resp_store, ServiceSettings(robot="injected"))
    service.setup(server)
    session = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
    try:
        client = KnowledgeClient(session, "injected", timeout=3.0)
        wait_for(lambda: client.query("platforms", {}) == [], 5, "the service to answer")
        for i, value in enumerate(CORPUS):
            kind, result = outcome(lambda: client.write("decision", {"name": value, "time": float(i),
                                                                     "trigger": value, "inputs_json": value}))
            assert kind == "ok", f"{value!r:.60}: {result}"
            rows = client.cypher(f"MATCH (a:{S.ADAPTATION_DECISION} {{name: $v}}) RETURN a.trigger AS t, "
                                 "a.inputs_json AS j", {"v": value})
            assert rows == [{"t": value, "j": value}]
            assert client.query("deployment", {"name": value}) == []
        decisions = client.query("decisions", {"limit": 100})
        assert sorted(d["name"] for d in decisions) == sorted(CORPUS)
        assert resp_store.execute(f"MATCH (n) WHERE NOT n:{S.FLEET_ROBOT} RETURN count(n) AS n")[0]["n"] == len(
            decisions)
        assert [r["robot"] for r in client.query("fleet_roster", {})] == ["injected"]  # the roster: itself only
    finally:
        session.close()
        service.shutdown()
        server.close()


# -- model files -----------------------------------------------------------------------------------------


def dsl(value: str) -> str:
    """``value`` as a string literal of the block notations (knowledge/importers/tokens.py)."""
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t") + '"'


def raw(value: str) -> str | None:
    """``value`` as the rest of a ``key: value`` / ``Key=value`` line, when a line can hold it at all."""
    if value != value.strip() or len((value + "x").splitlines()) != 1:
        return None
    return value


def unit_raw(value: str) -> str | None:
    """Like :func:`raw` for a unit file, where a line ending in a backslash continues on the next one."""
    return None if value.endswith("\\") else raw(value)


def word(value: str) -> str | None:
    """``value`` as one shell-like word (shlex quoting), when a line can hold it."""
    quoted = shlex.quote(value)
    return quoted if len((quoted + "x").splitlines()) == 1 else None


# slot -> (default, how to write a value there, what the graph stores for value v)
SLOTS: dict[str, tuple[str, Callable[[str], str | None], Callable[[str], str]]] = {
    "feature_name": ("zz_feature", dsl, str),
    "feature_description": ("zz feature text", dsl, str),
    "band_description": ("zz band text", dsl, str),
    "component_name": ("zz_camera", dsl, str),
    "component_description": ("zz camera text", dsl, str),
    "component_property": ("zz note", dsl, str),
    "port_name": ("zz_out", dsl, str),
    "data_type": ("zz_image", dsl, str),
    "dictionary": ("4X4_50", lambda v: dsl("DICT_" + v), lambda v: "DICT_" + v),  # OpenCV's names only
    "detector_parameter": ("adaptiveThreshConstant", dsl, str),
    "graph_name": ("zz_graph", dsl, str),
    "platform_name": ("zz_platform", dsl, str),
    "platform_description": ("zz platform text", dsl, str),
    "deploy_description": ("zz deploy text", raw, str),
    "deploy_executable": ("zz_exe", word, str),
    "deploy_argument": ("zz_arg", word, str),
    "deploy_environment": ("zz_env", lambda v: word("PROBE=" + v), lambda v: "PROBE=" + v),
    "unit_description": ("zz unit text", unit_raw, str),
    "unit_argument": ("zz_unit_arg", word, str),
    "unit_environment": ("zz_unit_env", lambda v: word("UNIT=" + v), lambda v: "UNIT=" + v),
}
# Names a deployment refers to go through a strict name check, and a detector parameter must be an
# attribute of cv2.aruco.DetectorParameters: every hostile string is refused there.
STRICT = {"graph_name", "platform_name"}
REFUSE_ALL = STRICT | {"detector_parameter", "dictionary"}

TEMPLATES = {
    "features.features": """
feature {feature_name}
  description {feature_description}
end
band day
  description {band_description}
  min_level 0
  max_level 255
end
""",
    "components.rpsl": """
rpsl.sensor_component do
  name {component_name}
  description {component_description}
  property "note", {component_property}
  add_port :out, {port_name}, {data_type}
  resolution 640, 480
  memory_demand_mb 10
end
rpsl.processing_component do
  name "detector"
  add_port :in, "in", {data_type}
  memory_demand_mb 20
  dictionary {dictionary}
  parameter {detector_parameter}, 7
end
rpsl.perception_graph do
  name {graph_name}
  realizes {feature_name}
  suited_for :day
  connect {component_name}, {port_name}, "detector", "in"
end
""",
    "hosts.platform": """
platform {platform_name}
  description => {platform_description}
  processor cpu
    cores => 2
  end cpu
  memory ram
    size_mb => 512
  end ram
end
""",
    "probe.deploy": """
name: probe
description: {deploy_description}
deploys: {graph_name}
executable: {deploy_executable}
arguments: -m json.tool {deploy_argument}
environment: {deploy_environment}
executable_on: {platform_name}
""",
    "unit.service": """
[Unit]
Description={unit_description}

[Service]
ExecStart={{python}} -m http.server {unit_argument}
Environment={unit_environment}

[X-Kgadapt]
Deploys={graph_name}
ExecutableOn={platform_name}
""",
}


def write_models(directory: Path, slot: str, value: str) -> bool:
    """The template models with ``value`` in ``slot`` (defaults elsewhere); False when it cannot be written."""
    texts: dict[str, str] = {}
    for name, (default, encode, _) in SLOTS.items():
        encoded = encode(value if name == slot else default)
        if encoded is None:
            return False
        # Strict names are written bare where a name list expects them (deploys:, ExecutableOn=).
        texts[name] = encoded
    bare = {name: (value if name == slot else SLOTS[name][0]) for name in STRICT}
    for file, template in TEMPLATES.items():
        fields = dict(texts)
        if file.endswith((".deploy", ".service")):
            fields.update(bare)
        (directory / file).write_text(template.format(**fields), encoding="utf-8")
    return True


def test_the_model_templates_load_with_their_defaults(resp_store, tmp_path):
    assert write_models(tmp_path, "feature_name", "zz_feature")
    report = load_models(resp_store, [tmp_path])
    assert report.labels[S.DEPLOYMENT] == 2 and report.labels[S.FEATURE] == 1


@pytest.mark.parametrize("slot", sorted(SLOTS))
def test_hostile_strings_in_every_model_field_are_stored_verbatim_or_refused_leaving_the_graph_alone(
    resp_store, tmp_path, slot
):
    default, _, stored_as = SLOTS[slot]
    store = resp_store
    assert write_models(tmp_path, slot, default)
    store.clear()
    load_models(store, [tmp_path])
    plain_graph = snapshot(store)
    verbatim, refused = [], []
    for value in CORPUS:
        if not write_models(tmp_path, slot, value):
            continue  # the notation cannot hold it on one line: nothing to load
        store.clear()
        store.execute(f"CREATE (:{S.PLATFORM} {{name: 'sentinel'}})")
        before = snapshot(store)
        kind, result = outcome(lambda: load_models(store, [tmp_path]))
        if kind == "refused":
            assert isinstance(result, ModelError), result
            assert snapshot(store) == before, f"{slot}={value!r:.60} was refused but changed the graph"
            refused.append(value)
            continue
        store.execute(f"MATCH (n:{S.PLATFORM} {{name: 'sentinel'}}) DELETE n")
        expected = substituted_snapshot(plain_graph, stored_as(default), stored_as(value))
        assert snapshot(store) == expected, f"{slot}={value!r:.60} did not land verbatim"
        verbatim.append(value)
    if slot in REFUSE_ALL:
        assert verbatim == []
    else:
        assert len(verbatim) >= 3, f"{slot}: only {verbatim} stored; the test proves little"
    assert not any("'" in v or "\\" in v for v in verbatim)  # refused by every importer (Bolt stores splice them)
