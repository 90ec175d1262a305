"""The knowledge graph's schema: labels, relations, keys and indexes.

Names appear in queries, so they say what they mean and relations point the
way they read ("a Deployment is EXECUTABLE_ON a Platform").

Nodes (every node has a ``name`` unique within its primary label; nodes made
from a model file carry ``model_file``, the file they came from, so that a
changed model replaces its old version)::

    Feature           name, description
    IlluminationBand  name, min_level, max_level          (mean luminance 0..255)
    PerceptionGraph   name, description                   (one detector configuration)
    Component         name, memory_demand_mb, cpu_load    (+ SensorComponent | ProcessingComponent | FlightControl)
        Camera (a SensorComponent): width, height, fx, fy, cx, cy, fps
        marker detector (a ProcessingComponent): dictionary, config_json (detector
        parameters and pre-processing as a JSON object)
    Port              name, key ("component/port"), direction ("in"|"out"), data_type
    Deployment        name, executable, arguments (list), environment (list of "K=V"), kind
                      (+ SystemdServiceFile | DeploymentFile)
    Platform          name, memory_total_mb, cpu_cores, cpu_capacity    design time
                      memory_free_mb, cpu_load, online, last_seen        run time (late bound)
    ProcessProfile    name (instance id), pid, host, start_time, end_time, exit_status,
                      rss_mb_last, rss_mb_mean, rss_mb_max, cpu_percent_mean   (run time)
    AdaptationDecision name, time, trigger, inputs_json, query, config, host, duration_ms, outcome
    Site              name, dictionary                    (where the robot lands; a ``*.site`` model)
    Marker            name ("site/id"), marker_id, size_m (printed side, m), dictionary,
                      marker_name, position ([north, east, down] m; both optional)
    FleetRobot        name (a robot), first_seen, last_seen, heard ("self"|"answer"|"announce"),
                      zid, routers (list of Zenoh ids)      (run time: the fleet roster, knowledge/fleet_roster.py)

Relations (direction matters)::

    (PerceptionGraph)-[:REALIZES]->(Feature)
    (PerceptionGraph)-[:CONTAINS]->(Component)
    (PerceptionGraph)-[:SUITED_FOR]->(IlluminationBand)
    (PerceptionGraph)-[:CALIBRATED {condition, source, detection_rate, false_per_frame, false_per_reported,
                                    ms_per_frame, at}]->(IlluminationBand)   source: synthetic | frames:NAME
    (PerceptionGraph)-[:LIVE_RATE {condition, detection_rate, frames, frames_expected, frames_seen, since, at,
                                   run_id, host}]->(IlluminationBand)   (run time: this robot's own detections,
                                   one per configuration x band x condition, updated: knowledge/runtime.py)
    (Component)-[:HAS_PORT]->(Port)
    (Port)-[:CONNECTED_TO]->(Port)                 out port to in port
    (Feature)-[:REQUIRES]->(Feature)
    (Deployment)-[:DEPLOYS]->(PerceptionGraph | Component)
    (Deployment)-[:EXECUTABLE_ON]->(Platform)
    (ProcessProfile)-[:PROFILE_OF]->(Deployment)
    (ProcessProfile)-[:RAN_ON]->(Platform)
    (ProcessProfile)-[:RAN_CONFIG]->(PerceptionGraph)
    (AdaptationDecision)-[:CHOSE]->(PerceptionGraph), (AdaptationDecision)-[:PLACED_ON]->(Platform)
    (Site)-[:HAS_MARKER]->(Marker)

Graphs (:class:`Graph`): a robot's knowledge is the store's own graph, except the fleet roster
(``FleetRobot``), which is written at every roll call: where the backend holds several graphs on one
server it has a graph of its own beside the robot's, ``<graph>.fleet_roster``, reached only through
:meth:`Graph.store`; elsewhere it is in the robot's graph.

Late binding: ``Platform`` run-time properties and every ``ProcessProfile``
figure are unset until known; queries treat a missing figure as unknown.
Units: memory in MiB (``_mb``), CPU load in percent of one core, times in
seconds since the epoch (float).
"""

from __future__ import annotations

import enum

from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import ConfigError

