"""The per-host launcher (deploy/launcher.py) with the shipped models and the real marker detector.

Real processes throughout: the deployers run in this test process (which
becomes their child subreaper), the launcher is their child, and the forked
detectors are adopted by them.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import psutil
import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.migration import reconfigure
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.loader import load_models
from kgadapt.shared import keys
from kgadapt.shared.errors import DeploymentError
from kgadapt.shared.proc_stat import stat_fields
from kgadapt.shared.readiness import READY_TOKEN
from tests.deploy.conftest import ROBOT, Collector, DeployerHost, FrameSource, not_roll_calls, wait_for_deployers
from tests.deploy.test_deployer import alive, wait_until
from tests.deploy.test_real_detector import marker_jpeg
from tests.support import Child

MODELS = Path(S.__file__).resolve().parent / "models"
DAY = "marker_detection_day"


@pytest.fixture
def launcher() -> bool:
    return True


@pytest.fixture
def graph(resp_store):
    load_models(resp_store, [MODELS])
    return resp_store


def launcher_of(hosts, name: str = "onboard"):
    launcher = hosts[name].deployer.supervisor.launcher
    assert launcher is not None, "the deployer runs no launcher"
    assert launcher.wait_ready(60.0), "the launcher did not get ready"
    return launcher


def test_a_detector_forked_by_the_launcher_is_the_agents_child_gets_ready_and_detects(hosts, client_session):
    launcher = launcher_of(hosts)
    frames = FrameSource(client_session, fps=30.0, jpeg=marker_jpeg(), size=(320, 240))
    markers = Collector(client_session, keys.detector_markers(ROBOT, "*"), "detections")
    try:
        client = DeployerClient(client_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance="forked1")
        assert info.via == "launcher" and info.state in ("ready", "running")
        process = psutil.Process(info.pid)
        assert process.ppid() == os.getpid()  # adopted by the deployer, not left with the launcher
        assert os.getpgid(info.pid) == info.pid  # its own process group, as a plain start
        assert info.pid not in [c.pid for c in psutil.Process(launcher.pid).children()]
        _, first = markers.wait_for(lambda d: d["instance"] == "forked1" and d["ids"])
        assert first["ids"] == [7] and first["config"] == DAY and first["host"] == "onboard"
        # Run as its preloaded module's main: no second copy as __main__ (runpy warned of it in its output).
        output = "\n".join(client.status("onboard", "forked1").output or [])
        assert "RuntimeWarning" not in output, output
        stopped = client.stop("onboard", "forked1")
        assert stopped.state == "stopped" and stopped.returncode == 0  # SIGINT stops it cleanly
    finally:
        markers.close()
        frames.close()


def test_a_forked_detector_killed_with_sigkill_is_noticed_and_restarted(hosts, client_session):
    launcher_of(hosts)
    events = Collector(client_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    try:
        client = DeployerClient(client_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance="crashy")
        assert info.via == "launcher"
        os.kill(info.pid, signal.SIGKILL)
        _, exited = events.wait_for(lambda e: e["instance"] == "crashy" and e["event"] == "exited")
        assert exited["returncode"] == -signal.SIGKILL and exited["pid"] == info.pid
        events.wait_for(lambda e: e["instance"] == "crashy" and e["event"] == "restarted")
        _, ready = events.wait_for(lambda e: e["instance"] == "crashy" and e["event"] == "ready"
                                   and e["pid"] != info.pid)
        again = client.status("onboard", "crashy")
        assert again.pid == ready["pid"] and again.restarts == 1 and again.via == "launcher"
        assert not alive(info.pid)  # reaped by the deployer: no zombie left
        client.stop("onboard", "crashy")
    finally:
        events.close()


def test_a_killed_launcher_means_a_plain_start_then_a_new_launcher(hosts, client_session):
    launcher = launcher_of(hosts)
    first_pid, starts = launcher.pid, launcher.starts
    client = DeployerClient(client_session, ROBOT)
    kept = client.start("onboard", "detector_day", DAY, instance="kept")
    assert kept.via == "launcher"
    os.kill(first_pid, signal.SIGKILL)
    wait_until(lambda: launcher.pid != first_pid, what="the deployer noticed its launcher died")
    # The next start does not wait for the new launcher: the plain way, if it is not ready yet.
    plain = client.start("onboard", "detector_day", DAY, instance="plain")
    assert plain.via in ("exec", "launcher")
    wait_until(lambda: launcher.starts == starts + 1 and launcher.ready, timeout=60.0, what="a new launcher")
    assert launcher.pid != first_pid
    assert client.status("onboard", "kept").state in ("ready", "running")  # the launcher's death killed no detector
    forked = client.start("onboard", "detector_day", DAY, instance="forked2")
    assert forked.via == "launcher"
    for name in ("kept", "plain", "forked2"):
        client.stop("onboard", name)


def test_a_dead_launcher_falls_back_to_a_plain_start(hosts, client_session):
    launcher = launcher_of(hosts)
    os.kill(launcher.pid, signal.SIGSTOP)  # hung: no answer, then killed by its deployer
    launcher.reply_timeout = 0.5
    try:
        info = DeployerClient(client_session, ROBOT).start("onboard", "detector_day", DAY, instance="fallback")
        assert info.via == "exec" and info.state in ("ready", "running")
    finally:
        pid = launcher.pid
        if pid is not None:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
    DeployerClient(client_session, ROBOT).stop("onboard", "fallback")


def test_the_launcher_runs_nothing_the_graph_does_not_deploy(hosts, client_session):
    launcher_of(hosts)
    client = DeployerClient(client_session, ROBOT)
    with pytest.raises(DeploymentError, match="not in the knowledge store"):
        client.start("onboard", "no_such_deployment", DAY)
    with pytest.raises(DeploymentError, match="does not deploy"):
        client.start("onboard", "detector_day", "marker_detection_dark")
    assert hosts["onboard"].deployer.processes() == []


def test_the_launcher_forks_only_modules_it_preloaded(hosts):
    launcher = launcher_of(hosts)
    python = hosts["onboard"].deployer.settings.python
    assert launcher.fork([python, "-c", f"print({READY_TOKEN!r})"], dict(os.environ), None) is None
    assert launcher.fork([python, "-m", "http.server"], dict(os.environ), None) is None
    assert launcher.fork(["/bin/sh", "-m", "kgadapt.onboard.perception.detector"], dict(os.environ), None) is None
    # The tests' stand-in is no runtime detector: the launcher does not preload it, so it is not forked.
    assert launcher.fork([python, "-m", "kgadapt.sim.echo_detector"], dict(os.environ), None) is None
    assert launcher.ready  # a refusal is not a failure of the launcher


def dying(pid: int) -> bool:
    """Gone, exiting, or with SIGKILL pending: what the kernel has done to a process it was asked to end."""
    try:
        fields = stat_fields(pid)
        with open(f"/proc/{pid}/status") as f:
            status = dict(line.split(":", 1) for line in f if ":" in line)
    except (FileNotFoundError, ProcessLookupError):
        return True
    kill_bit = 1 << (signal.SIGKILL - 1)
    pending = int(status["SigPnd"], 16) | int(status["ShdPnd"], 16)
    return fields[0] in (b"Z", b"X") or bool(int(fields[6]) & 0x4) or bool(pending & kill_bit)  # 0x4: PF_EXITING


def tied(pid: int) -> bool:
    """Whether the pool member ``pid`` has asked for both of its deaths: its own session, which it takes
    right after asking for its parent-death signal and for SIGKILL on the lifeline (``O_ASYNC`` on a
    descriptor of its own). Its inherited descriptors prove nothing: a member just forked already holds
    its intermediate process's lifeline, whose signal goes to that process, not to the member."""
    try:
        if os.getsid(pid) != pid:
            return False
        for fd in os.listdir(f"/proc/{pid}/fdinfo"):
            with open(f"/proc/{pid}/fdinfo/{fd}") as f:
                flags = next((int(line.split()[1], 8) for line in f if line.startswith("flags:")), 0)
            if flags & os.O_ASYNC:
                return True
    except OSError:
        pass
    return False


