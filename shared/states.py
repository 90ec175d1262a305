"""The named states and kinds that cross the wire: a process's state and what
happened to it, why the adaptation manager acted (its trigger), and how it
carried a change out.

Each is a :class:`enum.StrEnum`: a member is the very string sent and stored
(msgpack, JSON and the graph see ``"ready"``, not an enum), and it compares
equal to that string, so a plain ``str`` (``messages.decode``'s map) is tested
against these members directly; ``messages.decode_as`` gives the members, and
refuses a value that is none of them, naming the field. docs/CONTRACTS.md lists the values;
tests/test_states.py checks the two agree.
"""

from __future__ import annotations

from enum import StrEnum


class ProcessState(StrEnum):
    """The state of one supervised instance (``deploy/supervisor.py``), as the deployer reports it."""

    STARTING = "starting"
    READY = "ready"
    RUNNING = "running"
    RESTARTING = "restarting"
    STOPPING = "stopping"
    STOPPED = "stopped"
    EXITED = "exited"
    FAILED = "failed"


class ProcessEventKind(StrEnum):
    """What happened to a supervised instance (``ProcessEvent.event``; ``event`` of a ``deploy_event``)."""

    STARTED = "started"  # every run, with its pid
    READY = "ready"  # its readiness line
    EXITED = "exited"  # every exit, with the return code (negative: a signal)
    RESTARTED = "restarted"  # after the new run's STARTED
    STOPPED = "stopped"  # stopped on request
    FAILED = "failed"  # not ready in time, out of restarts, or could not start
    RECONFIGURED = "reconfigured"  # took another configuration in place


# The instance ran its last: it ended (EXITED, also before a restart) or is over (STOPPED, FAILED).
ENDED_EVENTS = frozenset({ProcessEventKind.EXITED, ProcessEventKind.STOPPED, ProcessEventKind.FAILED})


# Not yet final: the process runs or is about to (again), or is on its way out.
LIVE_STATES = frozenset({ProcessState.STARTING, ProcessState.READY, ProcessState.RUNNING, ProcessState.RESTARTING,
                         ProcessState.STOPPING})
# The instance is done; only a new start runs it again.
FINAL_STATES = frozenset({ProcessState.STOPPED, ProcessState.EXITED, ProcessState.FAILED})
# Up and serving: readiness seen (or a program without a readiness line running).
SERVING_STATES = frozenset({ProcessState.READY, ProcessState.RUNNING})
# Live and meant to stay: every live state but STOPPING (a process being stopped is no one's detector).
KEPT_STATES = LIVE_STATES - {ProcessState.STOPPING}


class TriggerKind(StrEnum):
    """Why the adaptation manager reconsiders the placement (``Trigger.kind``; ``trigger_kind`` on the wire)."""

    STARTUP = "startup"  # nothing runs yet
    BAND_CHANGED = "band_changed"  # the light moved to another band (past hysteresis and dwell)
    MEMORY_SHORT = "memory_short"  # the running (or standby) detector's host cannot hold it any more
    HOST_LOST = "host_lost"  # a host's liveliness token went away
    HOST_BACK = "host_back"  # ... and came back
    RATE_COLLAPSED = "rate_collapsed"  # the running detector finds far fewer markers than calibration promised
    DETECTOR_GONE = "detector_gone"  # its deployer says our detector no longer runs
    STANDBY = "standby"  # time to start a warm standby
    REFLEX = "reflex"  # the running detector switched on its own evidence (or says its band needs another process)


# Acted on even during final descent: the detector is gone or about to be.
URGENT_TRIGGERS = frozenset({TriggerKind.STARTUP, TriggerKind.HOST_LOST})


class Change(StrEnum):
    """How a decision carried a change out (``change`` in a decision's inputs and event).

    The planner chooses between RECONFIGURE and MIGRATE; the manager adds the warm standby's.
    """

    RECONFIGURE = "reconfigure"  # the running detector took the configuration in place
    MIGRATE = "migrate"  # a new process, make-before-break
    STANDBY = "standby"  # switched to the idle warm standby
    STANDBY_START = "standby_start"  # a warm standby started (idle)
    STANDBY_STOPPED = "standby_stopped"  # the warm standby stopped to free memory
    REFLEX = "reflex"  # the running detector took the configuration in place on its own (its reflex)


class ReflexEvidence(StrEnum):
    """What made a detector switch on its own (``evidence`` of a ``reflex`` message; kgadapt.onboard.perception.reflex)."""

    LIGHT = "light"  # this frame's light is past the band's edge by more than its margin
    COLLAPSE = "collapse"  # no marker for a few frames right after markers were seen
    HEDGE = "hedge"  # the configuration run beside it found the markers where it did not
    REVERT = "revert"  # after a switch, the previous configuration found them and the new one did not
