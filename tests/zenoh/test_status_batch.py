"""Status fan-in in batches: many hosts' statuses written together, one store call per batch, none lost."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import zenoh

from kgadapt.knowledge import runtime
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.schema import ensure_indexes
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.zenoh.conftest import platform_row, wait_for, wait_until_serving

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


def _service(resp_store, zenoh_pair, robot, **settings):
    """A knowledge service of its own settings, and a client that waits until it serves."""
    server, session = zenoh_pair
    ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, **settings))
    svc.setup(server)
    wait_until_serving(session, robot)
    return svc, KnowledgeClient(session, robot, timeout=3.0)


def _status(host: str, free: float, *, total: float = 1000.0, load: float = 10.0) -> bytes:
    return messages.encode(messages.HostStatus(host=host, time=time.time(), memory_total_mb=total,
                                               memory_free_mb=free, cpu_load=load, cpu_cores=2))


def _free(client, host: str, free: float):
    return lambda: (platform_row(client, host) or {}).get("memory_free_mb") == free


def test_a_status_within_the_deadband_waits_and_one_beyond_it_is_written_at_once(zenoh_pair, robot, resp_store):
    _, session = zenoh_pair
    resp_store.execute("MERGE (:Platform {name: 'd0'})")
    # No refresh within the test: what waits, waits.
    svc, client = _service(resp_store, zenoh_pair, robot, status_refresh_s=3600.0, status_deadband_mb=16.0)
    try:
        session.put(keys.host_status(robot, "d0"), _status("d0", 500.0))
        wait_for(_free(client, "d0", 500.0), 10, "a host's first status written at once")
        session.put(keys.host_status(robot, "d0"), _status("d0", 505.0))  # 5 MiB: within the deadband
        wait_for(lambda: svc.stats().get("events_received", 0) >= 2, 10, "the second status received")
        session.put(keys.host_status(robot, "d0"), _status("d0", 700.0))  # 195 MiB: beyond it
        wait_for(_free(client, "d0", 700.0), 10, "a change beyond the deadband written at once")
        stats = svc.stats()
        assert stats["events_received"] == 3 and stats.get("events_dropped", 0) == 0, stats
        # The one within the deadband was never written (its batch ended before the third arrived).
        assert stats["status_applied"] == 2, stats
    finally:
        svc.shutdown()


def test_waiting_statuses_are_written_at_the_refresh_checked_against_the_profiles_read_then(
        zenoh_pair, robot, resp_store):
    _, session = zenoh_pair
    resp_store.execute("MERGE (:Platform {name: 'd1'})")
    svc, client = _service(resp_store, zenoh_pair, robot, status_refresh_s=0.5, status_deadband_mb=16.0)
    try:
        session.put(keys.host_status(robot, "d1"), _status("d1", 500.0))
        wait_for(_free(client, "d1", 500.0), 10, "the first status")
        # A process on d1 now holds 800 MiB: at most 1000 - 800 x 0.75 = 400 MiB can be free.
        runtime.record_process_start(resp_store, run_id="run-d1", instance="det-d1", deployment="d", config=None,
                                     host="d1", pid=4243, start_time=time.time())
        runtime.record_process_sample(resp_store, run_id="run-d1", rss_mb_last=800.0, rss_mb_mean=800.0,
                                      rss_mb_max=800.0, cpu_percent_mean=20.0)
        # Within the deadband of the 500 written, admitted against the profiles read with that one (none),
        # then refused at the refresh, against the profiles read then.
        session.put(keys.host_status(robot, "d1"), _status("d1", 505.0))
        wait_for(lambda: "running processes hold 800 MiB" in (svc.stats().get("last_drop") or ""), 10,
                 "the waiting status refused at the refresh")
        assert platform_row(client, "d1")["memory_free_mb"] == 500.0
        session.put(keys.host_status(robot, "d1"), _status("d1", 350.0))  # beyond the deadband, and believable
        wait_for(_free(client, "d1", 350.0), 10, "the believable change")
        session.put(keys.host_status(robot, "d1"), _status("d1", 345.0))  # within it: waits for the refresh
        wait_for(_free(client, "d1", 345.0), 10, "the waiting status written by the refresh")
    finally:
        svc.shutdown()


def test_a_lost_host_is_last_seen_when_its_last_status_was_heard_not_when_its_figures_were_last_written(
        zenoh_pair, robot, resp_store):
    # Statuses within the deadband wait for the refresh (10 s by default), and a lost host's waiting status
    # is never written: without the loss recording it, "last seen" would be the last write, seconds early.
    _, session = zenoh_pair
    resp_store.execute("MERGE (:Platform {name: 'd2'})")
    svc, client = _service(resp_store, zenoh_pair, robot, status_refresh_s=3600.0, status_deadband_mb=16.0)
    token = session.liveliness().declare_token(keys.host_alive(robot, "d2"))
    try:
        wait_for(lambda: (platform_row(client, "d2") or {}).get("online") is True, 10, "d2 online")
        session.put(keys.host_status(robot, "d2"), _status("d2", 500.0))
        wait_for(_free(client, "d2", 500.0), 10, "the first status written")
        written = platform_row(client, "d2")["last_seen"]
        sent = time.time()
        session.put(keys.host_status(robot, "d2"), _status("d2", 505.0))  # within the deadband: waits
        wait_for(lambda: svc.stats().get("events_received", 0) >= 3, 10, "the waiting status received")
        token.undeclare()
        token = None
        wait_for(lambda: platform_row(client, "d2")["online"] is False, 10, "d2 offline")
        row = platform_row(client, "d2")
        assert row["memory_free_mb"] == 500.0  # the waiting status's figures were not written
        assert row["last_seen"] >= sent > written, (row, sent, written)
    finally:
        if token is not None:
            token.undeclare()
        svc.shutdown()


def test_statuses_wait_in_zenohs_ring_for_the_status_worker_not_in_a_python_callback_each(zenoh_pair, robot,
                                                                                          resp_store):
    # 2,000 statuses a second into 100 services: a Python callback per status (its thread taking the
    # interpreter, a queue hand-off) cost more than everything the worker then did with it.
    server, session = zenoh_pair
    hosts = [f"q{i:02d}" for i in range(20)]
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": hosts})
    ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot))
    queued: list[str] = []  # the threads that put a status on the worker's queue
    enqueue = svc._enqueue_event

    def counted(event):
        if event[0] == "status":
            queued.append(threading.current_thread().name)
        enqueue(event)
    svc._enqueue_event = counted
    svc.setup(server)
    try:
        wait_until_serving(session, robot)
        client = KnowledgeClient(session, robot, timeout=3.0)
        for i, host in enumerate(hosts):
            session.put(keys.host_status(robot, host), _status(host, 100.0 + i))

        def every_host_written() -> bool:
            rows = {r["platform"]: r for r in client.query("platforms", {})}
            return all((rows.get(h) or {}).get("memory_free_mb") == 100.0 + i for i, h in enumerate(hosts))
        wait_for(every_host_written, 30, "every host's status in the graph")
        stats = svc.stats()
        assert stats["events_received"] == len(hosts) and stats.get("events_dropped", 0) == 0, stats
        assert queued == [], f"{len(queued)} statuses handed over one by one by {set(queued)}"
    finally:
        svc.shutdown()


def test_a_liveliness_change_is_written_at_once_whatever_the_status_window(zenoh_pair, robot, resp_store):
    # Statuses are taken from Zenoh's ring every status_batch_s; a liveliness change comes by callback
    # and wakes the worker at once (taking the statuses received before it along).
    server, session = zenoh_pair
    resp_store.execute("MERGE (:Platform {name: 'o1'})")
    svc, client = _service(resp_store, zenoh_pair, robot, status_batch_s=3600.0)
    try:
        token = session.liveliness().declare_token(keys.host_alive(robot, "o1"))
        wait_for(lambda: (platform_row(client, "o1") or {}).get("online") is True, 10, "o1 online")
        token.undeclare()
        wait_for(lambda: (platform_row(client, "o1") or {}).get("online") is False, 10, "o1 offline")
    finally:
        svc.shutdown()


def test_liveliness_changes_beyond_max_pending_statuses_are_dropped_and_counted_while_the_worker_is_held(
        zenoh_pair, robot, resp_store):
    # The worker's queue is bounded by its one producer (the liveliness callback): a worker held up (a
    # slow store) keeps max_pending_statuses changes, drops and counts the rest, and applies what it kept.
    server, session = zenoh_pair
    hosts = [f"b{i}" for i in range(8)]
    resp_store.execute("UNWIND $names AS name MERGE (:Platform {name: name})", {"names": hosts})
    ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, max_pending_statuses=3, status_batch_s=3600.0))
    held, release = threading.Event(), threading.Event()
    apply = svc._apply_events

    def held_up(batch):
        held.set()
        release.wait(30)
        apply(batch)
    svc._apply_events = held_up
    svc.setup(server)
    tokens = []
    try:
        wait_until_serving(session, robot)
        client = KnowledgeClient(session, robot, timeout=3.0)
        tokens.append(session.liveliness().declare_token(keys.host_alive(robot, hosts[0])))
        assert held.wait(10), "the worker never took the first change"
        tokens += [session.liveliness().declare_token(keys.host_alive(robot, h)) for h in hosts[1:]]
        wait_for(lambda: svc.stats().get("events_dropped", 0) >= len(hosts) - 1 - 3, 10, "the changes beyond 3 dropped")
        release.set()
        kept = hosts[:1 + 3]
        wait_for(lambda: all((platform_row(client, h) or {}).get("online") is True for h in kept), 10,
                 "the first change and the three kept written")
        stats = svc.stats()
        assert stats["events_dropped"] == len(hosts) - len(kept), stats
        assert "events pending" in stats.get("last_drop", ""), stats
    finally:
        release.set()
        for token in tokens:
            token.undeclare()
        svc.shutdown()


def test_a_service_that_hears_no_status_takes_zenohs_ring_once_a_second(zenoh_pair, robot, resp_store):
    # A hundred services taking an empty ring four times a second cost 3 % of a core doing nothing.
    server, session = zenoh_pair
    resp_store.execute("MERGE (:Platform {name: 'w1'})")
    ensure_indexes(resp_store)
    svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, status_batch_s=0.25))
    takes: list[float] = []
    take = svc._take_events

    def counted(first):
        takes.append(time.monotonic())
        return take(first)
    svc._take_events = counted
    svc.setup(server)
    try:
        wait_until_serving(session, robot)
        client = KnowledgeClient(session, robot, timeout=3.0)
        seen = len(takes)
        wait_for(lambda: len(takes) >= seen + 8, 30, "eight takes of the quiet ring")
        quiet = takes[-4:]
        assert quiet[-1] - quiet[0] >= 3 * 0.9, [round(b - a, 2) for a, b in zip(takes, takes[1:])]
        # A status after the quiet is still taken, and the takes come every status_batch_s again.
        session.put(keys.host_status(robot, "w1"), _status("w1", 300.0))
        wait_for(_free(client, "w1", 300.0), 10, "the status after the quiet")
    finally:
        svc.shutdown()


def test_a_service_shut_down_while_statuses_pour_in_leaves_no_thread_failed(zenoh_pair, robot, resp_store):
    # Zenoh's ring raises "Already mutably borrowed" when it is taken from while zenoh-python undeclares
    # it: the status worker died of it once at a shutdown. Statuses pour in while services start and stop.
    server, session = zenoh_pair
    ensure_indexes(resp_store)
    resp_store.execute("MERGE (:Platform {name: 'flood'})")
    failed: list[str] = []
    hook = threading.excepthook
    threading.excepthook = lambda args: failed.append(f"{args.thread.name if args.thread else '?'}: "
                                                      f"{args.exc_type.__name__}: {args.exc_value}")
    stop = threading.Event()
    pub = session.declare_publisher(keys.host_status(robot, "flood"), congestion_control=BLOCK)

    def pour() -> None:
        i = 0
        while not stop.is_set():
            i += 1
            pub.put(messages.encode("host_status", {"host": "flood", "time": float(i), "memory_total_mb": 1000.0,
                                                    "memory_free_mb": float(i % 500), "cpu_load": 1.0,
                                                    "cpu_cores": 4}))
    pourer = threading.Thread(target=pour, name="pour", daemon=True)
    pourer.start()
    try:
        for _ in range(30):
            svc = KnowledgeService(resp_store, ServiceSettings(robot=robot, sandbox=False, status_batch_s=0.001))
            svc.setup(server)
            wait_for(lambda: svc.stats().get("events_received", 0) > 20 or None, 30, "statuses taken")
            svc.shutdown()
    finally:
        stop.set()
        pourer.join(10)
        pub.undeclare()
        threading.excepthook = hook
    assert failed == []


def _thread_names(pid: int) -> list[str]:
    names = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            names.append(Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip())
        except OSError:  # a thread that ended meanwhile
            pass
    return names


def test_the_knowledge_services_router_reads_each_status_on_zenohs_receive_threads_alone(tmp_path, children, robot):
    # Each status is its own message; a link accepted on Zenoh's accept runtime stayed registered there, so
    # each woke the acc thread and then an rx thread. `kgadapt knowledge serve` hands the accept runtime over
    # to the receive runtime (session.SERVICE_RUNTIME): no acc thread, and the 8 rx threads kept. This test
    # process has opened sessions itself, so its children inherit our default $ZENOH_RUNTIME: the service
    # must still take its own.
    open_session(ZenohSettings(mode="peer")).close()
    assert os.environ.get("ZENOH_RUNTIME")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = children("service", "knowledge", "serve", "--store", f"embedded:{tmp_path / 'store'}",
                       "--robot", robot, "--listen", endpoint)
    service.wait_ready()
    publisher = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
    try:  # a host's link, accepted by the service's router, carrying a status
        publisher.put(keys.host_status(robot, "h1"), messages.encode("host_status", {
            "host": "h1", "time": time.time(), "memory_total_mb": 1000.0, "memory_free_mb": 500.0, "cpu_load": 1.0}))
        names = _thread_names(service.pid)
    finally:
        publisher.close()
    assert [n for n in names if n.startswith("acc-")] == [], sorted(names)
    assert sum(n.startswith("rx-") for n in names) >= 8, sorted(n for n in names if n != "python")


def test_status_takes_fall_on_a_grid_of_the_clock_shared_by_every_service():
    # Services take their rings on multiples of the window, so those of one process wake together and run
    # one after another on warm caches (docs/fleet.md, ninth round); no take waits longer than the window.
    from kgadapt.knowledge.service import _next_tick

    for period in (0.25, 1.0):
        for now in (1000.0, 1000.01, 1000.2499, 1000.25, 87_654.321):
            due = _next_tick(now, period)
            assert now < due <= now + period
            assert abs(due / period - round(due / period)) < 1e-9, (now, period, due)
        # two services whose last takes were apart within one window take next at the same instant
        assert _next_tick(5000.01, period) == _next_tick(5000.01 + period * 0.9, period)
    assert _next_tick(1000.1, 3600.0) == 1000.1 + 3600.0  # a long window is kept whole
