"""``python -m kgadapt.onboard.perception.config_check``: OpenCV's verdict on detector configurations, for the model loader.

Loading models must not load OpenCV (the knowledge service and ``kgadapt
knowledge load`` run where no camera is), yet a configuration OpenCV would
refuse should fail at load time with its file and line, not when a detector
starts. So the loader (``knowledge/importers/rpsl.py``) asks this program, in a
process of its own, what the detector program would say at start
(:func:`kgadapt.onboard.perception.markers.parse_config`, then one detection of a real marker).

Input on stdin: a JSON list of ``{"name": ..., "config_json": ...}``. Output
on stdout: a JSON list, one entry per configuration: ``null`` when OpenCV takes
it, else ``{"at": "dictionary" | "parameter" | "detector", "key": ..., "message": ...}``
(``at`` tells the loader which statement to name).
"""

from __future__ import annotations

import json
import sys
from typing import Any


def verdict(name: str, config_json: str) -> dict[str, Any] | None:
    """None if the detector program would start with this configuration, else what OpenCV refuses."""
    import cv2
    import numpy as np

    from kgadapt.onboard.perception.markers import MarkerDetector, aruco_dictionary, parse_config
    from kgadapt.shared.errors import ConfigError
    from kgadapt.shared.preprocessing import is_dictionary_file

    data = json.loads(config_json)
    dictionary = data.get("dictionary")
    if isinstance(dictionary, str) and is_dictionary_file(dictionary):
        try:
            found = aruco_dictionary(dictionary)
        except ConfigError as exc:
            return {"at": "dictionary", "key": dictionary, "message": str(exc)}
    elif not isinstance(getattr(cv2.aruco, str(dictionary), None), int):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int))
        return {"at": "dictionary", "key": dictionary,
                "message": f"dictionary {dictionary!r} is not one of OpenCV's ArUco dictionaries "
                           f"({', '.join(known[:4])}, ... {len(known)} in all) nor a dictionary file (.yml)"}
    else:
        found = aruco_dictionary(dictionary)
    attributes = {a for a in dir(cv2.aruco.DetectorParameters()) if not a.startswith("_")}
    for key in data.get("parameters") or {}:
        if key not in attributes:
            return {"at": "parameter", "key": key,
                    "message": f"parameter {key!r} is not an attribute of cv2.aruco.DetectorParameters"}
    try:
        detector = MarkerDetector(parse_config(name, config_json))
        marker = cv2.aruco.generateImageMarker(found, 0, 40)
        detector.detect(np.pad(marker, 12, constant_values=255))  # a real marker: the full detection path runs
    except ConfigError as exc:
        return {"at": "detector", "key": None, "message": str(exc)}
    except cv2.error as exc:
        why = f"({exc.code}) {exc.err}"  # OpenCV's own reason and code, without its file and line
        return {"at": "detector", "key": None, "message": f"{name}: OpenCV refuses these detector parameters: {why}"}
    return None


def main() -> int:
    configs = json.load(sys.stdin)
    json.dump([verdict(c["name"], c["config_json"]) for c in configs], sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
