"""``kgadapt why``: explain the current placement of the marker detector from the graph.

Reads what the adaptation manager wrote (the running detector's process
profile and the decision that put it there, with the inputs it used) and asks
the placement query again, so the answer shows both why it was chosen then
and whether it still fits now. Works on the store directly (``--store``) or,
from another machine, through the knowledge service over Zenoh (``--connect``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Callable

from kgadapt.shared.errors import ConfigError
from kgadapt.shared.keys import DEFAULT_ROBOT
from kgadapt.shared.states import Change

Ask = Callable[[str, dict[str, Any]], list[dict[str, Any]]]


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "why", help="explain where the marker detector runs and why",
        description="Explain the current detector placement from the knowledge graph: the decision that "
                    "chose it, the inputs it used, and whether the placement query still agrees.")
    parser.add_argument("--store", metavar="URL", help="store URL (default $KGADAPT_STORE or embedded:)")
    parser.add_argument("--robot", default=None,
                        help="ask this robot's knowledge service over Zenoh (default: read --store directly, "
                             "or robot quad1 with --connect)")
    parser.add_argument("--history", type=int, default=5, metavar="N", help="also list the last N decisions (default 5)")
    parser.add_argument("--json", action="store_true", help="print the explanation as JSON")
    from kgadapt.shared.session import add_arguments

    add_arguments(parser)
    parser.set_defaults(func=run)


def explain(ask: Ask, *, history: int = 5) -> dict[str, Any]:
    """Everything ``why`` says, as data."""
    current = ask("current_placement", {})
    decisions = ask("decisions", {"limit": history})
    out: dict[str, Any] = {"running": current[0] if current else None, "history": decisions}
    if not current:
        return out
    row = current[0]
    chosen = next((d for d in decisions if d.get("name") == row.get("decision")), None)
    if chosen is None and row.get("decision"):
        chosen = next((d for d in ask("decisions", {"limit": 1000}) if d.get("name") == row["decision"]), None)
    if chosen is not None:
        try:
            chosen = {**chosen, "inputs": json.loads(chosen.get("inputs_json") or "null")}
        except ValueError:
            pass
    out["decision"] = chosen
    out["placement_now"] = ask("placement", {"config": row["config"]})
    return out


def render(data: dict[str, Any]) -> str:
    running = data.get("running")
    if not running:
        return "No detector is running according to the graph (no process profile without an end time)."
    lines = [f"The detector {running['instance']} runs configuration {running['config']} on {running['host']} "
             f"(pid {running.get('pid')}, started {_ago(running.get('start_time'))})."]
    d = data.get("decision")
    if d:
        lines.append(f"It was placed there by decision {d['name']} ({_ago(d.get('time'))}), triggered by "
                     f"{d.get('trigger')}:")
        lines.append(f"  {d.get('outcome')}")
        inputs = d.get("inputs") or {}
        if inputs.get("ranking"):
            excluded = set(inputs.get("excluded") or [])
            skipped = {k.get("config"): k.get("why") for k in inputs.get("skipped") or []}
            lines.append(f"  ranking for band {inputs.get('band')} (named query config_ranking: "
                         f"rate - false markers per frame; within half a point the faster beyond timing noise, "
                         f"then the more robust in the band's other conditions; live_rates: this robot's own figures):")
            for i, c in enumerate(inputs["ranking"], start=1):
                note = (" (left out: its detections collapsed)" if c.get("config") in excluded
                        else f" (skipped: {skipped[c.get('config')]})" if c.get("config") in skipped else "")
                lines.append(f"   {i}. {c.get('config')}: score {_num(c.get('score'))}{_evidence(c)}, "
                             f"false/frame {_num(c.get('false_per_frame'))}, {_num(c.get('ms_per_frame'))} ms/frame, "
                             + (f"robustness {_num(c['robustness'])}, " if c.get("robustness") is not None else "")
                             + f"{_num(c.get('memory_demand_mb'))} MiB{note}")
            if inputs.get("evidence"):
                lines.append(f"  decided by: {_decided_by(inputs['evidence'])}")
        for c in inputs.get("candidates") or []:
            rate = c.get("detection_rate")
            rate_text = ("not calibrated (run `kgadapt perception calibrate`)" if rate is None
                         else f"calibrated rate {rate:.0%}" if isinstance(rate, (int, float)) else f"calibrated rate {rate}")
            ms = c.get("ms_per_frame")
            lines.append(f"  candidate {c.get('config')}: {rate_text}, "
                         f"{ms if not isinstance(ms, float) else round(ms, 1)} ms/frame")
        for p in inputs.get("platforms") or []:
            lines.append(f"  platform {p.get('platform')}: {p.get('free_mb')} MiB free then")
        if inputs.get("change") == Change.RECONFIGURE:
            lines.append(f"  carried out in place: the running detector took the configuration between two frames "
                         f"(first frame {inputs.get('first_seq')}); {inputs.get('change_why')}")
        elif inputs.get("change") == Change.MIGRATE:
            lines.append(f"  carried out as a new process (make-before-break): {inputs.get('change_why')}")
        elif inputs.get("change") == Change.REFLEX:
            t = inputs.get("trigger") or {}
            lines.append(f"  the detector's own reflex ({t.get('evidence')}): it took {t.get('config')} in place "
                         f"between two frames, no round trip (light {t.get('level')}, band {t.get('from_band')} -> "
                         f"{t.get('band')}, {t.get('answered_ms')} ms after the frame's capture); the manager "
                         f"recorded it and planned for the band" + ("; its plan agrees" if inputs.get("ranking") else ""))
        elif inputs.get("change") == Change.STANDBY:
            sb = inputs.get("standby") or {}
            lines.append(f"  carried out as a switch to the warm standby {sb.get('instance')} (started idle for "
                         f"{sb.get('config')} on {sb.get('host')}; no new process): {inputs.get('change_why')}"
                         + (f"; the old detector {inputs.get('previous_instance')}: {inputs.get('old')}"
                            if inputs.get("previous_instance") else ""))
    else:
        lines.append("No adaptation decision chose this placement (started by hand?).")
    now = data.get("placement_now") or []
    hosts = ", ".join(f"{r['platform']} ({r['free_mb']:.0f} MiB free)" for r in now)
    lines.append(f"Now, the platforms that can hold {running['config']}: {hosts or 'none'}.")
    if data.get("history"):
        lines.append("Recent decisions:")
        for h in data["history"]:
            lines.append(f"  {_ago(h.get('time'))}  {h.get('trigger')} -> {h.get('config')}@{h.get('host')}")
    return "\n".join(lines)


def _evidence(c: dict[str, Any]) -> str:
    """Which figure scored a ranking row: live (with the calibrated one beside it) or the calibration's."""
    rate = f"calibrated rate {_num(c.get('detection_rate'))}"
    live = c.get("live_rate")
    if c.get("evidence") == "live":
        return (f" from live evidence (rate {_num(live)} over {c.get('live_frames_expected')} frames with markers "
                f"expected, {_num(c.get('live_age_s'))} s old; {rate})")
    source = f" from {c['evidence']} calibration" if c.get("evidence") else ""
    figure = f"; live rate {_num(live)} over {c.get('live_frames_expected')} frames, {_num(c.get('live_age_s'))} s old"
    unused = ("" if live is None else f"{figure}, agrees with it" if c.get("live_agrees")
              else f"{figure}, not counted: too few frames or too old")
    return f"{source} ({rate}{unused})"


