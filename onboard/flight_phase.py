"""Which phase of flight a ``flight_state`` message says the vehicle is in, on the safe side.

The adaptation manager defers planned changes during the final descent. The
autopilot's landed state says so directly (LANDING); when it is unknown (its
stream stopped, an autopilot reboot, or the autopilot never sends it) a landing
mode counts as final descent: deferring a change is cheap, losing the detector
over the pad is not.
"""

from __future__ import annotations

from typing import Any, Mapping

# ArduCopter's LAND and RTL (whose last phase is a landing), PX4's AUTO.LAND, AUTO.RTL and AUTO.PRECLAND.
LANDING_MODES = frozenset({"LAND", "RTL", "SMART_RTL", "AUTO_RTL", "AUTO.LAND", "AUTO.RTL", "AUTO.PRECLAND"})


def in_final_descent(state: Mapping[str, Any]) -> bool:
    """True if landed state is LANDING, or unknown while the mode is a landing mode."""
    landed = state.get("landed_state")
    if landed == "LANDING":
        return True
    if landed in (None, "UNDEFINED"):
        return state.get("mode") in LANDING_MODES
    return False
