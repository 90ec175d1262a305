"""Status fan-in in batches: many hosts' statuses written together, one store call per batch, none lost."""

from __future__ import annotations

import time

import zenoh

from kgadapt.shared import keys, messages
from tests.zenoh.conftest import wait_for

BLOCK = zenoh.CongestionControl.BLOCK
HOSTS = 300


def test_a_batched_status_write_keeps_every_hosts_figures(zenoh_pair, client, service, robot, resp_store):
    _, session = zenoh_pair
    hosts = [f"h{i:03d}" for i in range(HOSTS)]
    # Platforms of the test's models: the service takes statuses only of hosts the models name.
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": hosts})
    publishers = {h: session.declare_publisher(keys.host_status(robot, h), congestion_control=BLOCK) for h in hosts}
    try:
        for round_ in (0, 1):  # two statuses per host; the second is the one the graph must hold
            for i, (host, pub) in enumerate(publishers.items()):
                pub.put(messages.encode("host_status", {
                    "host": host, "time": 1.0 + round_, "memory_total_mb": 1000.0 + i,
                    "memory_free_mb": float(i + round_), "cpu_load": float(i % 100) / 2 + round_, "cpu_cores": 4}))

        def every_host_current() -> dict[str, dict] | None:
            rows = {r["platform"]: r for r in client.query("platforms", {})}
            done = all((rows.get(h) or {}).get("memory_free_mb") == float(i + 1) for i, h in enumerate(hosts))
            return rows if done else None
        rows = wait_for(every_host_current, 60, f"the second status of all {HOSTS} hosts in the graph")
    finally:
        for pub in publishers.values():
            pub.undeclare()
    for i, host in enumerate(hosts):
        row = rows[host]
        assert (row["memory_total_mb"], row["memory_free_mb"], row["cpu_load"]) == (
            1000.0 + i, float(i + 1), float(i % 100) / 2 + 1), host
    stats = service.stats()
    assert stats["events_received"] == 2 * HOSTS
    assert stats.get("events_dropped", 0) == 0, stats["last_drop"]
    # Each store call carried many hosts: far fewer writes than statuses (one per status before batching).
    assert stats["status_writes"] * 10 <= stats["status_applied"], stats


def test_statuses_of_hosts_publishing_at_their_own_phases_share_a_write(zenoh_pair, client, service, robot,
                                                                           resp_store):
    # Real hosts publish at their own phases, not all at once: statuses 30 ms apart still share a write
    # (a 20 ms window wrote each alone: two store calls a status).
    _, session = zenoh_pair
    hosts = [f"p{i:02d}" for i in range(10)]
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": hosts})
    publishers = {h: session.declare_publisher(keys.host_status(robot, h), congestion_control=BLOCK) for h in hosts}
    try:
        for i, (host, pub) in enumerate(publishers.items()):
            pub.put(messages.encode("host_status", {"host": host, "time": 1.0, "memory_total_mb": 1000.0,
                                                    "memory_free_mb": float(100 + i), "cpu_load": 1.0}))
            time.sleep(0.03)  # the phase between two hosts' statuses is what is tested, not a wait

        def every_host_written() -> bool:
            rows = {r["platform"]: r for r in client.query("platforms", {})}
            return all((rows.get(h) or {}).get("memory_free_mb") == float(100 + i) for i, h in enumerate(hosts))
        wait_for(every_host_written, 30, "every host's status in the graph")
    finally:
        for pub in publishers.values():
            pub.undeclare()
    stats = service.stats()
    assert stats["status_applied"] == len(hosts), stats
    # At most half as many writes as statuses: a window of ServiceSettings.status_batch_s (0.25 s) holds
    # several hosts' statuses even if the machine stretches the 30 ms phases to 100 ms.
    assert stats["status_writes"] * 2 <= len(hosts), stats
