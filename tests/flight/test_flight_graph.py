"""The bridge's knowledge: camera intrinsics read from, and flight state written to, the graph.

Through the real knowledge service (embedded FalkorDB) and a real KnowledgeClient over Zenoh.
"""

from __future__ import annotations

import time

import pytest

from kgadapt.knowledge import runtime
from kgadapt.knowledge import schema as S
from kgadapt.knowledge.client import KnowledgeClient
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.onboard.flight.flight import FlightControlWriter, flight_control_params, intrinsics_from_graph
from kgadapt.onboard.flight.mavlink import FlightState
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.session import ZenohSettings, open_session
from tests.conftest import free_port
from tests.flight.conftest import wait_until

ROBOT = "quadgraph"


def proposed_update_flight_control(store, *, name: str, time: float, link: bool, armed: bool | None = None,
                                   mode: str | None = None, landed_state: str | None = None,
                                   battery_pct: float | None = None, battery_v: float | None = None,
                                   autopilot_load_pct: float | None = None,
                                   last_heartbeat: float | None = None) -> None:
    """The write verb ``flight_state`` as proposed to knowledge/runtime.py (used until it exists there)."""
    figures = {"link": link, "armed": armed, "mode": mode, "landed_state": landed_state,
               "battery_pct": battery_pct, "battery_v": battery_v,
               "autopilot_load_pct": autopilot_load_pct, "last_heartbeat": last_heartbeat}
    store.execute(f"MERGE (c:{S.COMPONENT}:{S.FLIGHT_CONTROL} {{name: $name}}) SET c += $figures, c.last_seen = $time",
                  {"name": name, "figures": figures, "time": float(time)})


@pytest.fixture
def knowledge(resp_store, monkeypatch):
    """(store, client): a knowledge service on its own Zenoh peer, a client on another."""
    monkeypatch.setitem(runtime.WRITERS, "flight_state",
                        runtime.WRITERS.get("flight_state", proposed_update_flight_control))
    # FalkorDB refuses read-only queries on a graph that does not exist yet ("empty key").
    resp_store.execute(f"CREATE (:{S.PLATFORM} {{name: 'onboard'}})")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    client_session = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    service = KnowledgeService(resp_store, ServiceSettings(robot=ROBOT, mark_offline_at_start=False, workers=1))
    service.setup(server)
    client = KnowledgeClient(client_session, ROBOT, timeout=3.0)
    try:
        wait_until(lambda: _answers(client), 5, "the knowledge service to answer")
        yield resp_store, client
    finally:
        service.shutdown()
        client_session.close()
        server.close()


def _answers(client: KnowledgeClient) -> bool:
    try:
        client.cypher("RETURN 1 AS one")
        return True
    except Exception:
        return False


def test_intrinsics_are_read_from_the_camera_component_in_the_graph(knowledge):
    store, client = knowledge
    store.execute(f"CREATE (:{S.COMPONENT}:{S.SENSOR_COMPONENT} {{name: $name, fx: $fx, fy: $fy, cx: $cx, cy: $cy}})",
                  {"name": "camera_hd", "fx": 920.0, "fy": 921.5, "cx": 640.0, "cy": 360.0})
    k = intrinsics_from_graph(client, "camera_hd")
    assert (k.fx, k.fy, k.cx, k.cy) == (920.0, 921.5, 640.0, 360.0)


def test_a_camera_without_intrinsics_is_a_config_error_naming_it(knowledge):
    store, client = knowledge
    store.execute(f"CREATE (:{S.COMPONENT} {{name: $name}})", {"name": "flight_control"})
    with pytest.raises(ConfigError, match="'flight_control'"):
        intrinsics_from_graph(client, "flight_control")
    with pytest.raises(ConfigError, match="'no_camera'"):
        intrinsics_from_graph(client, "no_camera")


