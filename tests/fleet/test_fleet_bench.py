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
         "--hosts", "60", "--fanin-s", "2", "--idle-s", "0.5", "--links", "shared", "--out", str(out)],
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
    assert fanin["links"] == "shared" and fanin["publisher_links"] == 3  # one publisher link per router
    sent = int(fanin["publisher"].split()[-1])
    decoded = int(fanin["decode_only_receiver"].split()[-1])
    assert sent >= 60 * 2 and decoded > 0  # the statuses flowed through the routers
    # The services took the statuses of the whole window, by their own counters (a 2 s window: its edges fall
    # between takes every 0.25 s, hence the margin).
    assert fanin["statuses_taken_in_window"] > 0 and 0.6 <= fanin["window_coverage"] <= 1.4, fanin
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


def test_the_fan_in_by_default_opens_a_link_per_host_and_the_statuses_flow(tmp_path):
    # Each simulated host its own session, as each host's agent has: the routers then hold a link per host.
    out = tmp_path / "fleet.json"
    done = subprocess.run(
        [sys.executable, "-m", "kgadapt", "bench", "fleet", "--sizes", "3", "--routers", "3", "--reps", "1",
         "--hosts", "12", "--fanin-s", "1", "--idle-s", "0.2", "--out", str(out)],
        capture_output=True, text=True, cwd=REPO, timeout=180)
    assert done.returncode == 0, done.stderr
    fanin = {r["op"]: r for r in json.loads(out.read_text())["records"]}["status_fanin"]
    assert fanin["links"] == "per-host" and fanin["hosts"] == 12 and fanin["publisher_links"] == 12
    assert int(fanin["publisher"].split()[-1]) >= 12 * 2
    assert fanin["zenoh_floor_taken"] >= 12  # through the floor routers' links too
    assert "12 hosts" in done.stdout and "per-host links" in done.stdout


def test_a_fleets_routers_get_distinct_ports_even_when_a_pick_repeats(monkeypatch, tmp_path):
    from kgadapt.bench import fleet_bench

    picks = iter([24001, 24001, 24002, 24001, 24003, 24004])
    monkeypatch.setattr(fleet_bench, "_free_port", lambda: next(picks))
    fleet = fleet_bench.SimulatedFleet(tmp_path, robots=3, routers=3, transit=True)
    assert fleet.endpoints == [f"tcp/127.0.0.1:{port}" for port in (24001, 24002, 24003, 24004)]
