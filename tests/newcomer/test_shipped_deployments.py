"""Every shipped deployment in knowledge/models starts on every host it names, through the real deployers.

The deployments are read from the models themselves (a new one is tested
without touching this file). The hosts are the README's agents; the flight
bridge gets the README's fake flight controller on its default port.
"""

from __future__ import annotations

import json

import pytest

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.importers import parse_file
from tests.support import REPO


def shipped_deployments() -> list[tuple[str, str, str]]:
    """(deployment, what it deploys, host) for every shipped deployment and host it names."""
    out = []
    for path in sorted((REPO / "knowledge" / "models" / "deployments").iterdir()):
        model = parse_file(path)
        for node in model.nodes:
            if node.label != S.DEPLOYMENT:
                continue
            deploys = [e.target.name for e in model.edges if e.type == S.DEPLOYS and e.source.name == node.name]
            hosts = [e.target.name for e in model.edges if e.type == S.EXECUTABLE_ON and e.source.name == node.name]
            out.extend((node.name, target, host) for target in deploys for host in hosts)
    return out


@pytest.mark.timeout(300)  # several robots' processes on a shared 2-core machine
def test_every_shipped_deployment_starts_on_each_host_it_names(terminal):
    pairs = shipped_deployments()
    assert {d for d, _, _ in pairs} >= {"detector_day", "detector_dusk", "detector_dark", "detector_hd", "flight_control"}
    k = f"{terminal.workdir}/.venv/bin/kgadapt"
    assert terminal.run(f"{k} knowledge load knowledge/models").returncode == 0
    terminal.start(f"{k} knowledge serve")
    terminal.start(f"{k} remote --host remote --memory-budget 4G")
    terminal.start(f"{k} flight fake-fc --url udpout:127.0.0.1:14550 --armed")
    terminal.start(f"{k} onboard --host onboard --memory-budget 700M")
    failures = []
    for deployment, config, host in pairs:
        started = terminal.run(f"{k} deploy start {deployment} {config} --host {host} --ready-timeout 30 --json",
                               timeout=90)
        if started.returncode != 0:
            failures.append(f"{deployment} ({config}) on {host}: {started.stderr.strip()}")
            continue
        info = json.loads(started.stdout)
        if info["state"] not in ("ready", "running"):
            failures.append(f"{deployment} on {host}: {info['state']} {info.get('detail')}")
        stopped = terminal.run(f"{k} deploy stop {info['instance']} --host {host} --json", timeout=60)
        assert stopped.returncode == 0, stopped.stderr
    assert not failures, "shipped deployments that do not start:\n" + "\n".join(failures)
