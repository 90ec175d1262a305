"""The one readiness protocol and the one way to start and stop a child, with real child processes.

A real AF_UNIX datagram socket stands where systemd's ``$NOTIFY_SOCKET`` would be.
"""

from __future__ import annotations

import io
import os
import signal
import socket
import sys
import textwrap
import threading
from pathlib import Path

import psutil
import pytest

from kgadapt.shared.children import ChildProcess, StopPolicy
from kgadapt.shared.errors import NotReady, ReadinessTimeout
from kgadapt.shared.readiness import READY_TOKEN, announce_ready, parse_ready, ready_line
from tests.conftest import REPO

ENV = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
ENV.pop("NOTIFY_SOCKET", None)


def python_child(code: str, name: str, tmp_path: Path, **kw) -> ChildProcess:
    env = {**ENV, **kw.pop("env", {})}
    return ChildProcess([sys.executable, "-c", textwrap.dedent(code)], name=name, env=env,
                        log=tmp_path / f"{name}.log", **kw)


def test_a_readiness_line_is_the_token_and_a_json_object_and_nothing_else_is_one():
    line = ready_line(role="onboard", robot="quad1")
    assert line.startswith(READY_TOKEN + " ")
    assert parse_ready(line) == {"pid": os.getpid(), "role": "onboard", "robot": "quad1"}
    assert parse_ready(f"  {READY_TOKEN}\n") == {}  # the bare token: a program that is not Python
    for not_ready in (f"{READY_TOKEN}X", f"{READY_TOKEN} [1, 2]", f"{READY_TOKEN} {{broken", f"say {READY_TOKEN}",
                      "onboard agent ready: robot quad1", ""):
        assert parse_ready(not_ready) is None, not_ready


def test_a_child_that_gets_ready_hands_over_its_payload_and_is_stopped_by_sigint(tmp_path):
    child = python_child("""
        import signal, time
        from kgadapt.shared.readiness import announce_ready
        # A suite started in the background of a non-interactive shell hands its children SIGINT ignored,
        # and Python then installs no KeyboardInterrupt handler: restore Python's own.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        print("warming up", flush=True)
        announce_ready(status="test child ready", role="test", n=3)
        print("after ready", flush=True)
        time.sleep(60)
    """, "ready-child", tmp_path)
    try:
        payload = child.wait_ready(30)
        assert payload == {"pid": child.pid, "role": "test", "n": 3}
        assert child.wait_for_line("after ready", 10)
    finally:
        # A generous first step: at load 25 one such child took over 10 s to die of its SIGINT.
        code = child.stop(StopPolicy(sigint_timeout=60))
    assert code == -signal.SIGINT  # Python dies of the SIGINT it did not handle: the first step was enough
    assert "warming up" in (tmp_path / "ready-child.log").read_text()  # stdout copied to its log


def test_a_child_that_exits_before_it_is_ready_is_named_with_its_last_output(tmp_path):
    child = python_child("""
        import sys
        print("loading the models", flush=True)
        print("no such store", file=sys.stderr, flush=True)
        sys.exit(3)
    """, "early-exit", tmp_path)
    with pytest.raises(NotReady) as caught:
        child.wait_ready(30)
    assert not isinstance(caught.value, ReadinessTimeout)
    message = str(caught.value)
    assert "early-exit exited with status 3" in message and READY_TOKEN in message
    assert "loading the models" in message and "no such store" in message
    assert child.stop() == 3


def test_a_child_that_hangs_past_the_timeout_is_named_and_stops_on_escalation(tmp_path):
    # Deaf to SIGINT: the stop must go on to SIGTERM.
    child = python_child("""
        import signal, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("waiting for a router that never comes", flush=True)
        time.sleep(60)
    """, "hanger", tmp_path)
    try:
        with pytest.raises(ReadinessTimeout, match=f"hanger did not print {READY_TOKEN} within 0.5 s") as caught:
            child.wait_ready(0.5)
        assert "waiting for a router that never comes" in str(caught.value)
    finally:
        code = child.stop(StopPolicy(sigint_timeout=0.3, sigterm_timeout=10))
    assert code == -signal.SIGTERM


def test_stopping_a_child_ends_its_whole_process_group_even_when_it_ignores_sigint_and_sigterm(tmp_path):
    child = python_child("""
        import signal, subprocess, time
        from kgadapt.shared.readiness import announce_ready
        grandchild = subprocess.Popen(["sleep", "60"])
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        announce_ready(grandchild=grandchild.pid)
        time.sleep(60)
    """, "deaf", tmp_path)
    grandchild = child.wait_ready(30)["grandchild"]
    assert psutil.pid_exists(grandchild)
    assert child.stop(StopPolicy(sigint_timeout=0.2, sigterm_timeout=0.2)) == -signal.SIGKILL
    # The group's SIGINT (not ignored by sleep) ended the grandchild; reaped by nobody yet is fine, running is not.
    assert not psutil.pid_exists(grandchild) or psutil.Process(grandchild).status() == psutil.STATUS_ZOMBIE


