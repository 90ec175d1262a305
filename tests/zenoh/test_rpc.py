"""shared/rpc.py between two real Zenoh peers: the answer rule, typed errors, workers."""

from __future__ import annotations

import contextlib
import threading
import uuid

import msgpack
import pytest

from kgadapt.knowledge import queries
from kgadapt.knowledge.service import KnowledgeService, ServiceSettings
from kgadapt.shared import messages, rpc
from kgadapt.shared.errors import MessageError, NoResponder, RemoteError, RequestTimeout, TransportError
from tests.support import wait_for


@pytest.fixture
def key() -> str:
    return f"test/rpc/{uuid.uuid4().hex}"


def echo(request: rpc.Request) -> rpc.Reply:
    """Answers a squeeze_request with its reserve_mb doubled; refuses anything else."""
    if request.payload is None:
        raise MessageError("squeeze_request has no payload")
    body = messages.decode(request.payload, "squeeze_request")
    if body["reserve_mb"] < 0:
        raise MessageError(f"squeeze_request field 'reserve_mb' must not be negative, got {body['reserve_mb']}")
    return rpc.Reply(key=request.key, payload=str(body["reserve_mb"] * 2).encode())


def test_a_request_gets_its_reply_decoded(zenoh_pair, key):
    server, client = zenoh_pair
    with rpc.serve(server, key, echo, name="echo"):
        got = rpc.call(client, key, messages.encode("squeeze_request", {"reserve_mb": 21.0}), float,
                       timeout=5, resend_for=5)
    assert got == 42.0


def test_a_malformed_request_gets_an_error_naming_the_field(zenoh_pair, key):
    server, client = zenoh_pair
    with rpc.serve(server, key, echo, name="echo", prefix="echo: ") as srv:
        with pytest.raises(RemoteError, match=r"^echo: .*'reserve_mb'"):
            rpc.call(client, key, messages.encode("squeeze_request", {"reserve_mb": -1.0}), float, timeout=5,
                     resend_for=5)
        with pytest.raises(RemoteError, match="reserve_mb"):  # a required field missing
            rpc.call(client, key, msgpack.packb({"kind": "squeeze_request", "v": 1}), float, timeout=5)
        with pytest.raises(RemoteError, match="no payload"):
            _no_payload(client, key)
        assert srv.stats()["refused"] == 3


def _no_payload(session, key: str) -> None:
    """A get without any payload (rpc.call always sends one)."""
    replies = list(session.get(key, timeout=5))
    assert len(replies) == 1 and replies[0].err is not None
    raise RemoteError(replies[0].err.payload.to_string())


def test_a_handler_exception_becomes_an_error_reply_and_the_server_keeps_serving(zenoh_pair, key):
    server, client = zenoh_pair
    calls = []

    def flaky(request: rpc.Request) -> rpc.Reply:
        calls.append(request.key)
        if len(calls) == 1:
            raise ZeroDivisionError("division by zero")
        return echo(request)

    payload = messages.encode("squeeze_request", {"reserve_mb": 1.5})
    with rpc.serve(server, key, flaky, name="flaky") as srv:
        with pytest.raises(RemoteError, match="internal error .*ZeroDivisionError: division by zero"):
            rpc.call(client, key, payload, float, timeout=5, resend_for=5)
        assert rpc.call(client, key, payload, float, timeout=5) == 3.0
        assert srv.stats() == {"answered": 1, "refused": 0, "failed": 1, "shed": 0}


def test_a_key_nobody_serves_raises_no_responder(zenoh_pair, key):
    _, client = zenoh_pair
    with pytest.raises(NoResponder, match=key):
        rpc.call(client, key, b"x", bytes, timeout=0.5)
    with pytest.raises(RequestTimeout):  # NoResponder is a RequestTimeout: old callers still catch it
        rpc.gather(client, key, b"x", bytes, timeout=0.5, resend_for=0.3)


