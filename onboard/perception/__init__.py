"""Perception: what the camera sees and how markers are found in it.

* :mod:`.camera` — camera sources and the camera part; :mod:`.illumination` — luminance, smoothing, bands;
* :mod:`.markers` — the detection core (configuration, pre-processing, ArUco); :mod:`.detector` — the detector
  program the deployer runs, with its :mod:`.reflex` table; :mod:`.config_check` — OpenCV's verdict on configurations;
* :mod:`.calibration` and :mod:`.recorded_calibration` — how each configuration does per band, on synthetic or recorded frames;
* :mod:`.perception_cli` — ``kgadapt perception``;
* :mod:`.scene` — the synthetic scene (markers under changing light, its camera model) that
  calibration renders and the ``synthetic:`` camera shows; ``scenarios/`` holds its illumination profiles.
"""