def test_the_flight_control_writer_stores_the_state_on_the_flight_control_component(knowledge):
    store, client = knowledge
    store.execute(f"CREATE (:{S.COMPONENT}:{S.FLIGHT_CONTROL} {{name: 'flight_control', cpu_load: 120}})")
    writer = FlightControlWriter(client)
    state = FlightState(time=time.time(), link=True, armed=True, mode="LAND", landed_state="LANDING",
                        battery_pct=61.0, battery_v=15.8, onboard_load=33.0, last_heartbeat=time.time())
    writer(state)
    writer(state)  # unchanged and within min_period_s: not written again
    assert (writer.written, writer.failed) == (1, 0)
    rows = store.execute(f"MATCH (c:{S.FLIGHT_CONTROL} {{name: 'flight_control'}}) RETURN c.link AS link, "
                         "c.armed AS armed, c.mode AS mode, c.landed_state AS landed, c.battery_pct AS pct, "
                         "c.autopilot_load_pct AS load, c.cpu_load AS cpu_load, c.last_seen AS seen")
    assert rows[0].pop("seen") == pytest.approx(state.time, abs=1e-3)  # FalkorDB keeps 15 significant digits
    assert rows == [{"link": True, "armed": True, "mode": "LAND", "landed": "LANDING", "pct": 61.0, "load": 33.0,
                     "cpu_load": 120}]


def test_a_failing_graph_write_is_counted_and_logged_not_raised(knowledge, caplog):
    store, client = knowledge
    writer = FlightControlWriter(client, verb="no_such_verb")
    writer(FlightState(time=time.time(), link=False))
    assert (writer.written, writer.failed) == (0, 1)
    assert "no_such_verb" in caplog.text


def test_flight_control_params_send_what_is_unknown_as_none():
    params = flight_control_params(FlightState(time=5.0, link=False, mode="LOITER"))
    assert params == {"name": "flight_control", "time": 5.0, "link": False, "mode": "LOITER", "armed": None,
                      "landed_state": None, "battery_pct": None, "battery_v": None, "autopilot_load_pct": None,
                      "last_heartbeat": None}


def test_a_figure_that_became_unknown_leaves_the_graph(knowledge):
    store, client = knowledge
    writer = FlightControlWriter(client)
    writer(FlightState(time=1.0, link=True, armed=True, mode="LAND", landed_state="LANDING", battery_pct=50.0))
    writer(FlightState(time=2.0, link=True, armed=True, mode="LAND", landed_state=None, battery_pct=50.0))
    assert writer.written == 2
    rows = store.execute(f"MATCH (c:{S.FLIGHT_CONTROL} {{name: 'flight_control'}}) RETURN c.landed_state AS landed, "
                         "c.mode AS mode, c.battery_pct AS pct, c.last_seen AS seen")
    assert rows == [{"landed": None, "mode": "LAND", "pct": 50.0, "seen": 2.0}]


def test_intrinsics_are_asked_again_until_a_late_knowledge_service_answers(resp_store, caplog):
    # The onboard agent's start: the soak saw it exit when the service refused its first read
    # (the store reloading after a kill -9); now it asks again for a bounded time.
    import logging
    import threading

    from kgadapt.shared.errors import RequestTimeout

    resp_store.execute(f"CREATE (:{S.COMPONENT}:{S.SENSOR_COMPONENT} {{name: 'cam', fx: 1.0, fy: 2.0, cx: 3.0, cy: 4.0}})")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = open_session(ZenohSettings(mode="peer", listen=(endpoint,)))
    client_session = open_session(ZenohSettings(mode="peer", connect=(endpoint,)))
    client = KnowledgeClient(client_session, ROBOT, timeout=1.0)
    service = KnowledgeService(resp_store, ServiceSettings(robot=ROBOT, mark_offline_at_start=False, workers=1))
    got: list = []
    try:
        with pytest.raises(RequestTimeout):
            intrinsics_from_graph(client, "cam")  # no service yet, no wait: the error at once
        caplog.set_level(logging.INFO, logger="kgadapt.knowledge.client")
        asking = threading.Thread(target=lambda: got.append(intrinsics_from_graph(client, "cam", wait_s=30.0)))
        asking.start()
        wait_until(lambda: "asking again" in caplog.text, 10, "a first unanswered ask")
        service.setup(server)
        asking.join(30)
        assert got and (got[0].fx, got[0].cy) == (1.0, 4.0), got
    finally:
        service.shutdown()
        client_session.close()
        server.close()
