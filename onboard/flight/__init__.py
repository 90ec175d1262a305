"""Flight: the link to the flight controller and what the vehicle is told to land on.

* :mod:`.mavlink` — the MAVLink link (our own transport, MAVLink 2); :mod:`.mavlink_commands` — its acknowledged commands;
* :mod:`.flight` — the flight bridge (detections in, LANDING_TARGET out, flight state back);
  :mod:`.flight_cli` — ``kgadapt flight``;
* :mod:`.confirmation`, :mod:`.site`, :mod:`.landing_targets`, :mod:`.geometry` — which markers count, where
  they are, the target in the autopilot's frame;
* :mod:`.flight_phase` — which phase of flight the vehicle is in, on the safe side.
"""
