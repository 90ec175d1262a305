"""The named, parameterised queries every part of kgadapt asks the knowledge graph.

A :class:`NamedQuery` is Cypher text with declared parameters; callers give
values, never text (``run_named`` checks names and types first and raises
:class:`NamedQueryError` naming the query and parameter). All run read-only.

The production queries follow the meaningful relations in their direction,
with bounded patterns, starting from the most selective named (indexed) node,
so their cost does not grow with the number of models (docs/bench-table1.md
has the figures). The paper's own texts are kept as ``fig4_literal`` and
``fig5_literal``: their unbounded ``-[*]-`` walks the whole graph once many
models share platforms, and Fig. 4's second MATCH is not joined to its first
(it returns every deployment executable on the platform whenever the feature
reaches any component).

Each query declares the graph it reads (``graph``, :class:`kgadapt.knowledge.schema.Graph`): callers pass
the robot's store and ``run_named`` runs it where that part of the knowledge is (``fleet_roster``: the
fleet roster's graph beside the robot's, on FalkorDB).

Where a query may be anchored on an optional parameter (``placement`` and
``cpu_overload`` on ``config``), ``cypher`` is the anchored text and
``when_missing`` holds the text used without it: one index seek instead of a
condition that would defeat the index.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from kgadapt.knowledge import schema as S
from kgadapt.knowledge.cypher_guard import CypherLimits
from kgadapt.knowledge.store import GraphStore
from kgadapt.shared.errors import NamedQueryError

DEFAULT_FEATURE = "MarkerDetection"
LITERAL_TIME_LIMIT_MS = 1000  # the paper's unbounded texts: 315 ms at N = 10, unbounded beyond


@dataclass(frozen=True)
class Param:
    """A declared parameter: ``type`` is "str", "int", "float" or "bool"; a number may be bounded (``low``,
    ``high``, inclusive)."""

    type: str
    required: bool = True
    default: Any = None
    help: str = ""
    low: float | None = None
    high: float | None = None

    def describe(self, name: str) -> str:
        if self.required:
            return f"{name}: {self.type}"
        if self.default is None:
            return f"{name}: {self.type} (optional)"
        return f"{name}: {self.type} = {self.default}"


@dataclass(frozen=True)
class NamedQuery:
    """A query by name: its meaning, its parameters and its Cypher text."""

    name: str
    description: str
    params: dict[str, Param]
    cypher: str
    when_missing: Mapping[str, str] = field(default_factory=dict)
    # A hard limit for queries that can run for ever (the paper's literal texts):
    # they always run in a query sandbox, killed when the limit is hit.
    time_limit_ms: int | None = None
    # The graph it reads (schema.Graph): run_named runs it there, given the robot's store.
    graph: S.Graph = S.Graph.ROBOT

    def text_for(self, values: Mapping[str, Any]) -> str:
        """The Cypher text for these (checked) values."""
        for param, text in self.when_missing.items():
            if values.get(param) is None:
                return text
        return self.cypher


_FEATURE = Param("str", required=False, default=DEFAULT_FEATURE, help="feature name")
_BAND = Param("str", help="illumination band, e.g. dark")
_SOURCE = Param("str", required=False, default="synthetic",
                help="what the figures were measured on: synthetic or frames:NAME (default synthetic)")
_CONFIG_OPT = Param("str", required=False, help="detector configuration (PerceptionGraph name)")

# Pieces shared by queries; labels and relation types only from knowledge/schema.py.
# A calibrated configuration's figures in its band's other conditions (not the one ranked, not the whole
# band), of the same source: what breaks a tie by robustness (kgadapt.onboard.perception.ranking).
# count(o) says whether there were any, rather than what each backend makes of an average over none.
_WHOLE = Param("str", required=False, default="all",
               help="the condition that stands for the band as a whole, left out of the other conditions (default all)")
_OTHER_CONDITIONS = f"""OPTIONAL MATCH (g)-[o:{S.CALIBRATED}]->(b)
WHERE o.condition <> $condition AND o.condition <> $whole AND coalesce(o.source, $source) = $source"""
_OTHER_FIGURES = ("avg(o.detection_rate) AS other_rate, avg(coalesce(o.false_per_frame, 0.0)) AS other_false_per_frame, "
                  "count(o) AS other_conditions")
_DEMAND = f"""
MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH g, sum(c.memory_demand_mb) AS demand"""
_PLACEMENT_TAIL = f"""
MATCH (g)<-[:{S.DEPLOYS}]-(d:{S.DEPLOYMENT})-[:{S.EXECUTABLE_ON}]->(p:{S.PLATFORM})
WHERE p.online = true AND p.memory_free_mb >= demand
RETURN g.name AS config, d.name AS deployment, p.name AS platform,
       demand AS demand_mb, p.memory_free_mb AS free_mb
