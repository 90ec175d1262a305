"""``kgadapt bench fleet`` in small: every robot answers across three routers, and the fan-in is measured."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import REPO


def test_a_small_fleet_bench_gets_every_robots_answer_and_measures_the_fan_in(tmp_path):
    out = tmp_path / "fleet.json"
    done = subprocess.run(
        [sys.executable, "-m", "kgadapt", "bench", "fleet", "--sizes", "6", "--routers", "3", "--reps", "3",
         "--hosts", "60", "--fanin-s", "1", "--idle-s", "0.5", "--out", str(out)],
        capture_output=True, text=True, cwd=REPO, timeout=180)
    assert done.returncode == 0, done.stderr
    records = {r["op"]: r for r in json.loads(out.read_text())["records"]}
    question = records["fleet_question"]
    assert (question["n"], question["routers"], question["complete"], question["min_answered"]) == (6, 3, 3, 6)
    # The sandboxes' copies are counted (on the server, as its DUMP calls) beside the answers.
    assert question["answers"] == 18 and isinstance(question["sandbox_copies"], int)
    assert question["copies_per_answer"] == round(question["sandbox_copies"] / 18, 4)
    fanin = records["status_fanin"]
    assert fanin["hosts"] == 60 and fanin["services_cpu_pct"] > 0
    sent = int(fanin["publisher"].split()[-1])
    decoded = int(fanin["decode_only_receiver"].split()[-1])
    assert sent >= 60 * 2 and decoded > 0  # the statuses flowed through the routers
    # The floor: one router per robot-hosting router, each taking its share of the statuses from its rings.
    assert fanin["zenoh_floor_routers"] == 3 and fanin["zenoh_floor_cpu_pct"] >= 0
    assert fanin["zenoh_floor_taken"] >= 60  # statuses reached the floor routers' subscribers
    assert "status fan-in: 60 hosts" in done.stdout


def test_the_fan_in_counts_as_the_store_only_the_falkordb_server(tmp_path):
    # The routers name the store's socket on their command lines (``serve --socket``): matching it took
    # them too, and the store's figure then held the knowledge services' CPU.
    from kgadapt.bench.fleet_bench import SimulatedFleet, _store_pids

    with SimulatedFleet(tmp_path / "fleet", robots=2, routers=2, transit=True) as fleet:
        assert _store_pids(fleet) == [fleet.server.address.pid]
        assert not set(_store_pids(fleet)) & {*fleet.pids(), fleet.transit_pid()}
