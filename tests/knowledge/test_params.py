"""One parameter check for every backend, and FalkorDB's parameter header written by us."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from kgadapt.knowledge.falkordb_store import params_header
from kgadapt.knowledge.params import MAX_DEPTH, check_params
from kgadapt.shared.errors import MessageError, QueryError, StoreTimeout

HOSTILE = ['a"b', "it's", "back\\slash", "ends with \\", '\\"', "\\\\\"", "x\ny\tz\r", "literal \\n", "ü€😀",
           "a'}) DETACH DELETE n //", '" RETURN 1 //', "$param", "CYPHER a=1 ", "`k`", ""]


def test_the_header_quotes_and_escapes_every_kind_of_value():
    header = params_header({"s": 'say "hi" \\o/', "n": None, "t": True, "f": False, "i": -3, "x": 1e20,
                            "l": [1, "a", [0.5]], "m": {"a b": {"c": None}}, "u": (1, 2)})
    assert header == ('CYPHER s=\'say "hi" \\\\o/\' n=null t=true f=false i=-3 x=1e20 '
                      "l=[1, 'a', [0.5]] m={`a b`: {`c`: null}} u=[1, 2] ")
    assert params_header(None) == params_header({}) == ""


@pytest.mark.parametrize("params, message", [
    ({"x": float("inf")}, r"parameter 'x': inf is not a finite number"),
    ({"x": [1.0, float("nan")]}, r"parameter 'x': nan is not a finite number"),
    ({"x": b"raw"}, r"parameter 'x': a bytes is not a graph value"),
    ({"x": {"k": object()}}, r"parameter 'x': a object is not a graph value"),
    ({"x": "nul\x00"}, r"parameter 'x': a NUL character"),
    ({"x": 2**63}, r"parameter 'x': 9223372036854775808 does not fit in 64 bits"),
    ({"x": {1: "a"}}, r"parameter 'x': map key 1 is not a string"),
    ({"x-y": 1}, r"bad parameter name 'x-y'"),
    ({"1x": 1}, r"bad parameter name '1x'"),
    ({"x": [[[[[[[[[[1]]]]]]]]]]}, rf"parameter 'x': nested more than {MAX_DEPTH} deep"),
    # The same inside maps and rows, which the check takes by exact type first.
    ({"rows": [{"free": 1.0}, {"free": float("-inf")}]}, r"parameter 'rows': -inf is not a finite number"),
    ({"x": {"k": -(2**63) - 1}}, r"parameter 'x': -9223372036854775809 does not fit in 64 bits"),
    ({"x": {"a": {"b": {"c": {"d": {"e": {"f": {"g": {"h": {"i": 1}}}}}}}}}},
     rf"parameter 'x': nested more than {MAX_DEPTH} deep"),
])
def test_what_no_store_can_take_is_refused_naming_the_parameter(params, message):
    with pytest.raises(QueryError, match=message):
        check_params(params)
    with pytest.raises(QueryError, match=message):
        params_header(params)


def test_the_service_gets_the_same_check_with_its_own_error_and_words():
    with pytest.raises(MessageError, match=r"^cypher: parameter 'x': nan is not a finite number$"):
        check_params({"x": float("nan")}, what="cypher", error=MessageError)


def test_the_check_gives_plain_values():
    clean = check_params({"i": np.int64(7), "f": np.float32(0.5), "t": (1, (2,)), "m": {"k": [True]},
                          "b": True, "o": collections.OrderedDict(a=np.float64(2.0))})
    assert clean == {"i": 7, "f": 0.5, "t": [1, [2]], "m": {"k": [True]}, "b": True, "o": {"a": 2.0}}
    assert type(clean["i"]) is int and type(clean["f"]) is float and clean["b"] is True
    assert type(clean["o"]) is dict and type(clean["o"]["a"]) is float


def test_map_keys_falkordb_cannot_write_are_refused_by_the_header_only():
    assert check_params({"m": {"a`b": 1, "": 2}}) == {"m": {"a`b": 1, "": 2}}  # Bolt servers take them
    with pytest.raises(QueryError, match="map key 'a`b' cannot be written for FalkorDB"):
        params_header({"m": {"a`b": 1}})


def test_hostile_values_round_trip_through_a_batch_and_a_single_statement(resp_store):
    values = [*HOSTILE, None, True, False, 0, -(2**63), 2**63 - 1, 0.1, 1e-7, 1e20, -0.0, 1.5e300,
              [1, "a\\\"", [None, 2.5]], {"k": 'v"\\', "n": [1, {"deep": "x'y"}]}]
    storable = [v for v in values if not isinstance(v, (list, dict))] + [["a\\\"", "", "x'y"]]  # property values
    resp_store.execute_atomic([("CREATE (:P {i: $i, v: $v})", {"i": i, "v": v}) for i, v in enumerate(storable)])
    rows = resp_store.execute("MATCH (p:P) RETURN p.i AS i, p.v AS v ORDER BY i", read_only=True)
    assert [r["v"] for r in rows] == storable
    for value in values:
        assert resp_store.execute("RETURN $v AS v", {"v": value}, read_only=True) == [{"v": value}]


def test_a_batch_with_one_bad_parameter_sends_nothing(resp_store):
    with pytest.raises(QueryError, match="parameter 'v'"):
        resp_store.execute_atomic([("CREATE (:P {v: $v})", {"v": 1}), ("CREATE (:P {v: $v})", {"v": float("inf")})])
    assert resp_store.execute("MATCH (p:P) RETURN count(p) AS n") == [{"n": 0}]


def test_backends_declare_what_they_guarantee(resp_store, bolt_store):
    resp, bolt = resp_store.capabilities, bolt_store.capabilities
    assert (resp.transactions, resp.timeouts, resp.read_only, resp.thread_safe, resp.sandbox) == \
           (True, True, "store", True, True)
    assert (bolt.read_only, bolt.thread_safe, bolt.sandbox) == ("check", True, False)


def test_a_query_the_store_stops_at_its_timeout_is_a_store_timeout(resp_store):
    resp_store.execute("UNWIND range(1, 2000) AS i CREATE (:N {i: i})")
    with pytest.raises(StoreTimeout, match="timed out"):  # four million pairs: far more than 1 ms of work
        resp_store.execute("MATCH (a:N), (b:N) WHERE a.i * b.i % 7 = 3 RETURN count(*) AS n",
                           read_only=True, timeout_ms=1)
