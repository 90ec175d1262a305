"""A Bolt server that announces itself as Memgraph or Neo4j, for the dialect tests (no such server runs here).

It speaks Bolt 5.0 over TCP as the real servers do (handshake, chunked
PackStream messages, HELLO/RUN/PULL/DISCARD/BEGIN/COMMIT/ROLLBACK/RESET/GOODBYE,
FAILURE then IGNORED until RESET) and answers the statements a store sends
while it connects and creates its indexes the way the announced server does:

- parameters are values, never pasted into the text (``RETURN $p AS p`` echoes ``p``);
- Memgraph (up to 3.9) accepts ``CREATE INDEX ON :L(p)`` and lists indexes with
  ``SHOW INDEX INFO``; it refuses Neo4j's ``CREATE INDEX IF NOT EXISTS FOR ...``
  with a syntax error, as Memgraph 3.9 does;
- Neo4j 5 accepts ``CREATE INDEX IF NOT EXISTS FOR (n:L) ON (n.p)`` and lists with
  ``SHOW INDEXES YIELD labelsOrTypes AS label, properties ...``; it refuses the
  ``ON :L(p)`` form, which it dropped in 5.0.

Anything else is refused with a FAILURE naming the statement.
"""

from __future__ import annotations

import re
import socket
import struct
import threading
from typing import Any

MEMGRAPH_AGENT = "Neo4j/v5.11.0 compatible graph database server - Memgraph"
NEO4J_AGENT = "Neo4j/5.26.0"

_MAGIC = b"\x60\x60\xb0\x17"


class _Struct:
    def __init__(self, tag: int, fields: list[Any]) -> None:
        self.tag, self.fields = tag, fields


def pack(value: Any) -> bytes:
    if value is None:
        return b"\xc0"
    if value is True:
        return b"\xc3"
    if value is False:
        return b"\xc2"
    if isinstance(value, int):
        if -16 <= value < 128:
            return struct.pack(">b", value)
        return b"\xcb" + struct.pack(">q", value)
    if isinstance(value, float):
        return b"\xc1" + struct.pack(">d", value)
    if isinstance(value, str):
        data = value.encode()
        return _sized(len(data), 0x80, 0xD0) + data
    if isinstance(value, list):
        return _sized(len(value), 0x90, 0xD4) + b"".join(pack(v) for v in value)
    if isinstance(value, dict):
        return _sized(len(value), 0xA0, 0xD8) + b"".join(pack(k) + pack(v) for k, v in value.items())
    if isinstance(value, _Struct):
        return bytes([0xB0 + len(value.fields), value.tag]) + b"".join(pack(f) for f in value.fields)
    raise TypeError(f"cannot pack {type(value).__name__}")


def _sized(n: int, tiny: int, sized: int) -> bytes:
    if n < 16:
        return bytes([tiny + n])
    if n < 256:
        return bytes([sized, n])
    return bytes([sized + 1]) + struct.pack(">H", n)


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.i = data, 0

    def take(self, n: int) -> bytes:
        out = self.data[self.i:self.i + n]
        self.i += n
        return out

    def value(self) -> Any:
        m = self.take(1)[0]
        if m < 0x80:
            return m
        if m >= 0xF0:
            return m - 0x100
        high = m & 0xF0
        if high in (0x80, 0x90, 0xA0, 0xB0):
            return self._sized(high, m & 0x0F)
        if m == 0xC0:
            return None
        if m in (0xC2, 0xC3):
            return m == 0xC3
        if m == 0xC1:
            return struct.unpack(">d", self.take(8))[0]
        ints = {0xC8: ">b", 0xC9: ">h", 0xCA: ">i", 0xCB: ">q"}
        if m in ints:
            fmt = ints[m]
            return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]
        for base, high in ((0xD0, 0x80), (0xD4, 0x90), (0xD8, 0xA0)):
            if base <= m <= base + 2:
                fmt = (">B", ">H", ">I")[m - base]
                return self._sized(high, struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0])
        raise ValueError(f"PackStream marker {m:#x} not handled")

    def _sized(self, kind: int, n: int) -> Any:
        if kind == 0x80:
            return self.take(n).decode()
        if kind == 0x90:
            return [self.value() for _ in range(n)]
        if kind == 0xA0:
            return {self.value(): self.value() for _ in range(n)}
        tag = self.take(1)[0]
        return _Struct(tag, [self.value() for _ in range(n)])


