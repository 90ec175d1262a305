"""Statuses that cannot lie the detector off the drone: what a consumer of host statuses refuses.

The rules (:class:`kgadapt.shared.hostmonitor.StatusTrust`) alone, then the knowledge
service applying them to forged statuses put on this robot's own keys over real
Zenoh, with ProcessProfiles in a real FalkorDB, and closing the profiles of a
host whose liveliness token is lost.
"""

from __future__ import annotations

import time

import msgspec
import pytest

from kgadapt.knowledge import runtime
from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.knowledge.falkordb_store import FalkorDBStore
from kgadapt.knowledge.schema import ensure_indexes
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.knowledge.store import StoreSettings
from kgadapt.shared import keys, messages
from kgadapt.shared.errors import ConfigError, MessageError
from kgadapt.shared.hostmonitor import StatusTrust, TrustSettings
from tests.zenoh.conftest import platform_row, wait_for


def status(host: str = "remote", *, free: float = 500.0, total: float = 1000.0,
           at: float | None = None) -> messages.HostStatus:
    return messages.HostStatus(host=host, time=time.time() if at is None else at, memory_total_mb=total,
                               memory_free_mb=free, cpu_load=10.0, cpu_cores=2)


def test_a_status_of_a_host_without_liveliness_is_refused():
    trust = StatusTrust()
    with pytest.raises(MessageError, match="no liveliness token"):
        trust.admit("remote", status(), received=1.0)
    trust.alive("remote", True)
    assert trust.admit("remote", status(), received=1.0).memory_free_mb == 500.0
    trust.alive("remote", False)
    with pytest.raises(MessageError, match="no liveliness token"):
        trust.admit("remote", status(), received=2.0)
    assert trust.refused == 2


def test_a_status_far_older_than_the_newest_is_refused_and_a_slightly_late_one_is_not():
    trust = StatusTrust(TrustSettings(stale_s=5.0))
    trust.alive("remote", True)
    trust.admit("remote", status(at=1000.0), received=1.0)
    trust.admit("remote", status(at=998.0), received=1.1)  # reordered on the way: within bounds
    with pytest.raises(MessageError, match="before its newest status"):
        trust.admit("remote", status(at=990.0), received=1.2)


def test_free_memory_above_the_hosts_total_or_held_by_its_processes_is_refused():
    trust = StatusTrust()
    trust.alive("remote", True)
    with pytest.raises(MessageError, match="free of"):
        trust.admit("remote", status(free=1200.0, total=1000.0), received=1.0)  # check_status's rule
    trust.admit("remote", status(free=500.0, total=1000.0), received=1.0)
    with pytest.raises(MessageError, match="above the host's 1000 MiB"):
        trust.admit("remote", status(free=60000.0, total=60000.0), received=1.1)  # a host does not grow
    # Its running processes' profiles hold 400 MiB: at most ~700 of 1000 can be free (shared pages allowed for).
    trust.admit("remote", status(free=650.0), received=1.2, used_mb=400.0)
    with pytest.raises(MessageError, match="running processes hold 400 MiB"):
        trust.admit("remote", status(free=900.0), received=1.3, used_mb=400.0)


def test_no_single_status_decides_room_or_shortage():
    trust = StatusTrust(TrustSettings(window_s=2.0, min_statuses=2))
    trust.alive("remote", True)
    trust.admit("remote", status(free=900.0), received=10.0)
    assert trust.confirmed_free("remote", 10.0) is None  # one status confirms nothing
    trust.admit("remote", status(free=100.0), received=10.5)  # a forged "full" between real ones
    trust.admit("remote", status(free=900.0), received=11.0)
    assert trust.roomiest("remote", 11.0) == 900.0  # the shortage does not hold over the window
    assert trust.confirmed_free("remote", 11.0) == 100.0  # and room is only what every status shows
    trust.admit("remote", status(free=900.0), received=12.0)
    assert trust.confirmed_free("remote", 12.6) == 900.0  # the forgery left the window
    assert trust.confirmed_free("remote", 14.0) == 900.0  # late statuses (a loaded machine): the last two
    assert trust.confirmed_free("remote", 20.0) is None  # nothing recent: not confirmed
    trust.alive("remote", False)
    trust.alive("remote", True)  # a new session of the host starts afresh
    assert trust.confirmed_free("remote", 11.0) is None



