"""Perception: what the camera sees and how markers are found in it.

* :mod:`.scene` — the synthetic scene (markers under changing light, its camera model) that
  calibration renders and the ``synthetic:`` camera shows; ``scenarios/`` holds its illumination profiles.
"""
