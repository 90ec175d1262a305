"""kill -9 of the knowledge store during a burst of acknowledged writes: after restart, every one is there."""

from __future__ import annotations

from kgadapt.bench.reliability_bench import StoreCrashSettings, store_crash_trial

TRIALS = 20


def test_every_acknowledged_write_survives_kill_9_of_the_store_in_20_trials(tmp_path):
    results, hung = [], []
    for i in range(TRIALS):
        result = store_crash_trial(tmp_path / f"trial{i}", trial=i)
        if result["acked"] < result["kill_after"]:
            # The server stopped answering before the kill was due (seen once: a fresh FalkorDB 4.16 never
            # answered its first write, under two test workers). Not this test's fault; counted, and the
            # trial is run again on a fresh server.
            hung.append((i, result["acked"], result["first_failure"]))
            result = store_crash_trial(tmp_path / f"trial{i}-again", trial=i)
        if result["restart_hung"]:  # the server started to count never answered; a second start counted
            hung.append((i, "restart"))
        results.append(result)

    assert len(hung) <= 1, f"the store stopped answering in more than one trial: {hung}"

    assert all(r["killed"] for r in results)
    assert all(r["acked"] >= r["kill_after"] for r in results)  # the kill came mid-burst, after the target
    assert all(r["failed_writes"] == 1 for r in results)  # the burst ended at the kill
    lost = {r["trial"]: r["lost_examples"] for r in results if r["lost"]}
    assert not lost, f"acknowledged writes missing after restart: {lost}"
    assert sum(r["found"] for r in results) >= sum(r["acked"] for r in results)


def test_the_embedded_store_restarts_its_killed_server_by_itself_and_keeps_every_acknowledged_write(tmp_path):
    result = store_crash_trial(tmp_path / "auto", trial=0, settings=StoreCrashSettings(restart="store", tail=30))

    assert result["restarted_by_store"], result
    assert result["acked_after_restart"] > 0
    assert result["lost"] == 0, result