def _decided_by(evidence: str) -> str:
    if evidence == "live":
        return ("live evidence (this robot's own detections in the band, fresh, on enough frames and "
                "disagreeing with calibration)")
    if evidence.startswith("frames:"):
        return f"calibration on recorded frames ({evidence})"
    return f"{evidence} calibration"


def _num(value: Any) -> str:
    return f"{value:.3g}" if isinstance(value, (int, float)) else "?"


def _ago(t: Any) -> str:
    from kgadapt.shared.timefmt import stamp

    return stamp(t)  # 14:02:31 UTC (12 s ago)


def run(args: argparse.Namespace) -> int:
    if args.robot or args.connect or args.zenoh_config:
        # A store holds one robot's knowledge and does not say whose: --robot always asks that robot's service.
        if args.store:
            raise ConfigError("give --store (read a store directly) or --robot/--connect (ask a robot's "
                              "knowledge service over Zenoh), not both")
        from kgadapt.knowledge.client import KnowledgeClient
        from kgadapt.shared.session import DEFAULT_ENDPOINT, open_session, settings_from_args

        zenoh = settings_from_args(args).with_defaults(mode="client", connect=[DEFAULT_ENDPOINT])
        session = open_session(zenoh)
        try:
            client = KnowledgeClient(session, args.robot or DEFAULT_ROBOT, own=True)
            data = explain(client.query, history=args.history)
        finally:
            session.close()
        source = f"the knowledge service of robot {client.robot} via {', '.join(zenoh.connect) or zenoh.config_file}"
    else:
        from kgadapt.knowledge.queries import run_named
        from kgadapt.knowledge.store import open_store

        with open_store(args.store) as store:
            data = explain(lambda name, params: run_named(store, name, params), history=args.history)
            source = f"store {store.url}"
    data["source"] = source
    print(json.dumps(data, default=str, indent=2) if args.json else f"{render(data)}\n(asked {source})")
    return 0