def test_the_knowledge_client_and_squeeze_keep_no_responder_for_a_robot_nobody_serves(zenoh_pair):
    # CONTRACTS.md: "our clients raise NoResponder (a RequestTimeout)" for a query that reaches no queryable.
    from kgadapt.knowledge.client import KnowledgeClient
    from kgadapt.shared.hostmonitor import squeeze

    _, client = zenoh_pair
    with pytest.raises(NoResponder, match="knowledge service of robot 'nobody'"):
        KnowledgeClient(client, "nobody", timeout=0.3).query("platforms")
    with pytest.raises(NoResponder, match="no host monitor answered"):
        squeeze(client, "nobody", "remote", 0.0, timeout=0.3)


def test_a_name_with_a_trailing_newline_is_no_key_chunk():
    # re's "$" matches before a final newline: "onboard\n" passed and made a key with a line break in a chunk.
    from kgadapt.shared import keys
    from kgadapt.shared.errors import ConfigError

    for bad in ("onboard\n", "onboard\n\n", "\nonboard", "on board"):
        with pytest.raises(ConfigError, match="bad host"):
            keys.check_name(bad, "host")
    assert keys.check_name("onboard-2_x", "host") == "onboard-2_x"


def test_a_query_that_reached_nobody_is_sent_again_soon_then_less_often(zenoh_pair, key, monkeypatch):
    """A session opened a moment ago does not know the queryables yet: its first query reaches nobody.
    It is sent again after 2 ms, not 50 (the first question of a new detector's session waited 50 ms);
    the pauses double up to RESEND_PAUSE, so a key nobody serves is not asked about in a tight loop."""
    _server, client = zenoh_pair
    slept: list[float] = []
    real_sleep = rpc.time.sleep

    def sleep(seconds: float) -> None:
        if threading.current_thread() is threading.main_thread():
            slept.append(seconds)
        real_sleep(seconds)

    monkeypatch.setattr(rpc.time, "sleep", sleep)
    with pytest.raises(NoResponder):
        rpc.call(client, key, b"x", bytes, timeout=2.0, resend_for=1.0)
    assert slept[:5] == [0.002, 0.004, 0.008, 0.016, 0.032], slept
    assert max(slept) == rpc.RESEND_PAUSE and len(slept) <= 25, slept


def test_a_handler_slower_than_the_timeout_raises_request_timeout_not_an_error_reply(zenoh_pair, key):
    server, client = zenoh_pair
    release = threading.Event()

    def stuck(request: rpc.Request) -> rpc.Reply:
        release.wait(10)
        return rpc.Reply(key=request.key, payload=b"late")

    with rpc.serve(server, key, stuck, name="stuck"):
        try:
            with pytest.raises(RequestTimeout) as caught:
                rpc.call(client, key, b"x", bytes, timeout=0.5, resend_for=0.5)
            assert type(caught.value) is RequestTimeout  # the deadline, not a reply with the text "Timeout"
        finally:
            release.set()


def test_a_slow_handler_holds_only_its_worker(zenoh_pair, key):
    server, client = zenoh_pair
    release = threading.Event()
    entered = threading.Event()

    def handler(request: rpc.Request) -> rpc.Reply:
        if request.payload == b"slow":
            entered.set()
            release.wait(10)
        return rpc.Reply(key=request.key, payload=request.payload or b"")

    with rpc.serve(server, key, handler, name="two", workers=2):
        result: list[bytes] = []
        slow = threading.Thread(target=lambda: result.append(rpc.call(client, key, b"slow", bytes, timeout=10,
                                                                      resend_for=5)))
        slow.start()
        try:
            assert entered.wait(5)
            # One worker is held; the other answers, while the slow one is still unanswered.
            assert rpc.call(client, key, b"quick", bytes, timeout=5) == b"quick"
            assert not result
        finally:
            release.set()
            slow.join(10)
        assert result == [b"slow"]