def test_killing_the_agent_with_sigkill_ends_every_process_under_it_idle_pool_members_too(
        knowledge, endpoint, test_session, tmp_path):
    agent = Child([sys.executable, "-m", "kgadapt", "deploy", "serve", "--robot", ROBOT, "--host", "onboard",
                   "--connect", endpoint, "--pool", "1"], "agent", tmp_path)
    try:
        agent.wait_ready()
        assert "agent ready" in agent.output[0]  # the line for people comes first
        wait_for_deployers(test_session, ["onboard"])
        client = DeployerClient(test_session, ROBOT)
        launcher = wait_until(lambda: (found := client.launcher("onboard")) and found.ready and found,
                              timeout=60.0, what="the agent's launcher ready")
        info = client.start("onboard", "detector_day", DAY)
        # Forked, or handed to the idle detector its launcher keeps (--pool 1).
        assert info.via in ("launcher", "pool") and psutil.Process(info.pid).ppid() == agent.pid
        idle = wait_until(lambda: client.launcher("onboard").idle_members, timeout=30.0, what="an idle pool member")
        # The launcher names a member once it is forked, before the member has run a line: on a loaded machine
        # it may not yet have asked for its deaths (it would die one death later, when it finds its parent gone).
        wait_until(lambda: all(tied(pid) for pid in idle), what="the idle members to ask for their deaths")
        under = {p.pid: " ".join(p.cmdline()) for p in psutil.Process(agent.pid).children(recursive=True)}
        assert {info.pid, launcher.pid, *idle} <= set(under), under
        os.kill(agent.pid, signal.SIGKILL)
        agent.process.wait()
        # By the time the agent can be reaped the kernel has told every process under it to end: its
        # detector (parent-death signal), its launcher (the same) and each idle member and its intermediate
        # process (the lifeline pipe, which closed with the agent's files) - not one after another.
        assert [(pid, line) for pid, line in under.items() if not dying(pid)] == []
        wait_until(lambda: not any(alive(pid) for pid in under), timeout=10.0,
                   what="every process under the agent gone after its kill -9")
    finally:
        agent.stop()


