"""A bounded queue that serves its askers in turn, each with a bound of its own.

A FIFO shared by every asker lets one that asks without pause fill it, and
everyone behind waits for all of its questions. Here each asker (named by
``asker_of(item)``) has its own line of at most ``per_asker`` items, the
lines together at most ``maxsize``, and ``get`` takes one item from each
line in turn: a flooding asker fills only its own line and gets one turn in
as many as there are askers waiting.

It offers what :class:`kgadapt.shared.rpc.Server` needs of a queue:
``put_nowait`` (``queue.Full`` when the asker's line or the whole is full),
``put`` (with a timeout, for control items, which bypass the per-asker bound),
``get``, ``get_nowait`` and ``qsize``.
"""

from __future__ import annotations

import collections
import queue
import threading
import time
from typing import Any, Callable, Deque

from kgadapt.shared.errors import ConfigError


class FairQueue:
    """Round-robin over askers; at most ``per_asker`` items of one asker, ``maxsize`` in all."""

    def __init__(self, *, maxsize: int, per_asker: int, asker_of: Callable[[Any], str]) -> None:
        if maxsize < 1 or per_asker < 1:
            raise ConfigError(f"fair queue: maxsize {maxsize!r} and per_asker {per_asker!r} must be at least 1")
        self.maxsize = maxsize
        self.per_asker = per_asker
        self.asker_of = asker_of
        self._lines: collections.OrderedDict[str, Deque[Any]] = collections.OrderedDict()
        self._size = 0
        self._changed = threading.Condition()

    def qsize(self) -> int:
        with self._changed:
            return self._size

    def put_nowait(self, item: Any) -> None:
        asker = self.asker_of(item)
        with self._changed:
            line = self._lines.get(asker)
            if self._size >= self.maxsize or (line is not None and len(line) >= self.per_asker):
                raise queue.Full
            self._append(asker, item)

    def put(self, item: Any, timeout: float | None = None) -> None:
        """Queue ``item`` (a control item: only the whole's bound applies), waiting for room up to ``timeout``."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._size < self.maxsize, timeout=timeout):
                raise queue.Full
            self._append("", item)

    def get(self, timeout: float | None = None) -> Any:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._changed:
            while not self._size:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise queue.Empty
                self._changed.wait(remaining)
            return self._take()

    def get_nowait(self) -> Any:
        with self._changed:
            if not self._size:
                raise queue.Empty
            return self._take()

    def _append(self, asker: str, item: Any) -> None:
        self._lines.setdefault(asker, collections.deque()).append(item)
        self._size += 1
        self._changed.notify_all()

    def _take(self) -> Any:
        asker, line = next(iter(self._lines.items()))
        item = line.popleft()
        del self._lines[asker]
        if line:  # its next item waits for every other asker's turn
            self._lines[asker] = line
        self._size -= 1
        self._changed.notify_all()
        return item