class BoltDouble:
    """``setup()`` listens on a loopback port (``port``), ``shutdown()`` closes; each connection on a thread."""

    def __init__(self, agent: str) -> None:
        self.agent = agent
        self.memgraph = "memgraph" in agent.lower()
        self.indexes: set[tuple[str, str]] = set()
        self.statements: list[str] = []  # every statement run, in order
        self._lock = threading.Lock()
        self._listener: socket.socket | None = None
        self.port = 0

    def setup(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def shutdown(self) -> None:
        if self._listener is not None:
            self._listener.close()

    def _accept(self) -> None:
        assert self._listener is not None
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            try:
                hello = _recv(conn, 20)
                if hello[:4] != _MAGIC or not _offers_5_0(hello[4:]):
                    conn.sendall(b"\x00\x00\x00\x00")
                    return
                conn.sendall(b"\x00\x00\x00\x05")  # Bolt 5.0
                failed = False
                records: list[list[Any]] = []
                while True:
                    message = _read_message(conn)
                    tag = message.tag
                    if tag == 0x02:  # GOODBYE
                        return
                    if tag == 0x0F:  # RESET
                        failed, records = False, []
                        _send(conn, _Struct(0x70, [{}]))
                        continue
                    if failed:
                        _send(conn, _Struct(0x7E, []))
                        continue
                    if tag == 0x01:  # HELLO
                        _send(conn, _Struct(0x70, [{"server": self.agent, "connection_id": "bolt-1", "hints": {}}]))
                    elif tag == 0x10:  # RUN query params extra
                        try:
                            fields, records = self._run(message.fields[0], message.fields[1] or {})
                        except _Refused as exc:
                            failed = True
                            _send(conn, _Struct(0x7F, [{"code": exc.code, "message": str(exc)}]))
                            continue
                        _send(conn, _Struct(0x70, [{"fields": fields, "t_first": 0}]))
                    elif tag in (0x3F, 0x2F):  # PULL, DISCARD
                        for row in records if tag == 0x3F else []:
                            _send(conn, _Struct(0x71, [row]))
                        records = []
                        _send(conn, _Struct(0x70, [{"has_more": False, "t_last": 0, "type": "rw"}]))
                    elif tag in (0x11, 0x12, 0x13):  # BEGIN, COMMIT, ROLLBACK
                        _send(conn, _Struct(0x70, [{}]))
                    else:
                        failed = True
                        _send(conn, _Struct(0x7F, [{"code": "Neo.ClientError.Request.Invalid",
                                                     "message": f"message {tag:#x} not handled"}]))
            except (OSError, ConnectionError, ValueError):
                return

    def _run(self, text: str, params: dict[str, Any]) -> tuple[list[str], list[list[Any]]]:
        with self._lock:
            self.statements.append(text)
        query = " ".join(text.split())
        match = re.fullmatch(r"RETURN (\$?\w+) AS (\w+)", query)
        if match:
            value = match.group(1)
            return [match.group(2)], [[params.get(value[1:]) if value.startswith("$") else int(value)]]
        own = re.fullmatch(r"CREATE INDEX ON :(\w+)\((\w+)\)", query)
        neo = re.fullmatch(r"CREATE INDEX IF NOT EXISTS FOR \(n:(\w+)\) ON \(n\.(\w+)\)", query)
        if own and self.memgraph or neo and not self.memgraph:
            found = own or neo
            assert found is not None
            with self._lock:
                self.indexes.add((found.group(1), found.group(2)))
            return [], []
        if query == "SHOW INDEX INFO" and self.memgraph:
            rows = [["label+property", label, prop, 0] for label, prop in sorted(self.indexes)]
            return ["index type", "label", "property", "count"], rows
        if query.startswith("SHOW INDEXES YIELD labelsOrTypes AS label, properties") and not self.memgraph:
            return ["label", "properties"], [[[label], [prop]] for label, prop in sorted(self.indexes)]
        if self.memgraph:
            raise _Refused("Memgraph.ClientError.MemgraphError.MemgraphError",
                           f"line 1:0 mismatched input at {query[:40]!r}")
        raise _Refused("Neo.ClientError.Statement.SyntaxError", f"Invalid input at {query[:40]!r}")


class _Refused(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _offers_5_0(offers: bytes) -> bool:
    for k in range(0, 16, 4):
        _, spread, minor, major = offers[k:k + 4]
        if major == 5 and minor - spread <= 0 <= minor:
            return True
    return False


def _recv(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        part = conn.recv(n - len(data))
        if not part:
            raise ConnectionError("closed")
        data += part
    return data


def _read_message(conn: socket.socket) -> _Struct:
    data = b""
    while True:
        size = struct.unpack(">H", _recv(conn, 2))[0]
        if size == 0:
            if data:
                break
            continue  # a NOOP chunk
        data += _recv(conn, size)
    message = _Reader(data).value()
    if not isinstance(message, _Struct):
        raise ValueError("not a message")
    return message


def _send(conn: socket.socket, message: _Struct) -> None:
    data = pack(message)
    conn.sendall(struct.pack(">H", len(data)) + data + b"\x00\x00")
