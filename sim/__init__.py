"""Simulation: stand-ins for the world the robot software meets, for the demo, tests, benchmarks and dry runs.

The runtime never imports this package (tests/test_layers.py); it sits above the runtime and uses it.

* :mod:`.photos` — real photographs (``photographs/``) through perception's camera model
  (:mod:`kgadapt.onboard.perception.scene`, which also renders the synthetic scene);
* :mod:`.fake_fc` — a flight controller speaking ArduCopter's MAVLink over UDP;
* :mod:`.landing_scene` — a marker on the ground as the downward camera would see it;
* :mod:`.landing_check` — one precision landing flown end to end on the fake flight controller or SITL;
* :mod:`.echo_detector` — a detector process that answers every frame with empty detections;
* :mod:`.cli` — ``kgadapt flight fake-fc`` and ``kgadapt flight land-check`` (the command registry).
"""
