"""Simulation: stand-ins for the world the robot software meets, for the demo, tests, benchmarks and dry runs.

* :mod:`.scenario` — the synthetic camera scene under an illumination profile
  (``scenarios/`` holds the shipped profiles) and the camera model that exposes it;
* :mod:`.photos` — real photographs (``photographs/``) through the same camera model;
* :mod:`.fake_fc` — a flight controller speaking ArduCopter's MAVLink over UDP;
* :mod:`.landing_scene` — a marker on the ground as the downward camera would see it;
* :mod:`.echo_detector` — a detector process that answers every frame with empty detections.
"""
