"""The local supervisor with real child processes (no Zenoh)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time

import psutil
import pytest

from kgadapt.deploy.supervisor import ProcessEvent, ProcessSpec, RestartPolicy, StopPolicy, Supervisor, SupervisorSettings
from kgadapt.shared.errors import DeploymentError, ReadinessTimeout
from kgadapt.shared.readiness import READY_TOKEN

SAY_READY = f"print({READY_TOKEN!r}, flush=True)"  # the bare token: what a program that is not ours may print
READY_AND_WAIT = f"import time; {SAY_READY}; time.sleep(60)"
DEAF = (
    "import signal, time\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    f"{SAY_READY}; time.sleep(60)"
)


def py(code: str) -> tuple[str, ...]:
    return (sys.executable, "-c", code)


def spec(instance: str, code: str, **kw) -> ProcessSpec:
    kw.setdefault("ready_timeout", 10.0)
    return ProcessSpec(instance=instance, argv=py(code), **kw)


class Recorder:
    """Collects events; wait_for blocks until one of a kind arrives."""

    def __init__(self) -> None:
        self.events: list[ProcessEvent] = []
        self._cv = threading.Condition()

    def __call__(self, event: ProcessEvent) -> None:
        with self._cv:
            self.events.append(event)
            self._cv.notify_all()

    def kinds(self, instance: str) -> list[str]:
        with self._cv:
            return [e.event for e in self.events if e.instance == instance]

    def wait_for(self, instance: str, kind: str, count: int = 1, timeout: float = 15.0) -> None:
        with self._cv:
            ok = self._cv.wait_for(lambda: self.kinds(instance).count(kind) >= count, timeout)
        assert ok, f"no {count}x {kind} for {instance}; saw {self.kinds(instance)}"


@pytest.fixture
def events():
    return Recorder()


@pytest.fixture
def supervisor(events):
    sup = Supervisor()
    sup.add_listener(events)
    sup.setup()
    yield sup
    sup.shutdown()


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def wait_gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if gone(pid):
            return True
        time.sleep(0.02)
    return False


def test_a_started_child_is_ready_and_stops_on_sigint(supervisor, events):
    info = supervisor.start(spec("a", READY_AND_WAIT))
    assert info.state == "ready" and info.pid and info.ready_at >= info.started_at
    assert not gone(info.pid)
    final = supervisor.stop("a")
    assert final.state == "stopped"
    assert final.returncode == -signal.SIGINT  # Python dies of the SIGINT it did not handle
    assert gone(info.pid)
    assert events.kinds("a") == ["started", "ready", "exited", "stopped"]


def test_a_child_that_handles_sigint_exits_cleanly_without_escalation(supervisor):
    code = f"import time\ntry:\n    {SAY_READY}\n    time.sleep(60)\nexcept KeyboardInterrupt:\n    pass"
    supervisor.start(spec("clean", code))
    assert supervisor.stop("clean").returncode == 0


def test_a_child_deaf_to_sigint_and_sigterm_is_killed_after_the_timeouts(supervisor):
    stop = StopPolicy(sigint_timeout=0.3, sigterm_timeout=0.3)
    supervisor.start(spec("deaf", DEAF, stop=stop))
    t0 = time.monotonic()
    final = supervisor.stop("deaf")
    elapsed = time.monotonic() - t0
    assert final.returncode == -signal.SIGKILL
    assert elapsed >= 0.6  # both timeouts were given before SIGKILL


def test_a_crashing_child_is_restarted_up_to_the_limit_then_reported_failed(supervisor, events):
    policy = RestartPolicy(max_restarts=2, backoff_initial=0.05)
    with pytest.raises(DeploymentError, match="status 3 after 2 restarts.*boom"):
        supervisor.start(spec("crash", "import sys; print('boom'); sys.exit(3)", restart=policy))
    kinds = events.kinds("crash")
    assert kinds.count("started") == 3 and kinds.count("restarted") == 2
    assert kinds.count("exited") == 3 and kinds[-1] == "failed"
    info = supervisor.status("crash")
    assert info.state == "failed" and info.returncode == 3 and info.restarts == 2


def test_a_crash_is_reported_with_its_last_output_even_when_the_exit_is_seen_before_the_output_is_read(
        supervisor, events):
    """The child says ready, says why it fails and exits. Its reader is held (in the listener of the ready
    event, as a loaded machine's scheduler may hold it) until the supervisor has reaped the child: the last
    line is then still in the pipe. The exit's report waits for the reader (a loaded run once reported a
    crash without its reason)."""
    reaped = threading.Event()

    def hold_the_reader(event: ProcessEvent) -> None:
        if event.instance == "chatty" and event.event == "ready":
            deadline = time.monotonic() + 10.0
            while supervisor.status("chatty").returncode is None and time.monotonic() < deadline:
                reaped.wait(0.02)  # the waiter's reap has no event of its own to wait on
            reaped.set()

    supervisor.add_listener(hold_the_reader)
    code = f"import os; {SAY_READY}; print('why: boom', flush=True); os._exit(3)"
    supervisor.start(spec("chatty", code, restart=RestartPolicy(max_restarts=0)))
    events.wait_for("chatty", "failed")
    assert reaped.is_set()
    exited = [e for e in events.events if e.instance == "chatty" and e.event == "exited"]
    assert exited[0].returncode == 3 and exited[0].detail == "why: boom", exited
    info = supervisor.status("chatty")
    assert info.state == "failed" and info.detail is not None and info.detail.endswith("last output: why: boom"), info


def test_backoff_grows_between_restarts(supervisor, events):
    policy = RestartPolicy(max_restarts=2, backoff_initial=0.2, backoff_factor=2.0)
    with pytest.raises(DeploymentError):
        supervisor.start(spec("slowcrash", "import sys; sys.exit(1)", restart=policy))
    starts = [e.time for e in events.events if e.instance == "slowcrash" and e.event == "started"]
    exits = [e.time for e in events.events if e.instance == "slowcrash" and e.event == "exited"]
    assert starts[1] - exits[0] >= 0.2 and starts[2] - exits[1] >= 0.4


def test_a_child_that_crashes_after_ready_comes_back_ready(supervisor, events, tmp_path):
    flag = tmp_path / "crashed-once"
    code = textwrap.dedent(f"""
        import os, sys, time
        {SAY_READY}
        if not os.path.exists({str(flag)!r}):
            open({str(flag)!r}, 'w').close()
            sys.exit(5)
        time.sleep(60)
    """)
    supervisor.start(spec("phoenix", code, restart=RestartPolicy(backoff_initial=0.05)))
    events.wait_for("phoenix", "ready", count=2)
    info = supervisor.status("phoenix")
    assert info.state == "ready" and info.restarts == 1
    assert events.kinds("phoenix")[:5] == ["started", "ready", "exited", "started", "restarted"]


def test_a_child_that_never_gets_ready_is_stopped_and_not_restarted(supervisor, events):
    with pytest.raises(ReadinessTimeout, match=f"{READY_TOKEN} within 0.3 s"):
        supervisor.start(spec("mute", "import time; time.sleep(60)", ready_timeout=0.3))
    info = supervisor.status("mute")
    assert info.state == "failed" and gone(info.pid)
    assert events.kinds("mute").count("started") == 1


def test_stopping_a_child_also_ends_the_processes_it_started(supervisor):
    code = textwrap.dedent(f"""
        import subprocess, time
        child = subprocess.Popen(['sleep', '60'])
        print(child.pid, flush=True)
        {SAY_READY}
        time.sleep(60)
    """)
    supervisor.start(spec("parent", code))
    grandchild = _first_number_in_output(supervisor, "parent")
    assert not gone(grandchild)
    supervisor.stop("parent")
    assert wait_gone(grandchild)


def test_a_live_instance_name_cannot_be_started_twice(supervisor):
    supervisor.start(spec("twice", READY_AND_WAIT))
    with pytest.raises(DeploymentError, match="already running"):
        supervisor.start(spec("twice", READY_AND_WAIT))


def test_a_missing_program_is_refused_naming_it(supervisor):
    with pytest.raises(DeploymentError, match="no-such-detector"):
        supervisor.start(ProcessSpec(instance="ghost", argv=("/nonexistent/no-such-detector",)))
    assert supervisor.status("ghost").state == "failed"


def test_a_stop_during_backoff_ends_the_restarts(supervisor, events):
    policy = RestartPolicy(max_restarts=5, backoff_initial=60.0)
    supervisor.start(spec("loop", "import sys; sys.exit(1)", restart=policy), wait_ready=False)
    events.wait_for("loop", "exited")
    t0 = time.monotonic()
    assert supervisor.stop("loop").state == "stopped"
    assert time.monotonic() - t0 < 30.0  # the 60 s back-off wait was cut short
    assert events.kinds("loop").count("started") == 1


def test_shutdown_stops_every_child(events):
    sup = Supervisor()
    sup.add_listener(events)
    sup.setup()
    pids = [sup.start(spec(f"s{i}", READY_AND_WAIT)).pid for i in range(3)]
    sup.shutdown()
    assert all(gone(pid) for pid in pids)


@pytest.mark.parametrize("launcher", ["preexec", pytest.param("setpriv", marks=pytest.mark.skipif(
    not shutil.which("setpriv"), reason="util-linux setpriv is not installed"))])
def test_killing_the_supervising_process_with_sigkill_kills_its_children(tmp_path, launcher):
    script = tmp_path / "agent.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {os.getcwd()!r})
        from kgadapt.deploy.supervisor import ProcessSpec, Supervisor, SupervisorSettings
        sup = Supervisor(SupervisorSettings(death_signal_via={launcher!r})); sup.setup()
        info = sup.start(ProcessSpec(instance="det", argv=({sys.executable!r}, "-c", {DEAF!r})))
        print(info.pid, flush=True)
        time.sleep(60)
    """))
    agent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(agent.stdout.readline())
        assert not gone(child)
        agent.kill()
        agent.wait()
        assert wait_gone(child, timeout=5.0)
    finally:
        agent.kill()
        agent.wait()


