"""The agent skeleton: parts in order, liveliness token only while ready, clean undo on failure."""

from __future__ import annotations

import time

import pytest

from kgadapt.shared import keys
from kgadapt.shared.agent import Agent, AgentSettings
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.zenoh.conftest import wait_for


class Recorder:
    """A part that writes what happens to it, and whether the host's token was visible then."""

    def __init__(self, name: str, log: list, alive, *, fail: bool = False) -> None:
        self.name = name
        self.log = log
        self.alive = alive
        self.fail = fail

    def setup(self, session) -> None:
        self.log.append((self.name, "setup", self.alive()))
        if self.fail:
            raise RuntimeError(f"{self.name} cannot start")

    def shutdown(self) -> None:
        # The token must already be undeclared: it disappears from the observer's view shortly.
        deadline = time.monotonic() + 2
        while self.alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        self.log.append((self.name, "shutdown", self.alive()))


@pytest.fixture
def observed(robot):
    """Agent settings listening on a free port and an observer session that can see its token."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = AgentSettings(robot=robot, host="remote", role="remote", zenoh=ZenohSettings(mode="peer", listen=(endpoint,)))
    observer = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    key = keys.host_alive(robot, "remote")

    def alive() -> bool:
        return bool(list(observer.liveliness().get(key, timeout=0.2)))

    yield settings, alive
    observer.close()


def test_an_agent_is_alive_only_between_its_parts_setup_and_shutdown(observed):
    settings, alive = observed
    log: list = []
    agent = Agent(settings, [Recorder("first", log, alive), Recorder("second", log, alive)])
    agent.setup()
    try:
        wait_for(alive, 5, "the agent's token")
    finally:
        agent.shutdown()
    assert log == [("first", "setup", False), ("second", "setup", False),
                   ("second", "shutdown", False), ("first", "shutdown", False)]
    assert agent.session is None


def test_a_part_that_fails_setup_undoes_the_parts_before_it_and_the_error_is_raised(observed):
    settings, alive = observed
    log: list = []
    agent = Agent(settings, [Recorder("first", log, alive), Recorder("broken", log, alive, fail=True),
                             Recorder("never", log, alive)])
    with pytest.raises(RuntimeError, match="broken cannot start"):
        agent.setup()
    assert [(name, what) for name, what, _ in log] == [("first", "setup"), ("broken", "setup"), ("first", "shutdown")]
    assert agent.session is None


def test_agent_settings_refuse_a_host_name_that_is_not_one_key_chunk():
    with pytest.raises(ConfigError, match="host name"):
        AgentSettings(host="remote/**", role="remote")
