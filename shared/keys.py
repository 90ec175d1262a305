"""Zenoh key expressions, all under one robot namespace ``kgadapt/<robot>/``.

One robot's processes and other robots can share a Zenoh network: every key
starts with the robot's name, so a fleet never crosses wires.

==============================================  ===========================================
key                                             what travels there
==============================================  ===========================================
``kgadapt/<robot>/host/<host>/status``          host status (memory, CPU), put at ~2 Hz
``kgadapt/<robot>/host/<host>/alive``           liveliness token of the host's agent
``kgadapt/<robot>/host/<host>/deployer/<verb>`` deployer queryables: start, stop, list, status
``kgadapt/<robot>/host/<host>/deployer/events`` deployer events (started, ready, exited, ...)
``kgadapt/<robot>/camera/<cam>/frame``          JPEG frames with capture time and truth
``kgadapt/<robot>/camera/<cam>/illumination``   luminance figures per frame
``kgadapt/<robot>/detector/<instance>/markers`` detections of one detector instance
``kgadapt/<robot>/detector/<instance>/alive``   liveliness token of a detector instance
``kgadapt/<robot>/detector/<instance>/reflex``  the detector's own switches of configuration
``kgadapt/<robot>/host/<host>/detector/<i>/..`` ``.../configure``: queryable, reconfigure detector <i> in place;
                                                ``.../activity``: queryable, make it idle or active (a standby)
``kgadapt/<robot>/flight/state``                flight state from the MAVLink bridge
``kgadapt/<robot>/knowledge/query/<name>``      named queries (queryable)
``kgadapt/<robot>/knowledge/own/query/<name>``  the same, for the robot's own software only (queryable)
``kgadapt/<robot>/knowledge/cypher``            read-only Cypher (queryable)
``kgadapt/<robot>/knowledge/write/<verb>``      run-time writes from operators (queryable)
``kgadapt/<robot>/knowledge/write/<host>/<v>``  run-time writes of host <host>'s agent about itself
``kgadapt/<robot>/adaptation/events``           adaptation decisions as they happen
==============================================  ===========================================

Names (robot, host, camera, instance, query) are single key chunks: letters,
digits, ``_`` and ``-`` only, so no name can inject wildcards or extra chunks.
"""

from __future__ import annotations

import re

from kgadapt.shared.errors import ConfigError

# The robot every command and settings object means when none is named: the shipped
# configurations (deploy/zenoh, deploy/systemd) are written for it.
DEFAULT_ROBOT = "quad1"

PREFIX = "kgadapt"
_CHUNK = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is a safe single key chunk, else raise ConfigError."""
    if not isinstance(name, str) or not _CHUNK.fullmatch(name):  # fullmatch: "$" alone lets a final "\n" through
        raise ConfigError(f"bad {what} {name!r}: use 1-64 letters, digits, '_' or '-'")
    return name


def robot_root(robot: str) -> str:
    return f"{PREFIX}/{check_name(robot, 'robot name')}"


def host_status(robot: str, host: str = "*") -> str:
    return f"{robot_root(robot)}/host/{_name_or_star(host, 'host')}/status"


def host_alive(robot: str, host: str = "*") -> str:
    return f"{robot_root(robot)}/host/{_name_or_star(host, 'host')}/alive"


def deployer_verb(robot: str, host: str, verb: str) -> str:
    return f"{robot_root(robot)}/host/{_name_or_star(host, 'host')}/deployer/{check_name(verb, 'verb')}"


def deployer_events(robot: str, host: str = "*") -> str:
    return f"{robot_root(robot)}/host/{_name_or_star(host, 'host')}/deployer/events"


def camera_frame(robot: str, camera: str = "*") -> str:
    return f"{robot_root(robot)}/camera/{_name_or_star(camera, 'camera')}/frame"


def camera_illumination(robot: str, camera: str = "*") -> str:
    return f"{robot_root(robot)}/camera/{_name_or_star(camera, 'camera')}/illumination"


def detector_markers(robot: str, instance: str = "*") -> str:
    return f"{robot_root(robot)}/detector/{_name_or_star(instance, 'instance')}/markers"


def detector_reflex(robot: str, instance: str = "*") -> str:
    """Where a detector says it switched configuration on its own (kgadapt.onboard.perception.reflex)."""
    return f"{robot_root(robot)}/detector/{_name_or_star(instance, 'instance')}/reflex"


def detector_configure(robot: str, host: str, instance: str = "*") -> str:
    """A running detector's in-place reconfiguration queryable. Under its host's key space, so
    only those allowed to command that host's deployer may ask (deploy/zenoh/router.json5)."""
    return f"{robot_root(robot)}/host/{check_name(host, 'host')}/detector/{_name_or_star(instance, 'instance')}/configure"


def detector_activity(robot: str, host: str, instance: str = "*") -> str:
    """A running detector's idle/active switch (a warm standby is idle). Under its host's key space,
    like ``detector_configure``."""
    return f"{robot_root(robot)}/host/{check_name(host, 'host')}/detector/{_name_or_star(instance, 'instance')}/activity"


def detector_alive(robot: str, instance: str = "*") -> str:
    return f"{robot_root(robot)}/detector/{_name_or_star(instance, 'instance')}/alive"


def flight_state(robot: str) -> str:
    return f"{robot_root(robot)}/flight/state"


def knowledge_query(robot: str, name: str = "*") -> str:
    return f"{robot_root(robot)}/knowledge/query/{_name_or_star(name, 'query name')}"


def knowledge_own_query(robot: str, name: str = "*") -> str:
    """Named queries of the robot's own software: served apart from other robots' questions."""
    return f"{robot_root(robot)}/knowledge/own/query/{_name_or_star(name, 'query name')}"


def knowledge_own_stats(robot: str) -> str:
    """The knowledge service's own counters (refused hosts, dropped statuses): for the robot's own tools."""
    return f"{robot_root(robot)}/knowledge/own/stats"


def knowledge_cypher(robot: str) -> str:
    return f"{robot_root(robot)}/knowledge/cypher"


def knowledge_write(robot: str, verb: str = "*") -> str:
    return f"{robot_root(robot)}/knowledge/write/{_name_or_star(verb, 'write verb')}"


def knowledge_host_write(robot: str, host: str = "*", verb: str = "*") -> str:
    """Write verbs of host ``host``'s own software: the service accepts only what that host owns, and the
    shipped ACL lets only that host's certificate ask here (deploy/zenoh/router.json5)."""
    return f"{robot_root(robot)}/knowledge/write/{_name_or_star(host, 'host')}/{_name_or_star(verb, 'write verb')}"


def adaptation_events(robot: str) -> str:
    return f"{robot_root(robot)}/adaptation/events"


def last_chunk(key: str, from_end: int = 1) -> str:
    """The chunk ``from_end`` places from the end of a concrete key (1 = last)."""
    return str(key).split("/")[-from_end]


def _name_or_star(name: str, what: str) -> str:
    return name if name == "*" else check_name(name, what)
