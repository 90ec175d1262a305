"""Fixtures of the security tests: certificates made by ``kgadapt certs``, the shipped Zenoh configurations.

The shipped configurations (deploy/zenoh/*.json5) reference certificates
under ``/etc/kgadapt/tls/``; :func:`shipped_config` points them at a test
directory instead (a text substitution, so the file names must be exactly the
ones ``kgadapt certs`` writes) and changes only what a test on loopback needs:
endpoints and, for sessions that must fail fast, the connect timeout.

:class:`Network` is the robot as deployed (the service on the shipped router
configuration, the onboard agent, its detectors with their own certificate);
the ``network`` fixture starts one per test module and ``session_as(cn)``
opens a session with ``cn``'s certificate.
"""

from __future__ import annotations

import itertools
import json
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from kgadapt.shared.readiness import READY_TOKEN
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import REPO, free_port
from tests.support import Child as _Child  # noqa: F401
from tests.support import wait_for  # noqa: F401 (the tests import wait_for from here)

ZENOH_DIR = REPO / "deploy" / "zenoh"
SHIPPED_TLS_DIR = "/etc/kgadapt/tls"
ROBOT = "quad1"  # the robot the shipped configurations are written for
OTHER_ROBOT = "quad2"  # listed as one of the "other-robots" in router.json5
FAST_OPEN = {"scouting/delay": 0}
_written = itertools.count()


def kgadapt(*args: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """Run ``kgadapt ARGS`` from this checkout; with ``check`` fail showing its stderr."""
    result = subprocess.run([sys.executable, "-m", "kgadapt", *args], capture_output=True, text=True,
                            timeout=timeout, cwd=REPO)
    if check and result.returncode != 0:
        raise AssertionError(f"kgadapt {' '.join(args)} exited {result.returncode}: {result.stderr.strip()}")
    return result


def shipped_config(name: str, tls_dir: Path, out_dir: Path, **changes: Any) -> Path:
    """The shipped configuration ``name`` with its TLS files in ``tls_dir`` and ``changes`` (key/path -> value)."""
    text = (ZENOH_DIR / name).read_text().replace(SHIPPED_TLS_DIR, str(tls_dir))
    out_dir.mkdir(parents=True, exist_ok=True)
    n = next(_written)
    source = out_dir / f"{n}-{name}"
    source.write_text(text)
    config = zenoh.Config.from_file(str(source))
    for key, value in changes.items():
        config.insert_json5(key, json.dumps(value))
    path = out_dir / f"{n}-{Path(name).stem}.json"
    path.write_text(str(config))
    return path



@dataclass(frozen=True)
class Pki:
    """Certificates of one test fleet, all made by ``kgadapt certs``."""

    tls: Path  # ca.pem and every certificate of our CA: quad1-*, quad2-onboard, mallory-operator
    foreign: Path  # another CA with its own quad1-operator certificate

    def pair(self, cn: str, *, foreign: bool = False) -> tuple[Path, Path]:
        directory = self.foreign if foreign else self.tls
        return directory / f"{cn}.pem", directory / f"{cn}-key.pem"


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    """Our CA with this robot's four identities (router valid for localhost), another robot's onboard
    identity and a stranger's (CN not listed anywhere), plus a foreign CA that also issued a quad1-operator."""
    base = tmp_path_factory.mktemp("pki")
    tls, foreign = base / "tls", base / "foreign"
    kgadapt("certs", str(tls), "--robot", ROBOT, "--router-address", "localhost", "--router-address", "127.0.0.1")
    kgadapt("certs", str(tls), "--robot", OTHER_ROBOT, "--role", "onboard", "--use-ca")
    kgadapt("certs", str(tls), "--robot", "mallory", "--role", "operator", "--use-ca")
    kgadapt("certs", str(foreign), "--robot", ROBOT, "--role", "operator", "--router-address", "localhost")
    return Pki(tls=tls, foreign=foreign)




def Child(name: str, args: list[str], log_dir: Path) -> _Child:
    """A ``kgadapt ARGS`` child (see tests/support.py)."""
    return _Child.kgadapt(name, args, log_dir)


@pytest.fixture
def loopback_robot(tmp_path):
    """Start `kgadapt knowledge serve` on the shipped models and a remote agent, on loopback, no TLS.

    ``loopback_robot(remote_budget="2G")`` returns {robot, endpoint, session(), service, agent, store_dir};
    everything is stopped at teardown.
    """
    from kgadapt.knowledge.loader import load_models
    from kgadapt.knowledge.store import open_store
    from kgadapt.shared.session import ZenohSettings, open_session
    from tests.conftest import free_port

    started: list[_Child] = []
    sessions: list[Any] = []

    def start(remote_budget: str = "2G") -> dict[str, Any]:
        store_dir = tmp_path / "store"
        with open_store(f"embedded:{store_dir}") as store:
            load_models(store, [REPO / "knowledge" / "models"])
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        robot = f"s{free_port()}"
        service = _Child.kgadapt("service", ["knowledge", "serve", "--store", f"embedded:{store_dir}",
                                             "--robot", robot, "--listen", endpoint], tmp_path)
        started.append(service)
        service.wait_ready()
        # A host online with free memory, so that placement has an answer to give.
        agent = _Child.kgadapt("remote", ["remote", "--robot", robot, "--host", "remote", "--memory-budget",
                                          remote_budget, "--connect", endpoint], tmp_path)
        started.append(agent)
        agent.wait_ready()

        def session():
            s = open_session(ZenohSettings(mode="client", connect=(endpoint,)))
            sessions.append(s)
            return s

        return {"robot": robot, "endpoint": endpoint, "session": session, "service": service, "agent": agent,
                "store_dir": store_dir}

    yield start
    for s in sessions:
        s.close()
    for child in reversed(started):
        child.stop()


# Shell metacharacters in a deployment's arguments and environment (in the model file, quoted for
# shlex): the deployer runs the words as they are, without a shell, so none of these may run.
SHELL_WORDS = ["$(touch {m})", "`touch {m}`", "; touch {m}", "&& touch {m}", "| touch {m}", "> {m}"]
PROBE_CODE = ("import json, os, sys, time; print(json.dumps([sys.argv[1:], os.environ.get(\"PROBE\")]), flush=True); "
              f"print(\"{READY_TOKEN}\", flush=True); time.sleep(60)")


def write_probe_model(directory: Path, marker: Path) -> None:
    words = " ".join(shlex.quote(w.format(m=marker)) for w in SHELL_WORDS)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "shell_probe.deploy").write_text(
        "name: shell_probe\n"
        "deploys: marker_detection_day\n"
        "executable: {python}\n"
        f"arguments: -c {shlex.quote(PROBE_CODE)} {words}\n"
        f"environment: PROBE={shlex.quote(f'$(touch {marker})')}\n"
        "executable_on: onboard\n"
    )


