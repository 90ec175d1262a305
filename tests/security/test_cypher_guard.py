"""The Cypher subset other robots may send: what passes, what is refused and where."""

from __future__ import annotations

import time

import pytest

from kgadapt.knowledge.cypher_guard import CypherLimits, CypherRefused, check_cypher, writing_clause
from kgadapt.knowledge.queries import QUERIES
from kgadapt.knowledge.store import assert_read_only
from kgadapt.shared.errors import ReadOnlyViolation

ACCEPTED = [
    "MATCH (p:Platform) RETURN p.name, p.memory_free_mb",
    "MATCH (a)-[r:DEPLOYS|RUNS_ON*1..3]->(b) WHERE a.name = $x AND NOT b.y IS NULL "
    "RETURN a, count(*) AS c ORDER BY c DESC SKIP 1 LIMIT 5",
    "UNWIND [1, 2, 3] AS x WITH x WHERE x > 1 RETURN collect(DISTINCT x)",
    "OPTIONAL MATCH (n) RETURN [x IN [1, 2] WHERE x > 1 | x * 2], {a: 1, b: 'x'}, "
    "CASE WHEN 1 = 1 THEN 2 ELSE 3 END, any(y IN [1] WHERE y = 1)",
    "MATCH p = (a)-->(b)<--(c) RETURN nodes(p), a.x[0..2], a:Foo",
    "MATCH (n) WHERE n.name STARTS WITH 'a' OR n.name CONTAINS 'call' RETURN n.set AS load",
    "RETURN 1 AS x LIMIT 1 UNION ALL RETURN 2 AS x LIMIT 1",
    "MATCH (a)--(b) WHERE (a.x) - (b.x) > 1 AND 1 - -2 = 3 RETURN (1) - (-2)",  # arithmetic is still arithmetic
]


@pytest.mark.parametrize("cypher", ACCEPTED)
def test_the_subset_passes(cypher: str) -> None:
    check_cypher(cypher)


@pytest.mark.parametrize("name", sorted(n for n in QUERIES if not n.endswith("_literal")))
def test_every_bounded_named_query_is_inside_the_subset(name: str) -> None:
    check_cypher(QUERIES[name].text_for({}).replace("LIMIT $limit", "LIMIT 20"))  # ours may take a parameter


@pytest.mark.parametrize(
    ("cypher", "named"),
    [
        # The lexical check's bypass: an alias-looking "x.as" hid the CALL.
        ("WITH {as: 1} AS x ORDER BY x.as CALL db.labels() YIELD label RETURN label", "CALL"),
        ("CALL dbms.procedures()", "CALL"),
        ("MATCH (n) RETURN n LIMIT 1 CALL algo.pageRank(NULL, NULL) YIELD node RETURN node", "CALL"),
        ("LOAD CSV FROM 'https://127.0.0.1:9/x' AS r RETURN r", "LOAD"),
        ("RETURN 1 AS x CALL { RETURN 2 }", "CALL"),
        ("MATCH (n) SET n.x = 1 RETURN n", "SET"),
        ("MATCH (n) RETURN n LIMIT 1 CREATE (m)", "CREATE"),
        ("MATCH (n) RETURN n; MATCH (m) DETACH DELETE m", "';'"),
        ("RETURN " + "[" * 22 + "]" * 22 + " AS v", "nested deeper"),
        ("RETURN " + "(" * 9 + "1" + ")" * 9, "nested deeper"),
        ("RETURN " + "- " * 200 + "1", "nested deeper"),
        ("MATCH (a)-[*]->(b) RETURN a", "upper bound"),
        ("MATCH (a)-[*2..]->(b) RETURN a", "upper bound"),
        ("MATCH (a)-[:X*1..100]-(b) RETURN a", "upper bound"),
        ("RETURN range(1, 100000000)", "range()"),
        ("RETURN algo.pageRank()", "algo.pageRank()"),
        ("MATCH (n) WHERE n.name =~ '(a*)*b' RETURN n", "=~"),
        ("MATCH (n) WHERE (n)-->() RETURN n", "pattern predicates"),
        # Undirected ones read as arithmetic ((a) minus minus (b), (a) minus a list) until refused by name.
        ("MATCH (a), (b) WHERE (a)--(b) RETURN a", "pattern predicates"),
        ("MATCH (a), (b) WHERE NOT (a)-[:DEPLOYS]-(b) RETURN a", "pattern predicates"),
        ("MATCH (a), (b) RETURN (a)-[]-(b) AS linked", "pattern predicates"),
        ("MATCH (n)", "expected MATCH, OPTIONAL MATCH, UNWIND, WITH or RETURN"),
        ("RETURN 1 +", "end of the query"),
        ("RETURN 'x' # 1", "unexpected character"),
        ("   ", "empty"),
    ],
)
def test_outside_the_subset_is_refused_naming_the_offence(cypher: str, named: str) -> None:
    with pytest.raises(CypherRefused) as refused:
        check_cypher(cypher)
    assert named in str(refused.value)
    assert isinstance(refused.value, ReadOnlyViolation)  # callers that knew only the old error still refuse


def test_the_literal_paper_queries_are_not_for_other_robots() -> None:
    for name in ("fig4_literal", "fig5_literal"):
        with pytest.raises(CypherRefused, match="upper bound"):
            check_cypher(QUERIES[name].text_for({}).replace("LIMIT $limit", "LIMIT 20"))  # ours may take a parameter


def test_size_is_bounded_before_parsing() -> None:
    limits = CypherLimits()
    with pytest.raises(CypherRefused, match="characters"):
        check_cypher("RETURN '" + "x" * limits.max_chars + "'")
    with pytest.raises(CypherRefused, match="tokens"):
        check_cypher("RETURN " + ", ".join(["1"] * limits.max_tokens))
    # The 16 KB nested literal that held a FalkorDB thread for 10 minutes: refused at once.
    started = time.perf_counter()
    with pytest.raises(CypherRefused):
        check_cypher("RETURN " + "[" * 8000 + "]" * 8000, limits=CypherLimits(max_chars=20000, max_tokens=20000))
    assert time.perf_counter() - started < 1.0


def test_our_own_read_only_check_works_on_tokens() -> None:
    assert writing_clause("WITH {as: 1} AS x ORDER BY x.as CALL db.labels() YIELD label RETURN label") == "CALL"
    assert writing_clause("MATCH (n) RETURN n.set AS load, {call: 1} AS m, 'DELETE' AS s") is None
    with pytest.raises(ReadOnlyViolation, match="LOAD"):
        assert_read_only("LOAD CSV FROM 'file:///etc/passwd' AS r RETURN r")


def test_rows_are_bounded() -> None:
    limits = CypherLimits()
    assert check_cypher("MATCH (n) RETURN n").endswith(f"LIMIT {limits.max_rows}")
    assert check_cypher("MATCH (n) RETURN n LIMIT 5") == "MATCH (n) RETURN n LIMIT 5"
    with pytest.raises(CypherRefused, match="LIMIT must be a whole number"):
        check_cypher("MATCH (n) RETURN n LIMIT 100000000")
    with pytest.raises(CypherRefused, match="LIMIT must be a whole number"):
        check_cypher("MATCH (n) RETURN n LIMIT $many")
    with pytest.raises(CypherRefused, match="UNION"):
        check_cypher("RETURN 1 AS x UNION RETURN 2 AS x")