def test_announcing_readiness_sends_ready_to_the_notify_socket_and_prints_the_line(tmp_path):
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(30)
        child = python_child("""
            import time
            from kgadapt.shared.readiness import announce_ready
            announce_ready(status="notify child ready", role="notified")
            time.sleep(60)
        """, "notified", tmp_path, env={"NOTIFY_SOCKET": path})
        try:
            message = sock.recv(4096).decode()
            payload = child.wait_ready(30)
        finally:
            child.stop()
    assert message.splitlines() == ["READY=1", "STATUS=notify child ready"]
    assert payload == {"pid": child.pid, "role": "notified"}


def test_no_module_but_the_readiness_module_spells_the_token():
    """Every process and every waiter goes through kgadapt.shared.readiness."""
    own = REPO / "shared" / "readiness.py"
    found = []
    for folder, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if not d.startswith(".") and d not in ("build", "dist", "__pycache__")]
        for path in (Path(folder) / f for f in files if f.endswith(".py")):
            if path != own and READY_TOKEN in path.read_text(errors="replace"):
                found.append(str(path.relative_to(REPO)))
    assert found == [], f"spell the token through kgadapt.shared.readiness instead: {found}"


def test_a_detectors_record_and_its_readiness_line_written_from_two_threads_never_share_a_line():
    # A detector's reflex may record a swap (KGADAPT_CONFIGURED) on its frame thread while the main thread
    # announces it is ready; with the text and its newline written apart, the readiness line once began in
    # the middle of the record and the deployer never saw it (the start timed out).
    from kgadapt.shared.readiness import CONFIGURED_TOKEN, announce_configured

    r, w = os.pipe()
    # As a detector's stdout to its supervisor with PYTHONUNBUFFERED=1: every write goes to the pipe at once.
    out = io.TextIOWrapper(io.FileIO(w, "w"), line_buffering=True, write_through=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(os.fdopen(r).read().splitlines()))
    reader.start()
    rounds = 2000
    start = threading.Barrier(2)

    def records() -> None:
        start.wait()
        for i in range(rounds):
            announce_configured(f"config_{i}", "detector_day", out=out)

    def readiness() -> None:
        start.wait()
        for i in range(rounds):
            announce_ready(out=out, instance=f"i{i}")

    threads = [threading.Thread(target=records), threading.Thread(target=readiness)]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads take turns as often as they can: a loaded machine's worst case
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(interval)
    out.close()
    reader.join()
    ready = [line for line in lines if parse_ready(line) is not None]
    recorded = [line for line in lines if line.startswith(CONFIGURED_TOKEN + " ") and line.endswith(" detector_day")]
    assert len(ready) == rounds and len(recorded) == rounds, [x for x in lines if x not in ready and x not in recorded][:3]


_PARENT = """
import sys, threading, time
from kgadapt.shared.children import ChildProcess
grandchild = [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(120)"]
made = []
def start():
    made.append(ChildProcess(grandchild, name="grandchild", death_signal=%s))
if %r:
    worker = threading.Thread(target=start)
    worker.start()
    worker.join()  # the thread that started it has ended
else:
    start()
made[0].wait_for_line("up", 30)
print(made[0].pid, flush=True)
time.sleep(120)
"""


@pytest.mark.parametrize("death_signal, on_thread, ends", [
    ("signal.SIGTERM", False, True),   # the default, from the main thread: tied to us
    ("None", False, False),            # asked not to be
    ("signal.SIGTERM", True, False),   # started on a thread that ended since: never tied
], ids=["main-thread", "untied", "worker-thread"])
def test_a_child_ends_when_its_parent_is_killed_unless_untied_or_started_on_another_thread(
        death_signal, on_thread, ends):
    import subprocess

    code = "import signal\n" + _PARENT % (death_signal, on_thread)
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=ENV)
    child = None
    try:
        line = parent.stdout.readline()
        assert line.strip().isdigit(), f"the parent printed {line!r}, not its child's pid"
        child = psutil.Process(int(line))
        parent.kill()
        parent.wait(10)
        try:
            child.wait(10 if ends else 1)
            ended = True
        except psutil.TimeoutExpired:
            ended = False
        assert ended is ends, f"the child {'outlived' if ends else 'did not outlive'} its killed parent"
    finally:
        parent.kill()
        parent.wait(10)
        if child is not None:
            try:
                child.kill()
                child.wait(10)  # reaped here if it was handed to us (a test made this process a subreaper)
            except psutil.NoSuchProcess:
                pass