ORDER BY config, free_mb DESC, platform"""
_CPU_TAIL = f"""
MATCH (p:{S.PLATFORM} {{name: $platform}})
OPTIONAL MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH g, p, sum(c.cpu_load) AS detector_load
OPTIONAL MATCH (fc:{S.FLIGHT_CONTROL})
WITH g, p, detector_load, sum(fc.cpu_load) AS flight_load
WITH g, p, detector_load, flight_load, detector_load + flight_load AS total,
     p.cpu_capacity * $limit_pct / 100.0 AS limit_load
RETURN g.name AS config, p.name AS platform, detector_load, flight_load AS flight_control_load,
       total AS total_load, limit_load, total > limit_load AS exceeds
ORDER BY config"""

_QUERIES = [
    NamedQuery(
        "feature_deployments",
        "Fig. 4, directed: deployments of the perception graphs realising a feature that are "
        "executable on a platform.",
        {"feature": _FEATURE, "platform": Param("str", help="platform name, e.g. remote")},
        f"""
MATCH (f:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      <-[:{S.DEPLOYS}]-(d:{S.DEPLOYMENT})-[:{S.EXECUTABLE_ON}]->(p:{S.PLATFORM} {{name: $platform}})
RETURN d.name AS deployment, d.kind AS kind, g.name AS config, p.name AS platform
ORDER BY deployment""",
    ),
    NamedQuery(
        "placement",
        "Fig. 5, directed: online platforms whose free memory covers the summed memory demand of "
        "the components a detector configuration contains (every configuration of the feature, "
        "or the one given), where its deployment may run. Roomiest platform first.",
        {"feature": _FEATURE, "config": _CONFIG_OPT},
        f"""
MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}})-[:{S.REALIZES}]->(:{S.FEATURE} {{name: $feature}})"""
        + _DEMAND + _PLACEMENT_TAIL,
        when_missing={"config": f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})"""
                      + _DEMAND + _PLACEMENT_TAIL},
    ),
    NamedQuery(
        "deployable_components",
        "Components required for a feature that are also deployable on a platform "
        "(the remote host unless told otherwise), with the configurations that bring them there.",
        {"feature": _FEATURE, "platform": Param("str", required=False, default="remote", help="platform name")},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      <-[:{S.DEPLOYS}]-(:{S.DEPLOYMENT})-[:{S.EXECUTABLE_ON}]->(:{S.PLATFORM} {{name: $platform}})
MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH c, g ORDER BY g.name
RETURN c.name AS component, c.memory_demand_mb AS memory_demand_mb, collect(DISTINCT g.name) AS configs
ORDER BY component""",
    ),
    NamedQuery(
        "camera_resolutions",
        "Whether a feature can be realised with cameras of different resolutions: one row per "
        "resolution among the cameras of its perception graphs (more than one row means yes).",
        {"feature": _FEATURE},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})-[:{S.CONTAINS}]->(c:{S.CAMERA})
WITH c.width AS width, c.height AS height, c.name AS camera, g.name AS config
ORDER BY camera, config
RETURN width, height, collect(DISTINCT camera) AS cameras, collect(DISTINCT config) AS configs
ORDER BY width, height""",
    ),
    NamedQuery(
        "low_memory_components",
        "Components of a feature that ran in the past (process profiles with memory samples) "
        "with an average memory usage below a threshold.",
        {"feature": _FEATURE, "threshold_mb": Param("float", help="average resident memory limit, MiB")},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      <-[:{S.RAN_CONFIG}]-(r:{S.PROCESS_PROFILE})
WHERE r.rss_mb_mean IS NOT NULL
MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH c, avg(r.rss_mb_mean) AS avg_mb, count(DISTINCT r) AS runs
WHERE avg_mb < $threshold_mb
RETURN c.name AS component, runs, avg_mb AS avg_memory_mb
ORDER BY component""",
    ),
    NamedQuery(
        "cpu_overload",
        "Whether the CPU load would exceed a limit if a detector configuration (each of the "
        "feature's, or the one given) and the flight control ran on the same platform. Loads are "
        "the design-time cpu_load figures in percent of one core; the limit is limit_pct percent "
        "of the platform's capacity (100 per core).",
        {"platform": Param("str", help="platform name"), "config": _CONFIG_OPT, "feature": _FEATURE,
         "limit_pct": Param("float", required=False, default=80.0, help="percent of the platform's CPU capacity")},
        f"""
MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}})-[:{S.REALIZES}]->(:{S.FEATURE} {{name: $feature}})"""
        + _CPU_TAIL,
        when_missing={"config": f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})""" + _CPU_TAIL},
    ),
    NamedQuery(
        "detector_configs",
        "The detector configurations realising a feature: the band each is suited for, its memory "
        "demand, and its calibrated detection rate in that band (null until calibrated). "
        "ms_per_frame is the calibrated figure, else the design-time estimate. Calibration of the "
        "band as a whole (condition all) unless another condition is given.",
        {"feature": _FEATURE, "condition": Param("str", required=False, default="all",
                                                 help="calibration condition (default all)"),
         "source": _SOURCE},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
OPTIONAL MATCH (g)-[:{S.SUITED_FOR}]->(b:{S.ILLUMINATION_BAND})
OPTIONAL MATCH (g)-[cal:{S.CALIBRATED} {{condition: $condition}}]->(b)
WHERE coalesce(cal.source, $source) = $source
OPTIONAL MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH g, b, cal, sum(c.memory_demand_mb) AS demand, max(c.ms_per_frame) AS design_ms
RETURN g.name AS config, b.name AS band, b.min_level AS min_level, b.max_level AS max_level,
       demand AS memory_demand_mb, cal.detection_rate AS detection_rate,
       cal.false_per_frame AS false_per_frame, cal.false_per_reported AS false_per_reported,
       coalesce(cal.ms_per_frame, design_ms) AS ms_per_frame, cal.at AS calibrated_at
ORDER BY min_level, config""",
    ),
    NamedQuery(
        "config_ranking",
        "Every configuration realising a feature, ranked by its calibrated figures in a band and "
        "condition (all = the band as a whole): score = detection rate minus penalty x false markers "
        "per frame; configurations slower than max_ms per frame are left out. Memory demand is "
        "returned for the planner's placement. Highest score first; the planner breaks ties within half a "
        "point by speed beyond timing noise, then robustness (config_robustness), then name "
        "(kgadapt.onboard.perception.ranking).",
        {"feature": _FEATURE, "band": _BAND,
         "condition": Param("str", required=False, default="all",
                            help="all, clean, blur, uneven, window or small (default all)"),
         "penalty": Param("float", required=False, default=1.0,
                          help="score lost per false marker per frame (default 1.0)"),
         "max_ms": Param("float", required=False, default=1000.0,
                         help="leave out configurations slower than this, ms per frame (default 1000)"),
         "source": _SOURCE},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      -[cal:{S.CALIBRATED}]->(b:{S.ILLUMINATION_BAND} {{name: $band}})
WHERE cal.condition = $condition AND cal.ms_per_frame <= $max_ms AND coalesce(cal.source, $source) = $source
OPTIONAL MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH g, cal, sum(c.memory_demand_mb) AS demand
OPTIONAL MATCH (g)-[:{S.SUITED_FOR}]->(s:{S.ILLUMINATION_BAND})
RETURN g.name AS config, cal.detection_rate AS detection_rate, cal.false_per_frame AS false_per_frame,
       cal.false_per_reported AS false_per_reported, cal.ms_per_frame AS ms_per_frame,
       demand AS memory_demand_mb, s.name AS suited_for,
       cal.detection_rate - $penalty * coalesce(cal.false_per_frame, 0.0) AS score
ORDER BY score DESC, ms_per_frame ASC, config""",
    ),
    NamedQuery(
        "config_robustness",
        "How robust each configuration calibrated in a band and condition is: its mean figures in the "
        "band's other conditions from the same source (neither condition nor whole): other_rate, "
        "other_false_per_frame, other_conditions (how many; null rate and 0 where none). What breaks a tie "
        "of config_ranking between equally fast configurations (kgadapt.onboard.perception.ranking).",
        {"feature": _FEATURE, "band": _BAND,
         "condition": Param("str", required=False, default="all",
                            help="the condition ranked: all, clean, blur, uneven, window or small (default all)"),
         "source": _SOURCE,
         "whole": _WHOLE},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      -[cal:{S.CALIBRATED}]->(b:{S.ILLUMINATION_BAND} {{name: $band}})
WHERE cal.condition = $condition AND coalesce(cal.source, $source) = $source
{_OTHER_CONDITIONS}
WITH g, {_OTHER_FIGURES}
RETURN g.name AS config, other_rate, other_false_per_frame, other_conditions
ORDER BY config""",
    ),
    NamedQuery(
        "live_rates",
        "What this robot's running detectors found in a band and condition (all = the band as a whole): "
        "per configuration of the feature its live detection rate (markers found per marker expected), the "
        "frames of its window (frames, with markers expected, with markers seen), the window's start and "
        "last update (since, at) and the process measured (run_id, host). The planner weighs fresh "
        "figures with enough frames above calibration (kgadapt.onboard.adaptation.live_rate).",
        {"feature": _FEATURE, "band": _BAND,
         "condition": Param("str", required=False, default="all", help="condition (default all)")},
        f"""
MATCH (:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
      -[l:{S.LIVE_RATE} {{condition: $condition}}]->(:{S.ILLUMINATION_BAND} {{name: $band}})
RETURN g.name AS config, l.detection_rate AS detection_rate, l.frames AS frames,
       l.frames_expected AS frames_expected, l.frames_seen AS frames_seen, l.since AS since, l.at AS at,
       l.run_id AS run_id, l.host AS host
ORDER BY config""",
    ),
    NamedQuery(
        "reflex_table",
        "What a running detector may switch to on its own, between two frames: for every illumination "
        "band (lowest first; its edges and margin) each configuration of the feature calibrated in it "
        "(condition, default all) or suited for it, with its settings, its figures, whether the running "
        "deployment may take it in place on the host (in_place_change's rule) and the feature's "
        "ms-per-frame budget, and this robot's live figures of it in the band (live_rate, live_frames_expected, "
        "live_at; as live_rates gives them), its mean figures in the band's other conditions (other_rate, "
        "other_false_per_frame, other_conditions, as config_robustness gives them), and its figures under motion "
        "blur in the band (blur_rate, blur_false_per_frame; condition $blur, null where not calibrated: what a "
        "collapse of its detections in steady light tries first). The detector ranks the rows "
        "as the planner does (kgadapt.onboard.perception.ranking), with fresh live evidence weighed above "
        "calibration (kgadapt.onboard.adaptation.live_rate).",
        {"feature": _FEATURE, "deployment": Param("str", help="deployment of the running detector"),
         "host": Param("str", help="platform it runs on"),
         "condition": Param("str", required=False, default="all", help="calibration condition (default all)"),
         "source": _SOURCE,
         "whole": _WHOLE,
         "blur": Param("str", required=False, default="blur",
                       help="the calibration condition of motion blur (default blur)")},
        f"""
MATCH (f:{S.FEATURE} {{name: $feature}})<-[:{S.REALIZES}]-(g:{S.PERCEPTION_GRAPH})
MATCH (b:{S.ILLUMINATION_BAND})
OPTIONAL MATCH (g)-[cal:{S.CALIBRATED} {{condition: $condition}}]->(b)
WHERE coalesce(cal.source, $source) = $source
OPTIONAL MATCH (g)-[suit:{S.SUITED_FOR}]->(b)
WITH f, g, b, cal, suit
WHERE cal IS NOT NULL OR suit IS NOT NULL
{_OTHER_CONDITIONS}
WITH f, g, b, cal, suit, {_OTHER_FIGURES}
OPTIONAL MATCH (g)-[bl:{S.CALIBRATED} {{condition: $blur}}]->(b)
WHERE coalesce(bl.source, $source) = $source
WITH f, g, b, cal, suit, other_rate, other_false_per_frame, other_conditions,
     avg(bl.detection_rate) AS blur_rate, avg(bl.false_per_frame) AS blur_false_per_frame
MATCH (g)-[:{S.CONTAINS}]->(m:{S.PROCESSING_COMPONENT})
WHERE m.config_json IS NOT NULL
OPTIONAL MATCH (g)-[lr:{S.LIVE_RATE} {{condition: $condition}}]->(b)
OPTIONAL MATCH (g)<-[:{S.DEPLOYS}]-(d:{S.DEPLOYMENT})-[:{S.EXECUTABLE_ON}]->(:{S.PLATFORM} {{name: $host}})
OPTIONAL MATCH (a:{S.DEPLOYMENT} {{name: $deployment}})-[:{S.EXECUTABLE_ON}]->(:{S.PLATFORM} {{name: $host}})
WITH f, g, b, cal, suit, other_rate, other_false_per_frame, other_conditions, blur_rate, blur_false_per_frame,
     lr, m, d, d IS NOT NULL AND a IS NOT NULL AND (d.name = a.name OR (a.reconfigurable_as IS NOT NULL
         AND a.reconfigurable_as = d.reconfigurable_as AND a.executable = d.executable)) AS here
RETURN b.name AS band, b.min_level AS min_level, b.max_level AS max_level, b.margin AS margin,
       g.name AS config, m.dictionary AS dictionary, m.config_json AS config_json,
       cal.detection_rate AS detection_rate, cal.false_per_frame AS false_per_frame,
       coalesce(cal.ms_per_frame, m.ms_per_frame) AS ms_per_frame, suit IS NOT NULL AS suited,
       d.name AS deployment, here AS in_place, f.frame_budget_ms AS budget_ms,
       lr.detection_rate AS live_rate, lr.frames_expected AS live_frames_expected, lr.at AS live_at,
       other_rate, other_false_per_frame, other_conditions, blur_rate, blur_false_per_frame
ORDER BY min_level, config, in_place DESC, deployment""",
    ),
    NamedQuery(
        "detector_config",
        "One detector configuration: its ArUco dictionary, detector settings (config_json), "
        "memory demand and deployment. No row when the configuration is unknown.",
        {"config": Param("str", help="detector configuration (PerceptionGraph name)")},
        f"""
MATCH (g:{S.PERCEPTION_GRAPH} {{name: $config}})
OPTIONAL MATCH (g)-[:{S.CONTAINS}]->(c:{S.COMPONENT})
WITH g, sum(c.memory_demand_mb) AS demand
OPTIONAL MATCH (g)-[:{S.CONTAINS}]->(m:{S.PROCESSING_COMPONENT})
WHERE m.config_json IS NOT NULL
OPTIONAL MATCH (g)<-[:{S.DEPLOYS}]-(d:{S.DEPLOYMENT})
RETURN g.name AS config, m.dictionary AS dictionary, m.config_json AS config_json,
       demand AS memory_demand_mb, min(d.name) AS deployment""",
    ),
    NamedQuery(
        "deployment",
        "One deployment description: kind, executable, arguments, environment, the platforms it "
        "is executable on and what it deploys. No row when unknown.",
        {"name": Param("str", help="deployment name")},
        f"""
MATCH (d:{S.DEPLOYMENT} {{name: $name}})
OPTIONAL MATCH (d)-[:{S.EXECUTABLE_ON}]->(p:{S.PLATFORM})
WITH d, p ORDER BY p.name
WITH d, collect(p.name) AS platforms
OPTIONAL MATCH (d)-[:{S.DEPLOYS}]->(t)
WITH d, platforms, t ORDER BY t.name
RETURN d.name AS name, d.kind AS kind, d.executable AS executable, d.arguments AS arguments,
       d.environment AS environment, platforms, collect(t.name) AS deploys""",
    ),
    NamedQuery(
        "in_place_change",
        "Whether a running process of deployment `from` may take the configuration of deployment "
        "`to` in place on `host` (no restart): both executable there, the same executable, and the "
        "same program family (reconfigurable_as). One row when it may, none when a new process is needed.",
        {"from": Param("str", help="deployment of the running process"),
         "to": Param("str", help="deployment of the planned configuration"),
         "host": Param("str", help="platform both would run on")},
        f"""
MATCH (a:{S.DEPLOYMENT} {{name: $from}})-[:{S.EXECUTABLE_ON}]->(p:{S.PLATFORM} {{name: $host}})
MATCH (b:{S.DEPLOYMENT} {{name: $to}})-[:{S.EXECUTABLE_ON}]->(p)
WHERE a.reconfigurable_as IS NOT NULL AND a.reconfigurable_as = b.reconfigurable_as
      AND a.executable = b.executable
RETURN a.reconfigurable_as AS family, a.name AS from_deployment, b.name AS to_deployment, p.name AS host""",
    ),
    NamedQuery(
        "platforms",
        "Every platform with its design-time size and its latest run-time figures (null until known).",
        {},
        f"""
MATCH (p:{S.PLATFORM})
RETURN p.name AS platform, p.memory_total_mb AS memory_total_mb, p.memory_free_mb AS memory_free_mb,
       p.cpu_load AS cpu_load, p.online AS online, p.online_since AS online_since, p.last_seen AS last_seen,
       p.cpu_cores AS cpu_cores, p.cpu_capacity AS cpu_capacity
ORDER BY platform""",
    ),
    NamedQuery(
        "flight_control",
        "The flight control component(s) with the flight state last written into the graph (null until "
        "a flight bridge writes it).",
        {},
        f"""
MATCH (c:{S.FLIGHT_CONTROL})
RETURN c.name AS name, c.mode AS mode, c.armed AS armed, c.landed_state AS landed_state, c.link AS link,
       c.last_seen AS last_seen
ORDER BY name""",
    ),
    NamedQuery(
        "process_profile",
        "One process run's profile (the deployer's run id): its instance, host and resource figures "
        "(null until sampled). rss_mb_max is what the adaptation manager counts as the memory it holds.",
        {"run_id": Param("str", help="run id, as the deployer reports it")},
        f"""
MATCH (r:{S.PROCESS_PROFILE} {{name: $run_id}})
RETURN r.name AS run_id, r.instance AS instance, r.host AS host, r.rss_mb_last AS rss_mb_last,
       r.rss_mb_mean AS rss_mb_mean, r.rss_mb_max AS rss_mb_max, r.cpu_percent_mean AS cpu_percent_mean""",
    ),
    NamedQuery(
        "camera_intrinsics",
        "A camera component's pinhole intrinsics in pixels (null where the model gives none).",
        {"camera": Param("str", help="camera component name, e.g. camera")},
        f"""
MATCH (c:{S.COMPONENT} {{name: $camera}})
RETURN c.name AS camera, c.fx AS fx, c.fy AS fy, c.cx AS cx, c.cy AS cy""",
    ),
    NamedQuery(
        "site_markers",
        "The markers of a landing site (a *.site model): one row per marker with its id, printed size "
        "(m), dictionary, optional name and position; every site's when none is given. The flight "
        "bridge's confirmation and landing targets use them.",
        {"site": Param("str", required=False, help="site name, e.g. demo-hall")},
        f"""
MATCH (s:{S.SITE} {{name: $site}})-[:{S.HAS_MARKER}]->(m:{S.MARKER})
RETURN s.name AS site, s.dictionary AS site_dictionary, m.marker_id AS marker_id, m.size_m AS size_m,
       m.dictionary AS dictionary, m.marker_name AS marker_name, m.position AS position
ORDER BY site, marker_id""",
        when_missing={"site": f"""
MATCH (s:{S.SITE})-[:{S.HAS_MARKER}]->(m:{S.MARKER})
RETURN s.name AS site, s.dictionary AS site_dictionary, m.marker_id AS marker_id, m.size_m AS size_m,
       m.dictionary AS dictionary, m.marker_name AS marker_name, m.position AS position
ORDER BY site, marker_id"""},
    ),
    NamedQuery(
        "decisions",
        "The adaptation decisions taken, newest first.",
        # At most the rows any public question gets (CypherLimits.max_rows): the text has its own LIMIT.
        {"limit": Param("int", required=False, default=20, low=0, high=CypherLimits().max_rows, help="how many")},
        f"""
MATCH (a:{S.ADAPTATION_DECISION})
RETURN a.name AS name, a.time AS time, a.trigger AS trigger, a.inputs_json AS inputs_json,
       a.query AS query, a.config AS config, a.host AS host, a.duration_ms AS duration_ms,
       a.outcome AS outcome
ORDER BY time DESC, name DESC
LIMIT $limit""",
    ),
    NamedQuery(
        "current_placement",
        "The running detector process (a process profile with no end time that ran a detector "
        "configuration; of several, the one a decision chose last, then the newest), and the newest "
        "decision that chose that configuration and host. A warm standby (started idle by a "
        "'standby' decision) is not the running detector until a later decision chooses it.",
        {"standby": Param("str", required=False, default="standby",
                          help="the trigger that starts a standby (decisions whose trigger starts with it)")},
        f"""
MATCH (r:{S.PROCESS_PROFILE})-[:{S.RAN_CONFIG}]->(g:{S.PERCEPTION_GRAPH})
WHERE r.end_time IS NULL
OPTIONAL MATCH (g)<-[:{S.CHOSE}]-(c:{S.ADAPTATION_DECISION})
WHERE c.host = r.host AND NOT c.trigger STARTS WITH $standby
WITH r, g, max(c.time) AS chosen_at
OPTIONAL MATCH (g)<-[:{S.CHOSE}]-(s:{S.ADAPTATION_DECISION})
WHERE s.host = r.host AND s.trigger STARTS WITH $standby
WITH r, g, chosen_at, max(s.time) AS standby_at
WHERE standby_at IS NULL OR (chosen_at IS NOT NULL AND chosen_at > standby_at)
WITH r, g ORDER BY coalesce(chosen_at, -1.0) DESC, r.start_time DESC, r.name DESC LIMIT 1
OPTIONAL MATCH (g)<-[:{S.CHOSE}]-(a:{S.ADAPTATION_DECISION})
WHERE a.host = r.host AND NOT a.trigger STARTS WITH $standby
WITH r, g, a ORDER BY a.time DESC
WITH r, g, collect(a)[0] AS a
RETURN r.instance AS instance, g.name AS config, r.host AS host, r.pid AS pid,
       r.start_time AS start_time, r.name AS run_id, a.name AS decision, a.time AS decision_time,
       a.trigger AS trigger""",
    ),
    NamedQuery(
        "fleet_roster",
        "The robots this robot's knowledge service has heard answer or announce on the fleet keys (itself "
        "included), with when it first and last heard them and their Zenoh routers. A fleet question lists "
        "one that does not answer as silent. The parameters are a roll call's: the asking robot announces "
        "itself, its Zenoh id and its routers (knowledge/fleet_roster.py).",
        {"announce": Param("str", required=False, help="the asking robot, announcing itself"),
         "zid": Param("str", required=False, help="its knowledge service's Zenoh id"),
         "routers": Param("str", required=False, help="its Zenoh routers' ids, comma-separated")},
        f"""
MATCH (r:{S.FLEET_ROBOT})
RETURN r.name AS robot, r.first_seen AS first_seen, r.last_seen AS last_seen, r.heard AS heard,
       r.zid AS zid, r.routers AS routers
ORDER BY robot""",
        graph=S.Graph.FLEET_ROSTER,
    ),
    NamedQuery(
        "fig4_literal",
        "The paper's Fig. 4 as written (unbounded undirected path; the second MATCH is not "
        "joined to the first). Kept for comparison; use feature_deployments.",
        {"feature": _FEATURE, "platform": Param("str", help="platform name")},
        f"""
MATCH (f:{S.FEATURE})-[*]-(c:{S.COMPONENT})
WHERE f.name = $feature
MATCH (p:{S.PLATFORM})-[:{S.EXECUTABLE_ON}]-(d:{S.DEPLOYMENT})
WHERE p.name = $platform
RETURN d""",
        time_limit_ms=LITERAL_TIME_LIMIT_MS,
    ),
    NamedQuery(
        "fig5_literal",
        "The paper's Fig. 5 as written (unbounded <-[*]->, memory of every component reachable "
        "from the feature), with our property names. Kept for comparison; use placement.",
        {"feature": _FEATURE},
        f"""
MATCH (f:{S.FEATURE} {{name: $feature}}) <-[*]-> (c:{S.COMPONENT})
WITH DISTINCT c
WITH SUM(c.memory_demand_mb) as MEM
MATCH (p:{S.PLATFORM}) <-[:{S.EXECUTABLE_ON}]-(d:{S.DEPLOYMENT})
WHERE p.memory_free_mb >= MEM
RETURN p""",
        time_limit_ms=LITERAL_TIME_LIMIT_MS,
    ),
]

QUERIES: dict[str, NamedQuery] = {q.name: q for q in _QUERIES}


def get_query(name: str) -> NamedQuery:
    """The named query, or NamedQueryError listing the known names."""
    try:
        return QUERIES[name]
    except KeyError:
        raise NamedQueryError(f"unknown named query {name!r} (known: {', '.join(sorted(QUERIES))})") from None


def check_params(name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Every declared parameter of query ``name`` with a checked value (None for an absent optional)."""
    query = get_query(name)
    params = dict(params or {})
    for key in params:
        if key not in query.params:
            known = ", ".join(query.params) or "none"
            raise NamedQueryError(f"query {name!r} has no parameter {key!r} (parameters: {known})")
    values: dict[str, Any] = {}
    for key, spec in query.params.items():
        value = params.get(key)
        if value is None:
            if spec.required:
                what = f"{spec.type}: {spec.help}" if spec.help else spec.type
                raise NamedQueryError(f"query {name!r} needs parameter {key!r} ({what})")
            value = spec.default
        if value is not None:
            value = _typed(name, key, spec.type, value)
            if (spec.low is not None and value < spec.low) or (spec.high is not None and value > spec.high):
                raise NamedQueryError(f"query {name!r}: parameter {key!r} {value!r} is not between "
                                      f"{spec.low if spec.low is not None else '-inf'} and "
                                      f"{spec.high if spec.high is not None else 'inf'}")
        values[key] = value
    return values


def _typed(name: str, key: str, kind: str, value: Any) -> Any:
    ok = {
        "str": isinstance(value, str),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "bool": isinstance(value, bool),
    }.get(kind)
    if ok is None:
        raise NamedQueryError(f"query {name!r}: parameter {key!r} declares unknown type {kind!r}")
    if not ok:
        raise NamedQueryError(f"query {name!r}: parameter {key!r} must be {kind}, not {type(value).__name__} ({value!r})")
    if kind == "float":
        if not math.isfinite(value):
            raise NamedQueryError(f"query {name!r}: parameter {key!r} must be a finite number, not {value!r}")
        return float(value)
    if kind == "str" and not value:
        raise NamedQueryError(f"query {name!r}: parameter {key!r} is empty")
    return value


def run_named(store: GraphStore, name: str, params: Mapping[str, Any] | None = None, *,
              timeout_ms: int | None = None) -> list[dict[str, Any]]:
    """Check the parameters, then run named query ``name`` read-only on the graph it reads (``store`` is the
    robot's store: its own graph, or the one beside it that the query's ``graph`` names); return its rows."""
    values = check_params(name, params)
    query = get_query(name)
    return query.graph.store(store).execute(query.text_for(values), values, read_only=True, timeout_ms=timeout_ms)


_TRUE = {"true", "yes", "1", "on"}
_FALSE = {"false", "no", "0", "off"}


def coerce_params(name: str, raw: Mapping[str, str]) -> dict[str, Any]:
    """Command-line strings to the types query ``name`` declares (unknown names are refused)."""
    query = get_query(name)
    out: dict[str, Any] = {}
    for key, text in raw.items():
        spec = query.params.get(key)
        if spec is None:
            known = ", ".join(query.params) or "none"
            raise NamedQueryError(f"query {name!r} has no parameter {key!r} (parameters: {known})")
        try:
            if spec.type == "int":
                out[key] = int(text)
            elif spec.type == "float":
                out[key] = float(text)
            elif spec.type == "bool":
                lowered = text.strip().lower()
                if lowered not in _TRUE | _FALSE:
                    raise ValueError(text)
                out[key] = lowered in _TRUE
            else:
                out[key] = text
        except ValueError:
            raise NamedQueryError(f"query {name!r}: parameter {key!r} must be {spec.type}, not {text!r}") from None
    return out


def catalogue() -> list[dict[str, Any]]:
    """One row per named query: name, parameters, description (for listings)."""
    return [{"name": q.name, "params": ", ".join(p.describe(k) for k, p in q.params.items()) or "-",
             "description": q.description} for q in _QUERIES]
