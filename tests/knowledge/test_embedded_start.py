"""A FalkorDB that cannot start says why, from this start's own log lines."""

from __future__ import annotations

import time

import pytest

from kgadapt.knowledge.embedded import EmbeddedServer
from kgadapt.shared.errors import StoreUnavailable


def test_a_server_that_exits_while_starting_reports_its_own_log_lines_not_an_older_crash(tmp_path):
    data = tmp_path / "store"
    server = EmbeddedServer(data)
    server.ensure()
    server.stop()
    # An older run's crash report stays in the log, which is kept across starts.
    with open(data / "server.log", "a") as log:
        log.write("=== REDIS BUG REPORT START: Cut & paste starting from here ===\ncrashed by signal: 11\n")
    manifest = next((data / "appendonlydir").glob("*.manifest"))
    manifest.write_text("not a manifest\n")
    with pytest.raises(StoreUnavailable) as caught:
        EmbeddedServer(data).ensure()
    message = str(caught.value)
    assert "exited with status" in message and str(data / "server.log") in message
    assert "not a manifest" in message and "AOF MANIFEST" in message
    assert "crashed by signal" not in message


def test_a_crash_while_starting_shows_the_head_of_the_bug_report(tmp_path):
    data = tmp_path / "store"
    data.mkdir()
    # Only the reading of the log is under test here: the report is written as redis writes it.
    from kgadapt.knowledge import embedded

    log = data / "server.log"
    log.write_text("old line\n")
    offset = log.stat().st_size
    report = ["=== REDIS BUG REPORT START: Cut & paste starting from here ===",
              "12:M 25 Nov 2026 10:00:00.000 # Redis 7.2 crashed by signal: 11, si_code: 1",
              "------ STACK TRACE ------", *[f"frame {i}" for i in range(40)],
              "  Some other issues could be detected by redis-server --check-system"]
    with open(log, "a") as f:
        f.write("\n".join(report) + "\n")
    shown = embedded._tail(log, offset)
    assert "crashed by signal: 11" in shown and "STACK TRACE" in shown and "old line" not in shown
    assert "--check-system" not in shown


def test_a_restart_sends_no_command_while_the_server_replays_its_aof(tmp_path):
    """FalkorDB yields to the event loop while it replays a MULTI/EXEC of graph writes, and a command
    arriving then aborts the server ('!server.in_exec'). The starter waits for the log's ready line,
    so its first connection is the one PING after loading."""
    import re

    import redis

    data = tmp_path / "store"
    server = EmbeddedServer(data)
    address = server.ensure()
    client = redis.Redis(unix_socket_path=address.unix_socket)
    client.execute_command("GRAPH.QUERY", "g", "CREATE INDEX FOR (n:N) ON (n.i)")
    for batch in range(40):  # a model load's shape: many writes in MULTI/EXEC, in the AOF
        pipe = client.pipeline(transaction=True)
        for i in range(250):
            pipe.execute_command("GRAPH.QUERY", "g", "CREATE (:N {i: $i})".replace("$i", str(batch * 250 + i)))
        pipe.execute()
    client.close()
    server.stop()
    log = data / "server.log"
    before = log.stat().st_size

    restarted = EmbeddedServer(data, start_timeout=60)
    address = restarted.ensure()
    try:
        client = redis.Redis(unix_socket_path=address.unix_socket)
        connections = int(client.info("stats")["total_connections_received"])
        count = client.execute_command("GRAPH.RO_QUERY", "g", "MATCH (n:N) RETURN count(n)")[1][0][0]
        client.close()
    finally:
        restarted.stop()
    replay = re.search(rb"DB loaded from incr file [^:]+: ([0-9.]+) seconds", log.read_bytes()[before:])
    assert replay is not None, "the restart replayed no AOF"
    # The old starter pinged every 5 ms from the moment the socket existed: tens of connections here.
    assert float(replay.group(1)) > 0.02, "the AOF replays too fast to tell"
    assert connections == 2, f"{connections} connections by the time the data was loaded (starter's PING + this one)"
    assert count == 10_000


def test_a_model_load_leaves_a_snapshot_so_a_restart_replays_no_graph_query(tmp_path):
    """After ``load_models`` the append-only file is rewritten as a snapshot: the restart reads the graph
    from it and replays none of the load's index creations or MULTI/EXEC writes (the path where FalkorDB
    yields mid-replay)."""
    from kgadapt.knowledge.loader import load_models
    from kgadapt.knowledge.store import open_store
    from tests.conftest import REPO

    data = tmp_path / "store"
    with open_store(f"embedded:{data}") as store:
        load_models(store, [REPO / "knowledge" / "models"])
        features = store.execute("MATCH (f:Feature) RETURN count(f) AS n", read_only=True)[0]["n"]
    increments = list((data / "appendonlydir").glob("*.incr.aof"))
    assert increments, "no append-only file"
    replayed = b"".join(path.read_bytes() for path in increments)
    assert b"GRAPH.QUERY" not in replayed and b"MULTI" not in replayed
    with open_store(f"embedded:{data}") as store:
        assert store.execute("MATCH (f:Feature) RETURN count(f) AS n", read_only=True)[0]["n"] == features > 0


def test_a_start_that_never_becomes_ready_is_killed_and_started_once_more(tmp_path):
    """FalkorDB 4.16 has hung now and then replaying its AOF at a start under load, never ready; the same
    files then loaded at once. Here the first server started is stopped (SIGSTOP) as soon as it appears:
    the starter kills it after its timeout and the second one serves the data."""
    import signal
    import threading

    import psutil
    import redis

    data = tmp_path / "store"
    server = EmbeddedServer(data)
    address = server.ensure()
    client = redis.Redis(unix_socket_path=address.unix_socket)
    client.execute_command("GRAPH.QUERY", "g", "UNWIND range(1, 1000) AS i CREATE (:N {i: i})")
    client.close()
    server.stop()

    stopped: list[int] = []
    done = threading.Event()

    def stop_the_first() -> None:
        me = psutil.Process()
        while not done.is_set() and not stopped:
            for child in me.children():
                try:
                    if "redis-server" in " ".join(child.cmdline()) and str(data) in " ".join(child.cmdline()):
                        child.send_signal(signal.SIGSTOP)
                        stopped.append(child.pid)
                        break
                except psutil.Error:
                    continue
            time.sleep(0.0005)

    watcher = threading.Thread(target=stop_the_first, daemon=True)
    watcher.start()
    restarted = EmbeddedServer(data, start_timeout=10)
    try:
        address = restarted.ensure()
        done.set()
        assert stopped and address.pid != stopped[0]
        assert not psutil.pid_exists(stopped[0]) or psutil.Process(stopped[0]).status() == psutil.STATUS_ZOMBIE
        client = redis.Redis(unix_socket_path=address.unix_socket)
        assert client.execute_command("GRAPH.RO_QUERY", "g", "MATCH (n:N) RETURN count(n)")[1][0][0] == 1000
        client.close()
    finally:
        done.set()
        restarted.stop()