FEATURE = "Feature"
ILLUMINATION_BAND = "IlluminationBand"
PERCEPTION_GRAPH = "PerceptionGraph"
COMPONENT = "Component"
SENSOR_COMPONENT = "SensorComponent"
PROCESSING_COMPONENT = "ProcessingComponent"
FLIGHT_CONTROL = "FlightControl"
CAMERA = "Camera"
PORT = "Port"
DEPLOYMENT = "Deployment"
SYSTEMD_SERVICE_FILE = "SystemdServiceFile"
DEPLOYMENT_FILE = "DeploymentFile"
PLATFORM = "Platform"
PROCESS_PROFILE = "ProcessProfile"
ADAPTATION_DECISION = "AdaptationDecision"
SITE = "Site"
MARKER = "Marker"
FLEET_ROBOT = "FleetRobot"

REALIZES = "REALIZES"
CONTAINS = "CONTAINS"
SUITED_FOR = "SUITED_FOR"
CALIBRATED = "CALIBRATED"
LIVE_RATE = "LIVE_RATE"
HAS_PORT = "HAS_PORT"
CONNECTED_TO = "CONNECTED_TO"
REQUIRES = "REQUIRES"
DEPLOYS = "DEPLOYS"
EXECUTABLE_ON = "EXECUTABLE_ON"
PROFILE_OF = "PROFILE_OF"
RAN_ON = "RAN_ON"
RAN_CONFIG = "RAN_CONFIG"
CHOSE = "CHOSE"
PLACED_ON = "PLACED_ON"
HAS_MARKER = "HAS_MARKER"


class Graph(enum.Enum):
    """Which of a robot's graphs holds a part of its knowledge (what a named query reads, a write verb writes)."""

    ROBOT = ""  # the store's own graph: models, platforms, processes, decisions
    # FleetRobot nodes (knowledge/fleet_roster.py). Every roll call writes them, and the query sandboxes copy the
    # robot's graph again after any write to it: kept in the robot's graph, each roll call made the fleet's
    # next question to every robot pay a copy (issue 32). So they are kept beside it where the store can.
    FLEET_ROSTER = ".fleet_roster"

    def store(self, robot_store: GraphStore) -> GraphStore:
        """Where this part is for the robot whose store is ``robot_store``: that store, or (where the backend
        holds several graphs, ``capabilities.graphs``) its sibling ``<graph><suffix>`` on the same server,
        connected at first use and shut down with ``robot_store``. ConfigError when ``robot_store`` is itself
        such a sibling: what is asked of it would be looked for in a graph that never holds it."""
        graph = robot_store.settings.graph
        if graph.endswith(_BESIDE):  # every named query runs through here: one test on the common path
            kept = next(part for part in Graph if part.value and graph.endswith(part.value))
            raise ConfigError(f"store {robot_store.url}: graph {graph!r} is a robot's {kept.name.lower()}, "
                              "not the robot's own graph: give the robot's store")
        if self is Graph.ROBOT or not robot_store.capabilities.graphs:
            return robot_store
        return robot_store.sibling(self.beside(robot_store.settings.graph))

    @property
    def labels(self) -> tuple[str, ...]:
        """The labels of the nodes this part holds; ROBOT: () (every node no other part holds). What tells the
        parts apart where a store keeps them all in one graph (an export, knowledge/export.py)."""
        return _LABELS.get(self, ())

    def beside(self, robot_graph: str) -> str:
        """The name of the graph that holds this part beside the robot's graph ``robot_graph`` on a store of
        several graphs (ROBOT: ``robot_graph`` itself)."""
        return f"{robot_graph}{self.value}"


_BESIDE = tuple(part.value for part in Graph if part.value)  # the suffixes of the graphs beside a robot's
_LABELS = {Graph.FLEET_ROSTER: (FLEET_ROBOT,)}


def is_beside(graph: str) -> bool:
    """True when ``graph`` is one of the graphs kept beside a robot's (a part of its knowledge), not a robot's."""
    return graph.endswith(_BESIDE)


# Every query starts from a named node; these make that start an index seek.
INDEXED_NAMES = (
    FEATURE,
    ILLUMINATION_BAND,
    PERCEPTION_GRAPH,
    COMPONENT,
    PORT,
    DEPLOYMENT,
    PLATFORM,
    PROCESS_PROFILE,
    ADAPTATION_DECISION,
    SITE,
    MARKER,
)


def ensure_indexes(store: GraphStore) -> None:
    """Create the name indexes in the store's own dialect; idempotent on every backend.

    Often a fresh store's first statements: bounded and retried on a restarted server (GraphStore.prepare).
    """
    store.prepare(_ensure_indexes)


def _ensure_indexes(store: GraphStore) -> None:
    dialect = store.dialect
    existing = dialect.indexed(store.execute(dialect.list_statement))
    for label in INDEXED_NAMES:
        if (label, "name") not in existing:
            store.execute(dialect.create_index(label, "name"))