def _first_number_in_output(supervisor: Supervisor, instance: str) -> int:
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        for line in supervisor.status(instance).output:
            if line.strip().isdigit():
                return int(line.strip())
        time.sleep(0.02)
    raise AssertionError("the child did not print its child's pid")


def test_an_unknown_way_to_set_the_death_signal_is_refused_naming_it():
    with pytest.raises(DeploymentError, match="death_signal_via 'fork'"):
        SupervisorSettings(death_signal_via="fork")  # type: ignore[arg-type]  # the wrong value is the test
    with pytest.raises(DeploymentError, match="launcher 'setpriv'"):  # the old meaning of the name
        SupervisorSettings(launcher="setpriv")  # type: ignore[arg-type]  # the wrong value is the test


def test_a_supervisor_in_a_process_that_ignores_sigint_still_stops_its_child_with_sigint():
    # A background job of a non-interactive shell (CI, for one) starts with SIGINT ignored,
    # and an ignored signal stays ignored across fork and exec.
    code = textwrap.dedent(f"""
        import signal, sys
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        from kgadapt.deploy.supervisor import ProcessSpec, Supervisor
        sup = Supervisor()
        sup.setup()
        sup.start(ProcessSpec(instance="c", argv=(sys.executable, "-c", {READY_AND_WAIT!r})))
        print(sup.stop("c").returncode)
        sup.shutdown()
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip().splitlines()[-1]) == -signal.SIGINT


def test_a_launcher_gets_ready_whatever_openblas_threads_the_agents_environment_asks_for(tmp_path):
    # A value in kgadapt.env (OPENBLAS_NUM_THREADS=2) made every launcher exit with "3 threads after the
    # imports", restarted every 0.5 s for ever, each start then the plain way.
    script = tmp_path / "agent.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {os.getcwd()!r})
        from kgadapt.deploy.supervisor import Supervisor, SupervisorSettings
        sup = Supervisor(SupervisorSettings(launcher=True)); sup.setup()
        try:
            print(sup.launcher.wait_ready(60.0), sup.launcher.starts, flush=True)
        finally:
            sup.shutdown()
    """))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "2"})
    assert done.stdout.split() == ["True", "1"], done.stdout + done.stderr[-2000:]