def test_idle_members_end_when_the_agents_lifeline_closes_though_their_launcher_lives(knowledge, endpoint, test_session):
    """What a dying agent does to its idle pool members, without killing the launcher: the lifeline pipe's
    write end (this process, the agent here, holds it) closes, and the members end at once."""
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, warm_refresh_s=600.0)
    try:
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and launcher.wait_ready(60.0)
        assert host.deployer.warm("detector_day", DAY) == 1
        wait_until(lambda: launcher.idle_pids(), what="an idle pool member")
        members = launcher.idle_pids()
        assert launcher.pid is not None and all(alive(pid) for pid in members)
        # The lifeline: the one pipe this process shares with the launcher (beyond the standard streams).
        theirs = {os.readlink(f"/proc/{launcher.pid}/fd/{fd}") for fd in os.listdir(f"/proc/{launcher.pid}/fd")
                  if int(fd) > 2}
        ours = [int(fd) for fd in os.listdir("/proc/self/fd") if int(fd) > 2 and _link(fd) in theirs
                and _link(fd).startswith("pipe:")]
        assert len(ours) == 1, (ours, theirs)
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, ours[0])  # closes our end as a dying agent's files close (the client closes it later)
        finally:
            os.close(devnull)
        wait_until(lambda: not any(alive(pid) for pid in members), what="the idle members to end with the lifeline")
        assert alive(launcher.pid) and launcher.ready  # not through their launcher: it lives on
    finally:
        host.close()