class Network:
    """The robot's service and onboard agent behind TLS; ``config(cn)`` is a client configuration as ``cn``."""

    def __init__(self, pki: Any, work: Path) -> None:
        self.pki = pki
        self.work = work
        self.port = free_port()
        self.marker = work / "pwned"
        self.children: list[Child] = []

    def start(self) -> None:
        models = self.work / "models"
        write_probe_model(models, self.marker)
        store = f"embedded:{self.work / 'store'}"
        kgadapt("knowledge", "load", str(REPO / "knowledge" / "models"), str(models), "--store", store, timeout=120)
        router = shipped_config("router.json5", self.pki.tls, self.work, **{
            "listen/endpoints": [f"tls/127.0.0.1:{self.port}"], **FAST_OPEN})
        service = Child("service", ["knowledge", "serve", "--store", store, "--robot", ROBOT,
                                    "--zenoh-config", str(router)], self.work)
        self.children.append(service)
        service.wait_ready()
        onboard = self.config(f"{ROBOT}-onboard")
        # The detectors the deployer starts get their own identity, as the shipped units give them.
        self.detector_config = shipped_config("onboard-detector.json5", self.pki.tls, self.work, **{
            "connect/endpoints": [f"tls/localhost:{self.port}"], **FAST_OPEN})
        agent = Child("onboard", ["onboard", "--robot", ROBOT, "--host", "onboard", "--memory-budget", "700M",
                                  "--zenoh-config", str(onboard), "--mode", "client", "--ready-timeout", "10",
                                  "--detector-zenoh-config", str(self.detector_config)],
                      self.work)
        self.children.append(agent)
        agent.wait_ready()

    def config(self, cn: str, *, foreign: bool = False, **changes: Any) -> Path:
        cert, key = self.pki.pair(cn, foreign=foreign)
        return shipped_config("onboard.json5", self.pki.tls, self.work, **{
            "connect/endpoints": [f"tls/localhost:{self.port}"],
            "transport/link/tls/connect_certificate": str(cert), "transport/link/tls/connect_private_key": str(key),
            **FAST_OPEN, **changes})

    def stop(self) -> None:
        for child in reversed(self.children):
            child.stop()


@pytest.fixture(scope="module")
def network(pki, tmp_path_factory, request):
    """The robot as deployed (:class:`Network`), one per test module."""
    net = Network(pki, tmp_path_factory.mktemp(request.module.__name__.rsplit(".", 1)[-1]))
    try:
        net.start()
        yield net
    finally:
        net.stop()


@pytest.fixture
def session_as(network):
    """``session_as(cn, **config changes)``: a client session with ``cn``'s certificate, closed after the test."""
    opened = []

    def open_as(cn: str, *, foreign: bool = False, **changes: Any):
        session = open_session(ZenohSettings(config_file=str(network.config(cn, foreign=foreign, **changes))))
        opened.append(session)
        return session

    yield open_as
    for session in opened:
        session.close()


def dropped_kind(outcome: object) -> object:
    """What a request came to, for comparing: RequestTimeout for any timeout (NoResponder included: a request the
    router drops reaches no queryable), else the outcome's own type (a reply, a refusal)."""
    from kgadapt.shared.errors import RequestTimeout

    return RequestTimeout if isinstance(outcome, RequestTimeout) else type(outcome)
