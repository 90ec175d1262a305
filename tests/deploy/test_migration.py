"""Planned migration between two deployers on this machine, with the echo detector and 30 fps frames."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest

from kgadapt.deploy.client import DeployerClient
from kgadapt.deploy.migration import migrate
from kgadapt.shared import keys
from kgadapt.shared.errors import DeploymentError, ReadinessTimeout, SourceNotStopped
from tests.deploy.conftest import CONFIG, CONFIG_DUSK, ROBOT, Collector, FrameSource
from tests.deploy.test_deployer import REPO, alive


@pytest.fixture
def frames(client_session):
    source = FrameSource(client_session, fps=30.0)
    yield source
    source.close()


def test_the_target_produces_output_before_the_source_stops(hosts, client_session, frames):
    client = DeployerClient(client_session, ROBOT)
    source = client.start("onboard", "echo", CONFIG, instance="det1")
    markers = Collector(client_session, keys.detector_markers(ROBOT, "*"), "detections")
    events = Collector(client_session, keys.deployer_events(ROBOT, "*"), "deploy_event")
    markers.wait_for(lambda d: d["instance"] == "det1")

    report = migrate(client_session, ROBOT, "det1", "remote", new_instance="det2")

    assert (report.source_host, report.target_host, report.deployment, report.config) == ("onboard", "remote", "echo", CONFIG)
    # The source is stopped only after the target was ready and had detected. The target's first detection
    # may reach us before the reply that it is ready (two routes: a loaded run saw 170 ms against 184 ms).
    assert max(report.target_ready_ms, report.first_output_ms) <= report.source_stopped_ms
    first_new, _ = markers.wait_for(lambda d: d["instance"] == "det2" and d["host"] == "remote")
    source_exit, _ = events.wait_for(lambda e: e["instance"] == "det1" and e["event"] == "exited")
    assert first_new < source_exit  # the new detector answered frames while the old one still ran
    assert not alive(source.pid)
    live = {p.instance: p.host for p in client.processes("*") if p.state == "ready"}
    assert live == {"det2": "remote"}
    markers.close()
    events.close()


def test_a_target_that_never_gets_ready_leaves_the_source_running(hosts, client_session, frames):
    client = DeployerClient(client_session, ROBOT)
    source = client.start("onboard", "echo_hangs_on_remote", CONFIG, instance="keeper")
    with pytest.raises(ReadinessTimeout, match="keeper keeps running on onboard"):
        migrate(client_session, ROBOT, "keeper", "remote", new_instance="never", ready_timeout=0.5)
    assert client.status("onboard", "keeper").state == "ready" and alive(source.pid)
    assert client.status("remote", "never").state == "failed"
    # Still at work: it answers frames sent after the failed migration.
    sent = frames.seq
    markers = Collector(client_session, keys.detector_markers(ROBOT, "keeper"), "detections")
    markers.wait_for(lambda d: d["seq"] > sent)
    markers.close()


def test_a_migration_to_the_host_it_already_runs_on_is_refused(hosts, client_session):
    DeployerClient(client_session, ROBOT).start("remote", "echo", CONFIG, instance="stay")
    with pytest.raises(DeploymentError, match="already runs on remote"):
        migrate(client_session, ROBOT, "stay", "remote")


def test_a_change_of_configuration_on_the_same_host_is_made_before_the_old_one_is_broken(hosts, client_session, frames):
    client = DeployerClient(client_session, ROBOT)
    client.start("onboard", "echo", CONFIG, instance="day")
    markers = Collector(client_session, keys.detector_markers(ROBOT, "*"), "detections")
    events = Collector(client_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")
    report = migrate(client_session, ROBOT, "day", "onboard", config=CONFIG_DUSK, new_instance="dusk")
    assert (report.source_host, report.target_host, report.config) == ("onboard", "onboard", CONFIG_DUSK)
    first_dusk, _ = markers.wait_for(lambda d: d["instance"] == "dusk" and d["config"] == CONFIG_DUSK)
    day_exit, _ = events.wait_for(lambda e: e["instance"] == "day" and e["event"] == "exited")
    assert first_dusk < day_exit
    markers.close()
    events.close()


def test_a_migration_to_a_host_the_deployment_cannot_run_on_leaves_the_source_running(hosts, client_session):
    client = DeployerClient(client_session, ROBOT)
    client.start("remote", "echo_remote_only", CONFIG, instance="pinned")
    with pytest.raises(DeploymentError, match="not executable on host onboard.*pinned keeps running on remote"):
        migrate(client_session, ROBOT, "pinned", "onboard")
    assert client.status("remote", "pinned").state == "ready"


def test_the_command_line_starts_lists_migrates_and_stops(hosts, client_session, frames, endpoint):
    def kgadapt(*args: str) -> str:
        done = subprocess.run(
            [sys.executable, "-m", "kgadapt", "deploy", *args, "--robot", ROBOT, "--connect", endpoint],
            cwd=REPO, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        return done.stdout

    started = json.loads(kgadapt("start", "echo", CONFIG, "--host", "onboard", "--instance", "cli1", "--json"))
    assert started["state"] == "ready"
    listed = json.loads(kgadapt("list", "--json"))
    assert [(p["host"], p["instance"]) for p in listed] == [("onboard", "cli1")]
    moved = json.loads(kgadapt("migrate", "cli1", "--to", "remote", "--new-instance", "cli2", "--json"))
    assert moved["source_host"] == "onboard" and moved["new_instance"] == "cli2"
    assert "cli2 on remote: stopped" in kgadapt("stop", "cli2")
    refused = subprocess.run(
        [sys.executable, "-m", "kgadapt", "deploy", "start", "nope", CONFIG, "--host", "onboard", "--robot", ROBOT,
         "--connect", endpoint], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1 and "'nope' is not in the knowledge store" in refused.stderr


def test_a_source_whose_host_stops_answering_is_reported_with_the_target_that_runs(hosts, client_session, frames):
    """The soak's case: a link cut between the target's start and the source's stop."""
    client = DeployerClient(client_session, ROBOT)
    client.start("remote", "echo", CONFIG, instance="cut_off")
    events = Collector(client_session, keys.deployer_events(ROBOT, "onboard"), "deploy_event")

    def cut_remote() -> None:  # the remote deployer stops answering once the target's process starts
        events.wait_for(lambda e: e["instance"] == "moved" and e["event"] == "started", timeout=60)
        hosts["remote"].deployer.shutdown()

    cutter = threading.Thread(target=cut_remote, daemon=True)
    cutter.start()
    with pytest.raises(SourceNotStopped, match="moved runs on onboard, but stopping cut_off on remote failed") as caught:
        migrate(client_session, ROBOT, "cut_off", "onboard", new_instance="moved")
    cutter.join(60)
    report = caught.value.report
    assert (report.new_instance, report.target_host, report.source_stopped_ms) == ("moved", "onboard", None)
    assert client.status("onboard", "moved").state in ("ready", "running")
    events.close()