def test_every_process_that_holds_an_idle_member_yields_its_memory_to_a_start(knowledge, endpoint, test_session):
    """The host monitor leaves out of measured use what its deployer names yielding: every process under
    the launcher while only idle members are there (each member and the intermediate process above it,
    a fork of the launcher of some 30 MiB RSS that ends when its member is taken). Counted, they left the
    700 MiB onboard budget 21 MiB above the dark detector's 324 MiB, and a reflex could send it remote."""
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, warm_refresh_s=600.0)
    try:
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and launcher.wait_ready(60.0)
        assert host.deployer.warm("detector_day", DAY) == 1
        members = wait_until(lambda: launcher.idle_pids(), what="an idle pool member")
        under = {p.pid for p in psutil.Process(launcher.pid).children(recursive=True)}
        assert len(under) == 2 * len(members), under  # each member and its intermediate process
        assert set(host.deployer.yielding_pids()) == under
        client = DeployerClient(test_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance="yields1")
        assert info.via == "pool" and info.pid in members
        # Taken, the member is a detector like any other: measured; the refilled pool yields again.
        wait_until(lambda: launcher.idle_pids() and set(launcher.idle_pids()).isdisjoint(members), what="the pool refilled")
        assert info.pid not in host.deployer.yielding_pids()
        assert set(host.deployer.yielding_pids()) == {p.pid for p in psutil.Process(launcher.pid).children(recursive=True)}
        client.stop("onboard", "yields1")
    finally:
        host.close()


def _link(fd: str) -> str:
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return ""


def test_a_forked_detector_shows_its_own_command_line(hosts, client_session):
    launcher = launcher_of(hosts)
    info = DeployerClient(client_session, ROBOT).start("onboard", "detector_day", DAY, instance="titled")
    try:
        assert psutil.Process(info.pid).cmdline() == info.argv  # what ps and the fault tools look for
        assert psutil.Process(launcher.pid).cmdline()[1:3] == ["-m", "kgadapt.deploy.launcher"]
    finally:
        DeployerClient(client_session, ROBOT).stop("onboard", "titled")


def test_a_forked_detector_runs_with_the_environment_of_the_request_not_the_launchers(hosts, tmp_path):
    # The deployer hands each detector its own Zenoh config (its own certificate) in the
    # environment; a fork has no exec, so the launcher must install it in the child itself.
    launcher = launcher_of(hosts)
    python = hosts["onboard"].deployer.settings.python
    missing = tmp_path / "no-such-zenoh.json5"
    argv = [python, "-m", "kgadapt.onboard.perception.detector", "--robot", ROBOT, "--host", "onboard", "--instance", "env_probe",
            "--config", "marker_detection_day"]
    forked = launcher.fork(argv, {**os.environ, "KGADAPT_ZENOH_CONFIG": str(missing)}, None)
    assert forked is not None, "the launcher refused a preloaded module"
    assert forked.wait() != 0  # its session was built from the request's config file, which is missing
    output = forked.stdout.read() if forked.stdout is not None else b""
    assert READY_TOKEN.encode() not in (output if isinstance(output, bytes) else output.encode())


