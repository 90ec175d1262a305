"""Adaptation: the onboard MAPE-K loop that chooses the detector configuration and where it runs.

* :mod:`.adaptation` — analysis and planning (no I/O); :mod:`.adaptation_policy` — the manager's decisions
  as pure functions;
* :mod:`.adaptation_manager` — the loop as a part of the onboard agent; :mod:`.live_rate` — the running
  detector's evidence and how the ranking weighs it;
* :mod:`.planning_defaults` — the defaults the planner and the manager's settings share;
* :mod:`.adaptation_cli` — ``kgadapt why``.
"""