def test_a_host_flooding_its_key_is_judged_on_its_newest_statuses_alone():
    # 40 statuses within one window from the host's own sender: only the newest max_statuses are kept, so a
    # flood costs each admit what a status at the normal rate costs (the window is no longer than the bound).
    trust = StatusTrust(TrustSettings(window_s=2.0, min_statuses=2, max_statuses=4))
    trust.alive("remote", True)
    for i in range(40):
        trust.admit("remote", status(free=100.0 + 10 * i), received=10.0 + i / 100)
    assert trust.confirmed_free("remote", 10.4) == 100.0 + 10 * 36  # the least of the last four
    assert trust.roomiest("remote", 10.4) == 100.0 + 10 * 39
    with pytest.raises(ConfigError, match="max_statuses 1 is below min_statuses 2"):
        TrustSettings(min_statuses=2, max_statuses=1)

# -- the knowledge service on real Zenoh ----------------------------------------------


def _put(session, robot: str, body: messages.HostStatus) -> None:
    session.put(keys.host_status(robot, body.host), messages.encode(body))


def _applied(client, host: str, free: float):
    return lambda: (platform_row(client, host) or {}).get("memory_free_mb") == free


def test_the_service_refuses_forged_statuses_that_contradict_the_graph(zenoh_pair, client, service, robot, resp_store):
    _, session = zenoh_pair
    token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))
    try:
        wait_for(lambda: (platform_row(client, "remote") or {}).get("online") is True, 5, "remote online")
        _put(session, robot, status(free=300.0, total=1000.0))
        wait_for(_applied(client, "remote", 300.0), 5, "the first real status")
        # A detector on remote whose profile holds 500 MiB.
        runtime.record_process_start(resp_store, run_id="run-1", instance="det-1", deployment="d", config=None,
                                     host="remote", pid=4242, start_time=time.time())
        runtime.record_process_sample(resp_store, run_id="run-1", rss_mb_last=500.0, rss_mb_mean=400.0,
                                      rss_mb_max=500.0, cpu_percent_mean=20.0)
        forgeries = [
            (status(free=60000.0, total=60000.0), "above the host's 1000 MiB"),  # a host larger than it was
            (status(free=900.0, total=1000.0), "running processes hold 500 MiB"),  # room the profile shows used
            (status(free=350.0, at=time.time() - 60.0), "before its newest status"),  # a replay
        ]
        for body, why in forgeries:
            before = service.stats().get("events_dropped", 0)
            _put(session, robot, body)
            wait_for(lambda: service.stats().get("events_dropped", 0) > before, 5, f"the refusal of {body}")
            assert why in service.stats()["last_drop"]
            assert platform_row(client, "remote")["memory_free_mb"] == 300.0
        _put(session, robot, status(free=280.0, total=1000.0))  # real statuses still go through
        wait_for(_applied(client, "remote", 280.0), 5, "the next real status")
        row = platform_row(client, "remote")
        assert row["memory_total_mb"] == 1000.0
    finally:
        token.undeclare()


def test_a_hosts_profiles_close_when_its_liveliness_is_lost_and_reopen_if_its_process_outlived_it(
        zenoh_pair, client, service, robot, resp_store):
    _, session = zenoh_pair
    token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))
    wait_for(lambda: (platform_row(client, "remote") or {}).get("online") is True, 5, "remote online")
    for run in ("run-a", "run-b"):
        runtime.record_process_start(resp_store, run_id=run, instance=run, deployment="d", config=None,
                                     host="remote", pid=1, start_time=time.time())
    runtime.record_process_end(resp_store, run_id="run-b", end_time=123.0, exit_status=0)
    profile = "MATCH (r:ProcessProfile {name: $run}) RETURN r.end_time AS end, r.end_reason AS why"
    lost_at = time.time()
    token.undeclare()
    row = wait_for(lambda: (r := resp_store.execute(profile, {"run": "run-a"})[0])["end"] is not None and r,
                   5, "run-a's profile closed")
    assert row["why"] == "host_lost" and row["end"] >= lost_at - 1.0
    assert resp_store.execute(profile, {"run": "run-b"})[0] == {"end": 123.0, "why": "exited"}  # untouched
    assert runtime.held_by_processes(resp_store, host="remote") == 0.0
    # A sample received before the loss but applied after it (queued while the store restarted)
    # does not reopen it: the process may have died with its host's agent.
    runtime.record_process_sample(resp_store, run_id="run-a", rss_mb_last=40.0, rss_mb_mean=40.0,
                                  rss_mb_max=40.0, cpu_percent_mean=1.0, received=row["end"] - 0.5)
    assert resp_store.execute(profile, {"run": "run-a"})[0] == row
    # The process outlived a partition: its next sample, received after the loss, reopens the profile.
    runtime.record_process_sample(resp_store, run_id="run-a", rss_mb_last=50.0, rss_mb_mean=50.0,
                                  rss_mb_max=50.0, cpu_percent_mean=1.0, received=time.time())
    assert resp_store.execute(profile, {"run": "run-a"})[0] == {"end": None, "why": None}
    assert runtime.held_by_processes(resp_store, host="remote") == 50.0