def test_a_started_detector_takes_the_configuration_its_deployer_resolved_and_asks_for_none(
        hosts, client_session, knowledge):
    """Issue 32 item 2: the start carries the configuration the deployer resolved from the graph."""
    launcher_of(hosts)
    asked: list[tuple[str, float]] = []
    answer_named = knowledge.answer_named

    def counting(name, *args, **kwargs):  # the real service's answer, with when it was asked
        asked.append((name, time.time()))
        return answer_named(name, *args, **kwargs)

    knowledge.answer_named = counting
    events = Collector(client_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    try:
        client = DeployerClient(client_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance="carried")
        assert info.via == "launcher" and info.state in ("ready", "running")
        _, started = events.wait_for(lambda e: e["instance"] == "carried" and e["event"] == "started")
        # The deployer asked the graph before the process existed; the process itself asked nothing.
        assert [n for n, _ in asked if n == "detector_config"], asked
        assert [n for n, at in asked if n == "detector_config" and at >= started["time"]] == []
        client.stop("onboard", "carried")
    finally:
        knowledge.answer_named = answer_named
        events.close()


def others(asked: list[str], by_deployer: list[str]) -> Counter[str]:
    """The named queries the service answered that the deployer did not ask (the detector's own)."""
    return Counter(asked) - Counter(by_deployer)


def test_a_pooled_start_hands_the_configuration_to_an_idle_detector_and_asks_the_graph_nothing(
        knowledge, endpoint, test_session):
    """Issue 32 item 2: the launcher keeps an idle detector (session open); a start takes it."""
    by_deployer: list[str] = []  # the deployer's own questions (it sizes the pool again after a start)
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, asks=by_deployer)
    asked: list[str] = []  # at the service, from anyone
    answer_named = knowledge.answer_named
    frames = FrameSource(test_session, fps=30.0, jpeg=marker_jpeg(), size=(320, 240))
    markers = Collector(test_session, keys.detector_markers(ROBOT, "*"), "detections")
    events = Collector(test_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    try:
        wait_for_deployers(test_session, ["onboard"])
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and launcher.wait_ready(60.0)
        assert host.deployer.warm("detector_day", DAY) == 1
        wait_until(lambda: sum(launcher.idle.values()) == 1, what="an idle pool member")
        members = [p.pid for p in psutil.Process(launcher.pid).children(recursive=True)]
        assert members, "no pool member under the launcher"

        def counting(name, *args, **kwargs):  # the real service's answer
            asked.append(name)
            return answer_named(name, *args, **kwargs)

        # A question of the deployer's warming thread may be on its way as counting begins: it is in the log.
        since = max(0, len(by_deployer) - 1)
        knowledge.answer_named = counting
        client = DeployerClient(test_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance="pooled1")
        assert info.via == "pool" and info.state in ("ready", "running")
        assert info.pid in members  # the idle member took it: no new process
        assert psutil.Process(info.pid).ppid() == os.getpid()  # now the agent's child, as a forked one
        events.wait_for(lambda e: e["instance"] == "pooled1" and e["event"] == "started")
        _, first = markers.wait_for(lambda d: d["instance"] == "pooled1" and d["ids"])
        assert first["config"] == DAY and first["host"] == "onboard"
        # The pool is filled again for the next start.
        wait_until(lambda: sum(launcher.idle.values()) == 1, what="the pool filled again")
        # Neither its configuration nor its reflex table (the candidates, built while it waited) was asked
        # for: every detector_config the service answered came from the deployer (its admission and pool
        # sizing; the member that refilled the pool asked for its own reflex table, as a member does).
        assert not others(asked, by_deployer[since:])["detector_config"], (asked, by_deployer[since:])
        output = "\n".join(client.status("onboard", "pooled1").output or [])
        assert "reflex table prepared in the launcher's pool" in output, output
        stopped = client.stop("onboard", "pooled1")
        assert stopped.state == "stopped" and stopped.returncode == 0
        idle = [p.pid for p in psutil.Process(launcher.pid).children(recursive=True)]
    finally:
        knowledge.answer_named = answer_named
        events.close()
        markers.close()
        frames.close()
        host.close()
    # Idle members end with their launcher.
    wait_until(lambda: not any(alive(pid) for pid in idle), what="the idle pool members to end with the launcher")


def test_a_pooled_start_answers_the_frame_its_idle_member_held_instead_of_waiting_for_the_next(
        knowledge, endpoint, test_session):
    """Issue 32: a change as a new process waited for the camera's next frame after the pooled detector
    subscribed. The idle member holds the newest frame while it waits; the detector it becomes answers
    that frame, published before the start was asked for (frames come about once a second here: a
    detector that subscribed only once taken answers a later one)."""
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, warm_refresh_s=600.0)
    frames = FrameSource(test_session, fps=1.1, jpeg=marker_jpeg(), size=(320, 240))
    markers = Collector(test_session, keys.detector_markers(ROBOT, "*"), "detections")
    try:
        wait_for_deployers(test_session, ["onboard"])
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and launcher.wait_ready(60.0)
        assert host.deployer.warm("detector_day", DAY) == 1
        wait_until(lambda: sum(launcher.idle.values()) == 1, timeout=60.0, what="an idle pool member")
        last = frames.seq
        wait_until(lambda: frames.seq > last, what="a new frame")  # the member holds it (or it is on its way)
        asked_after = frames.seq
        info = DeployerClient(test_session, ROBOT).start("onboard", "detector_day", DAY, instance="held2")
        assert info.via == "pool"
        _, first = markers.wait_for(lambda d: d["instance"] == "held2")
        assert first["seq"] <= asked_after and first["ids"], (first["seq"], asked_after)
        assert first["dropped"] == 0  # frames replacing each other while it waited are not drops
    finally:
        markers.close()
        frames.close()
        host.close()


