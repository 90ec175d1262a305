"""Other robots' questions cannot starve the robot's own knowledge path.

A real `kgadapt knowledge serve` on the shipped models; four outsiders (tests/
security/outsider.py, written from CONTRACTS.md) ask heavy and hostile
questions in parallel while the robot's own software asks `placement` on
its own key. Asserted: every own question is answered, correctly; the heavy
questions are stopped at their hard limit; the hostile ones are refused
before they reach a store; LOAD CSV opens no connection.
"""

from __future__ import annotations

import socket
import statistics
import subprocess
import sys
import threading
import time

from kgadapt.bench import table1
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.store import open_store
from kgadapt.shared.errors import KgadaptError
from tests.conftest import REPO
from tests.security.outsider import Outsider
from tests.support import wait_for

DARK = "marker_detection_dark"
HEAVY = "MATCH (a), (b), (c), (d), (e) RETURN count(*) AS n"  # 33^5 rows: seconds of work


def _where(rows: list[dict]) -> list[tuple]:
    """What placement decides (free memory moves with the host's status)."""
    return [(r["config"], r["deployment"], r["platform"]) for r in rows]


def _closed_listener() -> tuple[socket.socket, list[socket.socket]]:
    """A TCP listener counting who connects: LOAD CSV must never reach it."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    listener.settimeout(0.1)
    accepted: list[socket.socket] = []

    def accept():
        while listener.fileno() != -1:
            try:
                accepted.append(listener.accept()[0])
            except OSError:
                continue

    threading.Thread(target=accept, daemon=True).start()
    return listener, accepted


def test_four_hostile_askers_in_parallel_leave_the_robots_own_placement_answered(loopback_robot):
    served = loopback_robot()
    robot = served["robot"]
    own = KnowledgeClient(served["session"](), robot, timeout=2.0, own=True)
    expected = wait_for(lambda: own.query("placement", {"config": DARK}) or None, 10, "first own placement")
    listener, accepted = _closed_listener()
    port = listener.getsockname()[1]
    attacks = {
        "heavy": lambda o: o.cypher(HEAVY),
        "literal": lambda o: o.query("fig5_literal"),
        "nested": lambda o: o.cypher("RETURN " + "[" * 22 + "]" * 22 + " AS v"),
        "bypass": lambda o: o.cypher("WITH {as: 1} AS x ORDER BY x.as CALL db.labels() YIELD label RETURN label"),
        "load_csv": lambda o: o.cypher(f"LOAD CSV FROM 'http://127.0.0.1:{port}/x' AS r RETURN r"),
        "flood": lambda o: o.query("placement", {"config": DARK}),
    }
    answers: dict[str, list] = {name: [] for name in attacks}
    stop = threading.Event()

    def attacker(seed: int) -> None:
        outsider = Outsider(served["session"](), robot)
        # Every kind, the expensive one in between each other; each attacker starts elsewhere.
        cycle = ["heavy", "literal", "nested", "heavy", "bypass", "load_csv", "heavy", "flood"]
        i = seed * 2
        while not stop.is_set():
            name = cycle[i % len(cycle)]
            answers[name].append(attacks[name](outsider))
            i += 1

    threads = [threading.Thread(target=attacker, args=(i,), daemon=True) for i in range(4)]
    for t in threads:
        t.start()
    latencies, unanswered, wrong = [], [], []
    started = time.monotonic()
    while time.monotonic() - started < 8.0:
        t0 = time.perf_counter()
        try:
            rows = own.query("placement", {"config": DARK})
        except KgadaptError as exc:
            unanswered.append(str(exc))
        else:
            latencies.append((time.perf_counter() - t0) * 1000)
            if _where(rows) != _where(expected):
                wrong.append(rows)
        time.sleep(0.02)
    stop.set()
    for t in threads:
        t.join(timeout=15)
    listener.close()

    latencies.sort()
    print(f"own placement under attack: n={len(latencies)} p50={statistics.median(latencies):.1f} ms "
          f"p99={latencies[int(len(latencies) * 0.99) - 1]:.1f} ms max={latencies[-1]:.1f} ms; "
          f"attack answers: { {k: len(v) for k, v in answers.items()} }")
    assert unanswered == [] and wrong == []
    assert len(latencies) > 100
    # The heavy questions were stopped at the hard limit, the hostile ones refused by the parser.
    assert answers["heavy"] and all(a.kind == "err" and "hard time limit" in a.error for a in answers["heavy"]), \
        answers["heavy"][:3]
    for name, why in (("nested", "nested deeper"), ("bypass", "CALL is not allowed"), ("load_csv", "LOAD is not allowed")):
        assert all(a.kind == "err" and why in a.error for a in answers[name]), (name, answers[name][:3])
    assert accepted == []  # the store never opened a connection for LOAD CSV
    assert all(a.kind == "ok" for a in answers["literal"]), answers["literal"][:3]
    # Other robots are served again once the attack ends.
    outsider = Outsider(served["session"](), robot)
    assert _where(outsider.query("placement", {"config": DARK}).rows) == _where(expected)


def test_the_cli_stops_a_literal_paper_query_at_its_limit_and_says_so(tmp_path):
    store_dir = tmp_path / "store"
    with open_store(f"embedded:{store_dir}") as store:
        table1.load_models(store, 300, batch=100, seed=1)  # fig5_literal: seconds at N = 300
        started = time.monotonic()
        result = subprocess.run([sys.executable, "-m", "kgadapt", "knowledge", "query", "fig5_literal",
                                 "--store", f"embedded:{store_dir}"], capture_output=True, text=True, timeout=60, cwd=REPO)
        took = time.monotonic() - started
        assert result.returncode != 0
        assert "hard time limit of 1000 ms" in result.stderr, result.stderr
        # The work is gone, not merely unanswered: the store answers at once, and no sandbox server is left.
        t0 = time.perf_counter()
        store.execute("RETURN 1 AS one", read_only=True)
        assert time.perf_counter() - t0 < took
        left = subprocess.run(["pgrep", "-f", "kgadapt-sandbox-"], capture_output=True, text=True)
        assert left.stdout.strip() == "" or all(
            str(tmp_path) not in open(f"/proc/{pid}/cmdline").read() for pid in left.stdout.split()
        )
