"""Which phase of flight a ``flight_state`` message says the vehicle is in, on the safe side.

The adaptation manager defers planned changes during the final descent. The
autopilot's landed state says so directly (LANDING); when it is unknown (its
stream stopped, an autopilot reboot, or the autopilot never sends it) a landing
mode counts as final descent, and so does a landing mode below 10 m whatever the
landed state: deferring a change is cheap, losing the detector over the pad is not.
"""

from __future__ import annotations

from typing import Any, Mapping

from kgadapt.shared import messages

# ArduCopter's LAND and RTL (whose last phase is a landing), PX4's AUTO.LAND, AUTO.RTL and AUTO.PRECLAND.
LANDING_MODES = frozenset({"LAND", "RTL", "SMART_RTL", "AUTO_RTL", "AUTO.LAND", "AUTO.RTL", "AUTO.PRECLAND"})


LOW_ALT_M = 10.0  # ArduCopter's LAND_ALT_LOW: below it a landing mode descends slowly, over the pad


def in_final_descent(state: Mapping[str, Any] | messages.FlightState, *, low_alt_m: float = LOW_ALT_M) -> bool:
    """True if landed state is LANDING; or, in a landing mode, if it is unknown or the vehicle is low.

    Low = ``alt_rel_m`` at or below ``low_alt_m``: RTL's return at altitude is not the final
    descent, its last ten metres are, whatever the landed state says.
    """
    if isinstance(state, messages.FlightState):
        landed, mode, alt = state.landed_state, state.mode, state.alt_rel_m
    else:  # a graph row (FlightControl's properties)
        landed, mode, alt = state.get("landed_state"), state.get("mode"), state.get("alt_rel_m")
    if landed == "LANDING":
        return True
    if landed == "ON_GROUND" or mode not in LANDING_MODES:
        return False
    if landed in (None, "UNDEFINED"):
        return True
    return isinstance(alt, (int, float)) and alt <= low_alt_m