def sent(origin: str, seq: int, **kw) -> messages.HostStatus:
    return msgspec.structs.replace(status(**kw), origin=origin, seq=seq)


def test_a_second_sender_beside_the_real_monitor_makes_none_of_the_hosts_statuses_count():
    trust = StatusTrust(TrustSettings(window_s=2.5, new_source_s=5.0, contest_s=15.0))
    trust.alive("onboard", True)
    trust.admit("onboard", sent("real", 0, host="onboard", free=600.0), received=10.0)
    trust.admit("onboard", sent("real", 1, host="onboard", free=600.0), received=10.5)
    assert trust.roomiest("onboard", 10.6) == 600.0
    # A forger's "full" statuses, each refused while on probation...
    for i, t in enumerate((11.0, 11.7, 12.4)):
        with pytest.raises(MessageError, match="not the host's 'real'"):
            trust.admit("onboard", sent("forger", i, host="onboard", free=0.0), received=t)
    # ...and once the real monitor speaks again (late: a loaded machine), the host is contested: its
    # figures stay what they were (not unconfirmed: that would make the drone's own host no target).
    trust.admit("onboard", sent("real", 2, host="onboard", free=300.0), received=13.0)
    assert trust.roomiest("onboard", 13.1) == 600.0 and trust.confirmed_free("onboard", 13.1) == 600.0
    trust.admit("onboard", sent("real", 3, host="onboard", free=300.0), received=20.0)
    assert trust.confirmed_free("onboard", 20.1) == 600.0  # still held
    trust.admit("onboard", sent("real", 4, host="onboard", free=300.0), received=28.5)
    trust.admit("onboard", sent("real", 5, host="onboard", free=300.0), received=29.0)
    assert trust.roomiest("onboard", 29.1) == 300.0  # the contest is over: the statuses count again


def test_a_forgery_without_an_origin_never_counts_while_the_monitor_speaks():
    trust = StatusTrust(TrustSettings(new_source_s=5.0))
    trust.alive("onboard", True)
    trust.admit("onboard", sent("real", 0, host="onboard"), received=1.0)
    with pytest.raises(MessageError, match="sender ''"):
        trust.admit("onboard", status("onboard", free=0.0), received=1.2)


def test_a_replayed_or_copied_sequence_number_is_refused_and_contests_the_host():
    trust = StatusTrust(TrustSettings(contest_s=15.0))
    trust.alive("onboard", True)
    trust.admit("onboard", sent("real", 7, host="onboard"), received=1.0)
    trust.admit("onboard", sent("real", 8, host="onboard"), received=1.5)
    with pytest.raises(MessageError, match="seq 8 not after 8"):
        trust.admit("onboard", sent("real", 8, host="onboard", free=0.0), received=1.6)
    trust.admit("onboard", sent("real", 9, host="onboard", free=100.0), received=2.0)
    assert trust.confirmed_free("onboard", 2.1) == 500.0  # held as before the copied number


def test_a_status_without_a_number_under_a_numbering_senders_origin_is_refused_and_contests_the_host():
    # The origin travels in every status (anyone who may read them has it); leaving out seq skipped the check.
    trust = StatusTrust(TrustSettings(contest_s=15.0))
    trust.alive("onboard", True)
    trust.admit("onboard", sent("real", 7, host="onboard"), received=1.0)
    trust.admit("onboard", sent("real", 8, host="onboard"), received=1.5)
    forged = msgspec.structs.replace(status("onboard", free=0.0), origin="real")  # seq left out
    with pytest.raises(MessageError, match="no seq from sender 'real'"):
        trust.admit("onboard", forged, received=1.6)
    trust.admit("onboard", sent("real", 9, host="onboard", free=100.0), received=2.0)
    assert trust.confirmed_free("onboard", 2.1) == 500.0  # held as before the forgery, not 0


