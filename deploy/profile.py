"""Process profiles: what each detector run cost, written into the knowledge graph.

A :class:`ProfileRecorder` listens to the supervisor. For every run it writes

- at once when the run starts: ``process_start`` (run id, instance,
  deployment, config, host, PID, start time);
- while it runs: ``process_sample`` with a few summary figures of resident
  memory (MiB: last, mean, max) and CPU (mean percent of one core over the
  run: CPU time over wall time), sampled with psutil every
  ``sample_interval`` seconds, the first right after start;
- when it took another configuration in place: ``process_reconfigured``
  (the profile then RAN_CONFIG the new configuration);
- when it exits: ``process_end`` (end time, exit status).

Writes go through a callable ``write(verb, params)`` -- in an agent that is
``KnowledgeClient.write`` (the knowledge service's write verbs from
``knowledge/runtime.py``). They run on a writer thread of their own, so a slow
or absent knowledge service never holds up supervision; a failed write is
logged and dropped. Samples not yet written are replaced by newer ones.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import psutil

from kgadapt.deploy.supervisor import ProcessEvent
from kgadapt.shared.errors import KgadaptError
from kgadapt.shared.states import ProcessEventKind

log = logging.getLogger(__name__)

Writer = Callable[[str, Mapping[str, Any]], Any]
MIB = 1024 * 1024


@dataclass(frozen=True, kw_only=True)
class ProfileSettings:
    sample_interval: float = 1.0
    max_pending: int = 1000  # writes waiting for the knowledge service; oldest samples go first
    flush_timeout: float = 3.0  # on shutdown, time left to write what is pending


@dataclass(frozen=True, kw_only=True)
class ResourceSummary:
    """Summary figures of one run so far."""

    samples: int
    rss_mb_last: float
    rss_mb_mean: float
    rss_mb_max: float
    cpu_percent_last: float | None  # percent of one core since the previous sample (None at first)
    cpu_percent_mean: float  # percent of one core over the run so far (CPU time / wall time)


class _Tracked:
    def __init__(self, run_id: str, pid: int) -> None:
        self.run_id = run_id
        self.pid = pid
        self.process: psutil.Process | None = None
        self.tried = False  # first sample attempted (it also primes the CPU counter)
        self.samples = 0
        self.rss_last = 0.0
        self.rss_sum = 0.0
        self.rss_max = 0.0
        self.cpu_last: float | None = None
        self.cpu_mean = 0.0

    def summary(self) -> ResourceSummary:
        return ResourceSummary(
            samples=self.samples,
            rss_mb_last=self.rss_last,
            rss_mb_mean=self.rss_sum / self.samples if self.samples else 0.0,
            rss_mb_max=self.rss_max,
            cpu_percent_last=self.cpu_last,
            cpu_percent_mean=self.cpu_mean,
        )


class ProfileRecorder:
    """Samples the supervisor's processes and writes their profiles. ``setup()`` before use."""

    def __init__(self, *, host: str, write: Writer, settings: ProfileSettings | None = None) -> None:
        self.host = host
        self.settings = settings or ProfileSettings()
        self._write = write
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)  # sampler: new run or shutdown
        self._pending_cv = threading.Condition(threading.Lock())  # writer queue
        self._tracked: dict[str, _Tracked] = {}
        self._finished: collections.OrderedDict[str, ResourceSummary] = collections.OrderedDict()
        self._pending: collections.deque[list[Any]] = collections.deque()  # [verb, params, run_id]
        self._pending_sample: dict[str, list[Any]] = {}
        self._busy = False
        self._closing = False
        self._threads: list[threading.Thread] = []
        self.write_failures = 0

    def setup(self) -> None:
        """Start the sampler and writer threads."""
        self._closing = False
        self._threads = [
            threading.Thread(target=self._sample_loop, name="profile-sampler", daemon=True),
            threading.Thread(target=self._write_loop, name="profile-writer", daemon=True),
        ]
        for t in self._threads:
            t.start()

    def shutdown(self) -> None:
        """Stop sampling; give pending writes up to ``flush_timeout`` seconds, then stop."""
        with self._lock:
            self._closing = True
            self._wake.notify_all()
        deadline = time.monotonic() + self.settings.flush_timeout
        with self._pending_cv:
            while (self._pending or self._busy) and time.monotonic() < deadline:
                self._pending_cv.wait(0.05)
            if self._pending:
                log.warning("dropping %d unwritten profile records at shutdown", len(self._pending))
                self._pending.clear()
            self._pending_cv.notify_all()
        for t in self._threads:
            t.join(timeout=max(0.1, deadline - time.monotonic()))
        self._threads = []

    def summary(self, run_id: str) -> ResourceSummary | None:
        """Figures of a run being sampled or recently ended."""
        with self._lock:
            tracked = self._tracked.get(run_id)
            if tracked is not None:
                return tracked.summary()
            return self._finished.get(run_id)

    # -- supervisor listener --------------------------------------------------------

    def on_event(self, event: ProcessEvent) -> None:
        """Supervisor listener: start and end records, and which runs to sample."""
        if event.event == ProcessEventKind.STARTED and event.pid is not None:
            self._enqueue("process_start", {
                "run_id": event.run_id, "instance": event.instance, "deployment": event.deployment,
                "config": event.config, "host": self.host, "pid": event.pid, "start_time": event.time,
            }, event.run_id)
            with self._lock:
                self._tracked[event.run_id] = _Tracked(event.run_id, event.pid)
                self._wake.notify_all()  # first sample right away
        elif event.event == ProcessEventKind.RECONFIGURED:
            self._enqueue("process_reconfigured", {
                "run_id": event.run_id, "config": event.config, "deployment": event.deployment, "time": event.time,
            }, event.run_id)
        elif event.event == ProcessEventKind.EXITED:
            with self._lock:
                tracked = self._tracked.pop(event.run_id, None)
                if tracked is not None:
                    self._finished[event.run_id] = tracked.summary()
                    while len(self._finished) > 100:
                        self._finished.popitem(last=False)
            self._enqueue("process_end", {
                "run_id": event.run_id, "end_time": event.time, "exit_status": event.returncode,
            }, event.run_id)

    # -- sampling -----------------------------------------------------------------

    def _sample_loop(self) -> None:
        interval = self.settings.sample_interval
        while True:
            with self._lock:
                if self._closing:
                    return
                due = list(self._tracked.values())
            for tracked in due:
                self._sample(tracked)
            with self._lock:
                if self._closing:
                    return
                # Sleep a full interval unless a new run needs its first sample.
                deadline = time.monotonic() + interval
                while not self._closing and all(t.tried for t in self._tracked.values()):
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._wake.wait(left)

    def _sample(self, tracked: _Tracked) -> None:
        first = not tracked.tried
        tracked.tried = True
        try:
            if tracked.process is None:
                # psutil remembers the create time, so a reused PID is never mistaken for this run.
                tracked.process = psutil.Process(tracked.pid)
            process = tracked.process
            with process.oneshot():
                rss = process.memory_info().rss / MIB
                # Since the previous call; the first call only primes the counter.
                cpu_last = process.cpu_percent(None)
                # The mean over the whole run, exact whatever the sampling rate.
                times = process.cpu_times()
                alive = max(1e-3, time.time() - process.create_time())
                cpu_mean = 100.0 * (times.user + times.system) / alive
        except (psutil.NoSuchProcess, psutil.ZombieProcess, psutil.AccessDenied) as exc:
            log.debug("cannot sample run %s (pid %s): %s", tracked.run_id, tracked.pid, exc)
            return
        with self._lock:
            if self._tracked.get(tracked.run_id) is not tracked:
                return  # exited meanwhile; its end record is queued already
            tracked.samples += 1
            tracked.rss_last = rss
            tracked.rss_sum += rss
            tracked.rss_max = max(tracked.rss_max, rss)
            tracked.cpu_mean = cpu_mean
            if not first:
                tracked.cpu_last = cpu_last
            summary = tracked.summary()
        self._enqueue("process_sample", {
            "run_id": tracked.run_id,
            "rss_mb_last": round(summary.rss_mb_last, 3),
            "rss_mb_mean": round(summary.rss_mb_mean, 3),
            "rss_mb_max": round(summary.rss_mb_max, 3),
            "cpu_percent_mean": round(summary.cpu_percent_mean, 2),
        }, tracked.run_id)

    # -- writing ------------------------------------------------------------------

    def _enqueue(self, verb: str, params: dict[str, Any], run_id: str) -> None:
        with self._pending_cv:
            if self._closing and not self._threads:
                return
            if verb == "process_sample":
                waiting = self._pending_sample.get(run_id)
                if waiting is not None:
                    waiting[1] = params  # newer figures replace unwritten ones, keeping their place
                    return
            item = [verb, params, run_id]
            self._pending.append(item)
            if verb == "process_sample":
                self._pending_sample[run_id] = item
            while len(self._pending) > self.settings.max_pending:
                dropped = self._pending.popleft()
                if dropped[0] == "process_sample":
                    self._pending_sample.pop(dropped[2], None)
                log.warning("profile queue full; dropped a %s record of %s", dropped[0], dropped[2])
            self._pending_cv.notify_all()

    def _write_loop(self) -> None:
        while True:
            with self._pending_cv:
                while not self._pending:
                    if self._closing:
                        return
                    self._pending_cv.wait(0.2)
                item = self._pending.popleft()
                if item[0] == "process_sample" and self._pending_sample.get(item[2]) is item:
                    del self._pending_sample[item[2]]
                self._busy = True
            verb, params, run_id = item
            try:
                self._write(verb, params)
            except KgadaptError as exc:
                self.write_failures += 1
                log.warning("profile %s of run %s not written: %s", verb, run_id, exc)
            except Exception:  # a bug in the writer must not end profiling
                self.write_failures += 1
                log.exception("profile %s of run %s not written", verb, run_id)
            finally:
                with self._pending_cv:
                    self._busy = False
                    self._pending_cv.notify_all()
