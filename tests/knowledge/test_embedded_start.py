"""A FalkorDB that cannot start says why, from this start's own log lines."""

from __future__ import annotations

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
