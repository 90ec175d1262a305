"""OpenCV's verdict on detector configurations, asked without loading OpenCV here.

The model loader runs where no camera is (the knowledge service, ``kgadapt
knowledge load``) and must not import OpenCV; yet a configuration OpenCV
would refuse should fail at load time with its file and line. So the
configurations go to :mod:`kgadapt.onboard.perception.config_check` in a child process, which
answers what the detector program would say at start.

A child costs an interpreter and an OpenCV import (~0.3 s idle, seconds on a
busy machine), and the same models are loaded again and again (every agent
start, every test cluster), so verdicts are kept: in this process, and on disk
under ``$XDG_CACHE_HOME/kgadapt/detector-verdicts/``, keyed by the
configuration, the OpenCV build (its file's path, size and time) and the
source of the checking code, so a new OpenCV or a changed check asks again.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from kgadapt.shared.errors import ModelError
from kgadapt.shared.preprocessing import is_dictionary_file

log = logging.getLogger(__name__)

Verdict = dict[str, Any] | None
# What the verdict depends on besides the configuration: the checking program and what it imports.
_CHECK_MODULES = (
    "kgadapt.onboard.perception.config_check", "kgadapt.onboard.perception.markers", "kgadapt.shared.preprocessing",
)
_memory: dict[str, Verdict] = {}


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(Path.home(), ".cache")
    return Path(base) / "kgadapt" / "detector-verdicts"


def verdicts(configs: list[tuple[str, str]], path: str) -> list[Verdict]:
    """One verdict per ``(name, config_json)``: None when OpenCV takes it (or is not installed here)."""
    if not configs:
        return []
    opencv = importlib.util.find_spec("cv2")
    if opencv is None or not opencv.origin:
        return [None] * len(configs)  # no OpenCV here: the detector program checks at start
    identity = _identity(opencv.origin)
    keys = [hashlib.sha256(json.dumps([identity, name, config, _dictionary_file(config)]).encode()).hexdigest()
            for name, config in configs]
    for key in keys:
        if key not in _memory:
            found = _read(key)
            if found is not None:
                _memory[key] = found[0]
    unknown = [(key, config) for key, config in zip(keys, configs) if key not in _memory]
    if unknown:
        asked = dict(unknown)  # one question per distinct configuration
        for key, verdict in zip(asked, _ask(list(asked.values()), path)):
            _memory[key] = verdict
            _write(key, verdict)
    return [_memory[key] for key in keys]


def _identity(opencv_origin: str) -> list[Any]:
    stat = os.stat(opencv_origin)
    digest = hashlib.sha256()
    for module in _CHECK_MODULES:
        spec = importlib.util.find_spec(module)
        if spec is not None and spec.origin:
            digest.update(Path(spec.origin).read_bytes())
    return [opencv_origin, stat.st_size, stat.st_mtime_ns, digest.hexdigest()]


def _dictionary_file(config: str) -> str | None:
    """A digest of the dictionary file a configuration names: a changed file is asked about again."""
    try:
        name = json.loads(config).get("dictionary")
    except (ValueError, AttributeError):
        return None
    if not isinstance(name, str) or not is_dictionary_file(name):
        return None
    try:
        return hashlib.sha256(Path(name).read_bytes()).hexdigest()
    except OSError:
        return "unreadable"


def _read(key: str) -> tuple[Verdict] | None:
    try:
        return (json.loads((cache_dir() / f"{key}.json").read_text())["verdict"],)
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write(key: str, verdict: Verdict) -> None:
    directory = cache_dir()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=directory, suffix=".tmp")
        with os.fdopen(fd, "w") as out:
            json.dump({"verdict": verdict}, out)
        os.replace(tmp, directory / f"{key}.json")  # whole or absent, with concurrent loaders
    except OSError as exc:
        log.debug("cannot keep a detector verdict in %s: %s", directory, exc)


def _ask(configs: list[tuple[str, str]], path: str) -> list[Verdict]:
    request = json.dumps([{"name": name, "config_json": config} for name, config in configs])
    try:
        done = subprocess.run([sys.executable, "-m", "kgadapt.onboard.perception.config_check"], input=request,
                              capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ModelError(path, None, f"cannot check the detector configurations with OpenCV: {exc}") from exc
    try:
        answer = json.loads(done.stdout) if done.returncode == 0 else None
    except ValueError:
        answer = None
    if not isinstance(answer, list) or len(answer) != len(configs):
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise ModelError(path, None, f"cannot check the detector configurations with OpenCV "
                                     f"(kgadapt.onboard.perception.config_check exited {done.returncode}: {last})")
    return answer


def dictionary_verdicts(names: list[str], path: str) -> dict[str, tuple[str | None, int | None]]:
    """OpenCV's verdict on ArUco dictionary names (a site's): name -> (problem or None, ids it holds or None).

    Asked of ``python -m kgadapt.onboard.flight.site`` (which calls kgadapt.onboard.perception.markers.aruco_dictionary);
    verdicts on predefined names are kept like the detector verdicts, custom dictionary files never
    (their content may change under the same name).
    """
    if not names:
        return {}
    opencv = importlib.util.find_spec("cv2")
    if opencv is None or not opencv.origin:
        return {name: (None, None) for name in names}  # no OpenCV on this host: nothing to ask (as for detectors)
    site_module = importlib.util.find_spec("kgadapt.onboard.flight.site")
    digest = hashlib.sha256(Path(site_module.origin).read_bytes()).hexdigest() if site_module and site_module.origin else ""
    identity = [*_identity(opencv.origin), digest]
    keys = {name: hashlib.sha256(json.dumps([identity, "dictionary", name]).encode()).hexdigest() for name in names}
    out: dict[str, tuple[str | None, int | None]] = {}
    for name, key in keys.items():
        if not name.startswith("DICT_"):
            continue
        if key not in _memory:
            found = _read(key)
            if found is not None:
                _memory[key] = found[0]
        kept: Any = _memory.get(key)
        if isinstance(kept, list) and len(kept) == 2:
            out[name] = (None if kept[0] is None else str(kept[0]), kept[1] if isinstance(kept[1], int) else None)
    unknown = [name for name in names if name not in out]
    if unknown:
        try:
            done = subprocess.run([sys.executable, "-m", "kgadapt.onboard.flight.site"], input=json.dumps(unknown),
                                  capture_output=True, text=True, timeout=120)
            answer = json.loads(done.stdout) if done.returncode == 0 else None
        except (OSError, subprocess.TimeoutExpired, ValueError) as exc:
            raise ModelError(path, None, f"cannot check the site's dictionaries with OpenCV: {exc}") from exc
        if not isinstance(answer, dict) or set(answer) != set(unknown):
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            raise ModelError(path, None, f"cannot check the site's dictionaries with OpenCV "
                                         f"(kgadapt.onboard.flight.site exited {done.returncode}: {last})")
        for name in unknown:
            problem, count = answer[name]
            out[name] = (None if problem is None else str(problem), count if isinstance(count, int) else None)
            if name.startswith("DICT_"):
                _memory[keys[name]] = [problem, count]  # type: ignore[assignment]
                _write(keys[name], [problem, count])  # type: ignore[arg-type]
    return out
