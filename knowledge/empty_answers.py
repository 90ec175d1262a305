"""Why a named query answered nothing, when the graph can tell.

"(no rows)" alone cost newcomers time: right after loading no platform is
online yet; a typo in a configuration's name matches nothing; a mistyped
``--store embedded:DIR`` is a new, empty store. :func:`explain_empty` asks a
few named queries (the same on the store and over Zenoh) and either returns a
reason (the empty answer is right, and this is why) or raises
:class:`NamedQueryError` (the question itself names something the graph does
not have, or asks a store with nothing in it).
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

from kgadapt.shared.errors import NamedQueryError

Run = Callable[[str, dict[str, Any]], list[dict[str, Any]]]

# Queries whose answer needs an online platform.
_NEEDS_ONLINE = {"placement", "feature_deployments", "deployable_components", "cpu_overload"}
_RUN_TIME = {"decisions": "no adaptation decision yet (is `kgadapt onboard --adapt` running?)",
             "current_placement": "no detector process is running according to the graph",
             "low_memory_components": "no process profile with memory samples yet (no detector has run)",
             "fleet_roster": "no robot heard yet: the robot's knowledge service (kgadapt knowledge serve) keeps "
                             "the roster, itself first"}


def roster_outside(cypher: str) -> str:
    """Why free Cypher about the fleet roster answered nothing: it reads the robot's graph, and the roster is
    kept beside it (schema.Graph.FLEET_ROSTER); "" when the text does not name FleetRobot."""
    from kgadapt.knowledge import schema as S

    if S.FLEET_ROBOT not in cypher:
        return ""
    return (f"{S.FLEET_ROBOT} nodes are kept in the fleet roster's own graph beside the robot's on FalkorDB, and "
            "free Cypher reads the robot's graph: ask the named query fleet_roster")


def store_is_empty(run: Run) -> bool:
    """No platform and no detector configuration: nothing was loaded."""
    from kgadapt.knowledge.queries import DEFAULT_FEATURE

    return not run("platforms", {}) and not run("detector_configs", {"feature": DEFAULT_FEATURE})


def explain_empty(name: str, params: Mapping[str, Any], run: Run, *, where: str) -> str:
    """The reason ``name`` with ``params`` answered no rows on ``where`` (a store URL or a robot's service).

    Raises NamedQueryError when the reason is a mistake: a name the graph does not have, or nothing loaded.
    Returns "" when no reason is known.
    """
    from kgadapt.knowledge.queries import DEFAULT_FEATURE

    platforms = run("platforms", {})
    feature = params.get("feature") or DEFAULT_FEATURE
    configs = run("detector_configs", {"feature": feature})
    if not platforms and not configs and store_is_empty(run):
        raise NamedQueryError(f"{where} holds no models: nothing is loaded there (kgadapt knowledge load "
                              f"knowledge/models; a mistyped --store or a new terminal without $KGADAPT_STORE "
                              f"opens a new, empty store)")
    _check_named(params, platforms, configs, feature, run, where)
    if name in _RUN_TIME:
        return _RUN_TIME[name]
    if name in _NEEDS_ONLINE:
        online = [p for p in platforms if p.get("online") is True]
        if not online:
            return ("no platform is online yet: the hosts' agents (kgadapt onboard, kgadapt remote) mark them "
                    "online; `kgadapt status` shows which are up")
        if name == "placement":
            config = params.get("config")
            wanted = [r for r in configs if r.get("config") == config] if config else configs
            demand = max((float(r.get("memory_demand_mb") or 0) for r in wanted), default=0.0)
            free = ", ".join(f"{p['platform']} {p.get('memory_free_mb') or 0:.0f} MiB" for p in online)
            return (f"no online platform where it may run has the free memory it needs "
                    f"({demand:.0f} MiB; free now: {free})")
    return ""


def _check_named(params: Mapping[str, Any], platforms: list[dict[str, Any]], configs: list[dict[str, Any]],
                 feature: str, run: Run, where: str) -> None:
    config = params.get("config")
    if config and not run("detector_config", {"config": config}):
        known = sorted({str(r.get("config")) for r in configs})
        raise NamedQueryError(f"no detector configuration {config!r} in {where}; known: {', '.join(known) or 'none'}")
    platform = params.get("platform")
    if platform and platform not in {p.get("platform") for p in platforms}:
        known = sorted(str(p.get("platform")) for p in platforms)
        raise NamedQueryError(f"no platform {platform!r} in {where}; known: {', '.join(known) or 'none'}")
    if params.get("feature") and not configs:
        raise NamedQueryError(f"no configuration realises feature {feature!r} in {where}")
    band = params.get("band")
    if band and band not in {r.get("band") for r in configs}:
        known = sorted({str(r.get("band")) for r in configs if r.get("band")})
        raise NamedQueryError(f"no illumination band {band!r} in {where}; known: {', '.join(known) or 'none'}")
    deployment = params.get("name")
    if deployment and not run("deployment", {"name": deployment}):
        raise NamedQueryError(f"no deployment {deployment!r} in {where}")
