"""The defaults the planner and the adaptation manager's settings share, in one place so they cannot drift.

:class:`~kgadapt.onboard.adaptation.adaptation.Planner`,
:class:`~kgadapt.onboard.adaptation.adaptation_policy.AdaptationSettings` and the onboard agent's command
line (``--prefer``, its host name) all take these. Plain values with no imports: the command line reads
them before anything heavy is loaded.
"""

from __future__ import annotations

ONBOARD_FIRST = "onboard-first"  # keep the detector on the quadcopter while it fits: the link to the remote can fail
REMOTE_FIRST = "remote-first"  # save the quadcopter's CPU and memory instead
PREFERENCES = (ONBOARD_FIRST, REMOTE_FIRST)
DEFAULT_PREFERENCE = ONBOARD_FIRST
ONBOARD_HOST = "onboard"  # the onboard agent's host name: its platform in the shipped models
IN_PLACE = True  # reconfigure in place where the graph allows it (False: every change is a new process)