def test_a_host_contested_before_any_figure_stays_unconfirmed():
    trust = StatusTrust(TrustSettings(contest_s=15.0))
    trust.alive("onboard", True)
    trust.admit("onboard", sent("real", 1, host="onboard"), received=1.0)
    with pytest.raises(MessageError):
        trust.admit("onboard", sent("real", 1, host="onboard"), received=1.1)
    assert trust.confirmed_free("onboard", 1.2) is None


def test_a_restarted_monitor_takes_over_once_the_old_one_stays_silent():
    trust = StatusTrust(TrustSettings(require_alive=False, new_source_s=5.0, window_s=2.5))
    trust.admit("remote", sent("old", 0, free=500.0), received=1.0)
    with pytest.raises(MessageError, match="counted once it alone has spoken for 5 s"):
        trust.admit("remote", sent("new", 0, free=400.0), received=3.0)
    trust.admit("remote", sent("new", 1, free=400.0), received=8.5)  # the old one silent since 1.0
    trust.admit("remote", sent("new", 2, free=400.0), received=9.0)
    assert trust.confirmed_free("remote", 9.1) == 400.0
    # A new liveliness token starts afresh: the first sender of the new session counts at once.
    trust.alive("remote", True)
    trust.admit("remote", sent("third", 0, free=300.0), received=10.0)
    trust.admit("remote", sent("third", 1, free=300.0), received=10.5)
    assert trust.confirmed_free("remote", 10.6) == 300.0


def test_a_loss_while_the_store_is_away_still_ends_the_hosts_profiles_once_it_is_back(zenoh_pair, robot, tmp_path):
    """The soak's ``graph_disagrees``: the remote agent died while the store restarted, its
    detector's profile stayed open for good. The loss (and the host's return in between) waits
    for the store; a detector the returned host started after the loss keeps its profile."""
    server_side, session = zenoh_pair
    embedded = EmbeddedServer(tmp_path / "store")
    address = embedded.ensure()
    store = FalkorDBStore(StoreSettings(kind="falkordb", url=f"falkordb+unix://{address.unix_socket}",
                                        unix_socket=address.unix_socket, graph="g", socket_timeout=2.0))
    store.setup()
    ensure_indexes(store)
    store.execute("MERGE (:Platform {name: 'remote'})")  # the models' host
    svc = KnowledgeService(store, ServiceSettings(robot=robot, liveliness_retry_s=0.2))
    svc.setup(server_side)
    profile = "MATCH (r:ProcessProfile {name: $run}) RETURN r.end_time AS end, r.end_reason AS why"
    token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))
    try:
        wait_for(lambda: svc.stats().get("liveliness_applied", 0) >= 1, 5, "remote online in the graph")
        runtime.record_process_start(store, run_id="old", instance="old", deployment="d", config=None,
                                     host="remote", pid=1, start_time=time.time())
        embedded.stop()  # the store is away
        lost_at = time.time()
        token.undeclare()
        wait_for(lambda: svc.stats().get("liveliness_retried", 0) >= 1, 10, "the loss refused by the absent store")
        token = session.liveliness().declare_token(keys.host_alive(robot, "remote"))  # the host is back
        wait_for(lambda: svc.stats().get("liveliness_retried", 0) >= 3, 10, "more tries")
        embedded.ensure()  # the store is back (an AOF-recovered server, as after a kill)
        runtime.record_process_start(store, run_id="new", instance="new", deployment="d", config=None,
                                     host="remote", pid=2, start_time=time.time())
        wait_for(lambda: svc.stats().get("liveliness_applied", 0) >= 3, 15, "the loss and the return applied")
        row = store.execute(profile, {"run": "old"})[0]
        assert row["why"] == "host_lost" and lost_at - 1.0 <= row["end"] <= lost_at + 5.0
        assert store.execute(profile, {"run": "new"})[0] == {"end": None, "why": None}
        online = store.execute("MATCH (p:Platform {name: 'remote'}) RETURN p.online AS online")[0]["online"]
        assert online is True
    finally:
        token.undeclare()
        svc.shutdown()
        store.shutdown()
        embedded.stop()