def test_the_deployer_keeps_an_idle_detector_for_what_may_run_on_its_host_before_any_start(
        knowledge, endpoint, test_session):
    """Issue 32 item 1: with a pool, a host's deployer has its launcher keep an idle detector for the
    detector deployments the graph lets run on the host as soon as the launcher is ready, before
    anything was started there; the first start of any of them (a failover's) takes it and asks the
    graph nothing, neither the configuration nor the reflex table."""
    # No reading of the graph again during the test (it would ask for the configurations' memory).
    by_deployer: list[str] = []
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, warm_refresh_s=600.0, asks=by_deployer)
    asked: list[str] = []
    answer_named = knowledge.answer_named
    events = Collector(test_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    try:
        wait_for_deployers(test_session, ["onboard"])
        client = DeployerClient(test_session, ROBOT)
        idle = wait_until(lambda: client.launcher("onboard").idle_members, timeout=60.0,
                          what="an idle detector kept with nothing started")
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and len(idle) == 1  # one kind: every detector deployment of the models
        under = [p.pid for p in psutil.Process(launcher.pid).children(recursive=True)]
        assert set(idle) <= set(under), (idle, under)  # the deployer names the launcher's own members
        assert host.deployer.processes() == []

        def counting(name, *args, **kwargs):  # the real service's answer
            asked.append(name)
            return answer_named(name, *args, **kwargs)

        since = max(0, len(by_deployer) - 1)
        knowledge.answer_named = counting
        # Not the deployment the member counts as (the least demanding, day's), but one of its kind.
        info = client.start("onboard", "detector_dusk", "marker_detection_dusk", instance="first")
        assert info.via == "pool" and info.pid in idle
        events.wait_for(lambda e: e["instance"] == "first" and e["event"] == "started")
        output = "\n".join(client.status("onboard", "first").output or [])
        assert ("configuration marker_detection_dusk carried by the start request; "
                "reflex table prepared in the launcher's pool") in output, output
        # Another idle one takes its place; the one taken is no member any more.
        again = wait_until(lambda: client.launcher("onboard").idle_members, timeout=30.0, what="the pool refilled")
        assert info.pid not in again
        assert not others(asked, by_deployer[since:])["detector_config"], (asked, by_deployer[since:])
        client.stop("onboard", "first")
    finally:
        knowledge.answer_named = answer_named
        events.close()
        host.close()


def test_a_taken_pool_member_sets_itself_up_while_it_is_re_parented_and_says_ready_only_once_adopted(
        knowledge, endpoint, test_session):
    """Issue 32: a pooled start's own setup (its arguments, configuration, detector, Zenoh declarations)
    waited for the member's re-parenting to the agent; now it runs meanwhile, and only its readiness
    waits. The member's intermediate process is held stopped, so the member cannot be re-parented: taken,
    it declares its liveliness token while that process is still its parent, and the start is not ready;
    let go, the member is the agent's child and ready."""
    host = DeployerHost(endpoint, "onboard", launcher=True, pool=1, warm_refresh_s=600.0)
    alive_tokens: list[str] = []
    tokens = test_session.liveliness().declare_subscriber(keys.detector_alive(ROBOT, "*"),
                                                          lambda s: alive_tokens.append(str(s.key_expr)))
    camera = test_session.declare_publisher(keys.camera_frame(ROBOT, "cam0"))
    outcome: dict[str, object] = {}
    starter: threading.Thread | None = None
    middle: int | None = None
    try:
        launcher = host.deployer.supervisor.launcher
        assert launcher is not None and launcher.wait_ready(60.0)
        launcher.reply_timeout = 30.0  # the launcher answers only once the stopped process is let go
        assert host.deployer.warm("detector_day", DAY) == 1
        (member,) = wait_until(lambda: launcher.idle_pids(), timeout=60.0, what="an idle pool member")
        # Idle: its camera subscription is the last thing it declares before it waits for a start.
        wait_until(lambda: camera.matching_status.matching, timeout=60.0, what="the idle member's camera subscription")
        (middle,) = set(launcher.yielding_pids()) - {member}
        assert psutil.Process(member).ppid() == middle
        os.kill(middle, signal.SIGSTOP)

        def start() -> None:
            try:
                outcome["info"] = DeployerClient(test_session, ROBOT, timeout=3.0, start_timeout=30.0).start(
                    "onboard", "detector_day", DAY, instance="overlap1")
            except Exception as exc:  # noqa: BLE001 - reported by the assertion below
                outcome["error"] = exc

        starter = threading.Thread(target=start, name="test-start")
        starter.start()
        token = keys.detector_alive(ROBOT, "overlap1")
        wait_until(lambda: token in alive_tokens, timeout=8.0,
                   what="the taken member's liveliness token while its intermediate process is stopped")
        assert psutil.Process(member).ppid() == middle  # set up before its re-parenting
        assert host.deployer.status("overlap1").state == "starting"  # ... but not ready before it
    finally:
        if middle is not None:
            try:
                os.kill(middle, signal.SIGCONT)
            except ProcessLookupError:
                pass
        if starter is not None:
            starter.join(timeout=30.0)
        tokens.undeclare()
        camera.undeclare()
    try:
        info = outcome.get("info")
        assert info is not None, outcome.get("error")
        assert info.via == "pool" and info.pid == member and info.state in ("ready", "running")
        assert psutil.Process(member).ppid() == os.getpid()  # the agent's child, as a forked detector
        assert not alive(middle)
        stopped = host.deployer.stop("overlap1")
        assert stopped.state == "stopped" and stopped.returncode == 0
    finally:
        host.close()


class HeldTable:
    """The knowledge service's answers, but the reflex table of ``deployment`` held until :meth:`release`
    (a service worker waits; the service has another): what a detector's start would wait for."""

    def __init__(self, knowledge, deployment: str) -> None:
        self.knowledge, self.deployment = knowledge, deployment
        self.answer_named = knowledge.answer_named
        self.asked = threading.Event()  # a question for the held table arrived
        self.released = threading.Event()
        knowledge.answer_named = self._answer

    def _answer(self, name, payload, *args, **kwargs):
        if name == "reflex_table" and self.deployment.encode() in (payload or b""):
            self.asked.set()
            self.released.wait(30.0)
        return self.answer_named(name, payload, *args, **kwargs)

    def release(self) -> None:
        self.released.set()

    def close(self) -> None:
        self.released.set()
        self.knowledge.answer_named = self.answer_named


def output_of(client: DeployerClient, instance: str) -> str:
    return "\n".join(client.status("onboard", instance).output or [])


@contextmanager
def forked_with_its_table_held(hosts, client_session, knowledge, instance):
    """A detector_day started through the launcher while the service holds its reflex table (HeldTable),
    30 fps of a marker on its camera; yields the client, the start's reply, the detections and the hold."""
    launcher_of(hosts)
    frames = FrameSource(client_session, fps=30.0, jpeg=marker_jpeg(), size=(320, 240))
    markers = Collector(client_session, keys.detector_markers(ROBOT, "*"), "detections")
    held = HeldTable(knowledge, "detector_day")
    try:
        client = DeployerClient(client_session, ROBOT)
        info = client.start("onboard", "detector_day", DAY, instance=instance)
        assert info.via == "launcher"
        yield client, info, markers, held
    finally:
        held.close()
        markers.close()
        frames.close()


def test_a_forked_detector_says_ready_before_its_reflex_table_which_arms_its_candidates_after(
        hosts, client_session, knowledge):
    """Issue 32: a launcher-forked detector fetched its reflex table and built every candidate's detector
    before it said ready (35 of its 63 ms: the first question on a new session). Now ready means it
    detects with the configuration it was given; the table follows. Held at the service until the start
    is ready, the table still arms the candidates: a change to one then asks the graph nothing more.
    (Before, the start waited for the held table until its question timed out, and it ran without one.)"""
    with forked_with_its_table_held(hosts, client_session, knowledge, "early1") as (client, info, markers, held):
        assert info.state in ("ready", "running")
        assert not held.released.is_set()
        held.release()
        markers.wait_for(lambda d: d["instance"] == "early1" and d["ids"] and d["config"] == DAY)
        line = wait_until(lambda: [x for x in output_of(client, "early1").splitlines() if "armed after ready" in x],
                          what="the reflex table armed after ready")
        assert "reflex table of detector_day armed after ready: 3 candidate configurations" in line[0], line
        assert "no reflex table" not in output_of(client, "early1")
        asked: list[str] = []
        answer_named = knowledge.answer_named

        def counting(name, *args, **kwargs):
            asked.append(name)
            return answer_named(name, *args, **kwargs)

        knowledge.answer_named = counting
        report = reconfigure(client_session, ROBOT, "onboard", "early1", "marker_detection_dark")
        knowledge.answer_named = answer_named
        assert report.config == "marker_detection_dark" and report.first_seq is not None, output_of(client, "early1")
        assert set(not_roll_calls(asked)) <= {"reflex_table"}, asked  # armed: only the new deployment's table
        client.stop("onboard", "early1")


def test_a_change_asked_before_the_reflex_table_arrives_is_built_on_demand_and_the_late_table_dropped(
        hosts, client_session, knowledge):
    """A change asked of a forked detector right after ready, while its reflex table is still on its way:
    the detector builds the new configuration on demand (asking the graph, as before any table), swaps
    between two frames and keeps detecting; the table of the deployment it left, arriving late, is not
    armed over the new deployment's one."""
    with forked_with_its_table_held(hosts, client_session, knowledge, "early2") as (client, info, markers, held):
        assert held.asked.wait(10.0), "the detector did not ask for its reflex table"
        report = reconfigure(client_session, ROBOT, "onboard", "early2", "marker_detection_dark")
        assert (report.previous, report.config, report.deployment) == (DAY, "marker_detection_dark", "detector_dark")
        assert not held.released.is_set()  # the change did not wait for the table
        _, first = markers.wait_for(lambda d: d["instance"] == "early2" and d["seq"] == report.first_seq)
        assert first["config"] == "marker_detection_dark"
        held.release()
        wait_until(lambda: "reflex table of detector_day dropped" in output_of(client, "early2"),
                   what="the late reflex table dropped")
        last = max(d["seq"] for _, d in markers.items)
        markers.wait_for(lambda d: d["instance"] == "early2" and d["seq"] > last and d["ids"]
                         and d["config"] == "marker_detection_dark")
        seen = [d for _, d in list(markers.items) if d["instance"] == "early2" and d["seq"] >= report.first_seq]
        assert {d["config"] for d in seen} == {"marker_detection_dark"}
        assert "armed after ready" not in output_of(client, "early2")
        assert client.status("onboard", "early2").deployment == "detector_dark"
        client.stop("onboard", "early2")


def test_the_launcher_has_the_detector_build_its_parser_and_read_a_carried_configuration_before_it_forks():
    """What every forked start did first (its argument parser built: 1.8 ms; a carried configuration read,
    msgspec's checks built on first use: 4.1 ms) is done once in the launcher, before any fork."""
    import threading as _threading

    from kgadapt.deploy.launcher import PRELOAD, RUNNABLE, preload
    from kgadapt.onboard.perception import detector

    detector._PARSER = None
    before = _threading.active_count()
    preload(PRELOAD, RUNNABLE)
    assert detector._PARSER is not None  # a forked start parses with it (main)
    assert _threading.active_count() == before  # the launcher forks single-threaded
    args = detector._PARSER.parse_args(["--host", "h", "--instance", "i", "--config", "c"])
    assert (args.host, args.instance, args.config) == ("h", "i", "c")