def _held(server, key: str, *, name: str, max_pending: int = 64) -> tuple[rpc.Server, threading.Event]:
    """A one-worker server whose handler waits for the returned event; its first request holds the worker."""
    release = threading.Event()

    def handler(request: rpc.Request) -> rpc.Reply:
        release.wait(10)
        return rpc.Reply(key=request.key, payload=b"done")

    return rpc.serve(server, key, handler, name=name, workers=1, max_pending=max_pending), release


def _asking(client, key: str, payload: bytes, outcomes: list[object]) -> threading.Thread:
    def ask() -> None:
        try:
            outcomes.append(rpc.call(client, key, payload, bytes, timeout=10, resend_for=5))
        except RemoteError as exc:
            outcomes.append(str(exc))

    thread = threading.Thread(target=ask)
    thread.start()
    return thread


def test_requests_beyond_max_pending_are_answered_busy_at_once(zenoh_pair, key):
    server, client = zenoh_pair
    srv, release = _held(server, key, name="tiny", max_pending=1)
    outcomes: list[object] = []
    try:
        first = _asking(client, key, b"1", outcomes)
        wait_for(lambda: srv.stats()["answered"] == 0 and srv.pending() == 0 and srv.busy() == 1, 5, "a held worker")
        second = _asking(client, key, b"2", outcomes)
        wait_for(lambda: srv.pending() == 1, 5, "a queued request")
        with pytest.raises(RemoteError, match="^tiny busy: too many .* requests pending"):
            rpc.call(client, key, b"3", bytes, timeout=10)
        assert srv.stats()["shed"] == 1
        release.set()
        first.join(10)
        second.join(10)
        assert outcomes == [b"done", b"done"]  # the queued one still answered
    finally:
        release.set()
        srv.shutdown()


def test_requests_still_queued_at_shutdown_are_answered_shutting_down(zenoh_pair, key):
    server, client = zenoh_pair
    srv, release = _held(server, key, name="closing")
    outcomes: list[object] = []
    first = _asking(client, key, b"held", outcomes)
    wait_for(lambda: srv.busy() == 1, 5, "a held worker")
    second = _asking(client, key, b"queued", outcomes)
    wait_for(lambda: srv.pending() == 1, 5, "a queued request")
    closer = threading.Thread(target=srv.shutdown)
    closer.start()
    second.join(10)
    assert outcomes == ["closing is shutting down"]  # at once: the held request is still being answered
    release.set()
    closer.join(10)
    first.join(10)
    assert outcomes == ["closing is shutting down", b"done"]


def test_declared_undeclares_quietly_even_after_the_session_closed():
    from kgadapt.shared.session import ZenohSettings, open_session

    session = open_session(ZenohSettings(mode="peer", listen=("tcp/127.0.0.1:0",)))
    with contextlib.ExitStack() as stack:
        rpc.declared(stack, session.declare_publisher("test/rpc/closed"))
        session.close()  # the publisher is gone with it: undeclaring now fails, quietly


def test_the_platforms_query_on_a_graph_never_written_returns_no_rows(resp_store):
    # Why KnowledgeService._mark_all_offline needs no "empty key" branch: the store answers a
    # read of a missing graph with no rows, it does not raise.
    assert queries.run_named(resp_store, "platforms", {}) == []
    KnowledgeService(resp_store, ServiceSettings(lock=False))._mark_all_offline()


def test_asking_on_a_closed_session_is_a_transport_error():
    from kgadapt.shared.session import ZenohSettings, open_session

    session = open_session(ZenohSettings(mode="peer", listen=("tcp/127.0.0.1:0",)))
    session.close()
    with pytest.raises(TransportError, match="test/rpc/closed"):
        rpc.call(session, "test/rpc/closed", b"x", bytes, timeout=0.5)
    with pytest.raises(TransportError, match="cannot declare"):
        rpc.serve(session, "test/rpc/closed", echo, name="closed")
