"""Zenoh session configuration: a JSON5 file, then environment, then flags.

Precedence, lowest first: Zenoh's defaults, our defaults (multicast scouting
off; a 1 s lease on hosts, so a hung or cut-off host is noticed within about a
second, and 4 s on routers, see ``ROUTER_LEASE_MS``; 4 keep-alives a lease; no
scouting delay; shared memory off), the JSON5 file given with ``--zenoh-config``
or ``$KGADAPT_ZENOH_CONFIG`` (each of our defaults applies only where the file
says nothing), then
``$KGADAPT_ZENOH_MODE`` / ``_CONNECT`` / ``_LISTEN`` and the flags ``--mode``,
``--connect``, ``--listen``. Sections we do not set (TLS under
``transport/link/tls``, ``access_control``, auth) pass through untouched.

Default on one machine: the knowledge service opens in router mode and
listens on ``tcp/127.0.0.1:7447``; the agents are peers that connect to it
and listen on loopback only (``LOOPBACK_LISTEN``), never on every interface.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from dataclasses import dataclass, field, replace
from typing import Sequence

import pyjson5
import zenoh

from kgadapt.shared.errors import ConfigError, TransportError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
# Where a peer listens when nothing says otherwise. Zenoh's own default is every
# interface (tcp/[::]:0), which let anyone on the network talk to an agent or a
# detector directly, past the router's access control: the router is the one door.
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
MODES = ("peer", "client", "router")
# Each side of a Zenoh link sends keep-alives for its *own* lease (one every lease / keep_alive when it has
# sent nothing else) and drops the link after the *other* side's lease (Zenoh's universal transport). So
# a router finds a hung or cut-off host within the host's lease, whatever its own. A router's own lease
# says only how soon its clients notice it gone, and without their router they can reach nothing anyway.
# At 1 s a router sent every host four keep-alives a second, more messages than the host's statuses at
# 2 Hz: measured, 330 host links to one router process of 33 services, its CPU 8.3-10.2 % of a core at
# 1 s, 6.7-7.4 % at 4 s and 6.8-6.9 % at 10 s (docs/fleet.md, eleventh round).
HOST_LEASE_MS = 1000
ROUTER_LEASE_MS = 4000


@dataclass(frozen=True, kw_only=True)
class ZenohSettings:
    """How to open a Zenoh session. Empty tuples mean "leave the file's (or Zenoh's) value"."""

    config_file: str | None = None
    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    # multicast_scouting, lease_ms, keep_alive, scouting_delay_ms and shared_memory are our defaults: each
    # applies only where the config file says nothing (flags and extra win over the file).
    multicast_scouting: bool = False
    lease_ms: int | None = None  # None: ROUTER_LEASE_MS for a router (by mode or the file's), HOST_LEASE_MS else
    keep_alive: int = 4
    # Zenoh waits this long in open() for scouting answers (default 500 ms, measured
    # here for routers and gossiping peers); our endpoints are explicit, so none.
    scouting_delay_ms: int | None = 0
    # Zenoh 1.x enables shared memory by default: a client on the same machine
    # negotiates it and puts every message above 3 KiB into a 16 MiB pool that
    # the router maps. When that client dies by kill -9 the router keeps the
    # mapping for good: measured 19 MiB of router RSS per onboard agent restart.
    # Our hosts talk over TCP/TLS anyway, so it is off unless the config file
    # sets transport/shared_memory itself (None: leave Zenoh's value).
    shared_memory: bool | None = False
    exit_on_failure: bool | None = None
    connect_timeout_ms: int | None = None
    # Zenoh's runtime threads (its ZENOH_RUNTIME, in RON). Zenoh reads them once per process, at the first
    # open, so the first session's value holds for the process; $ZENOH_RUNTIME wins. None: ZENOH_RUNTIME
    # below; the knowledge service's router uses SERVICE_RUNTIME.
    runtime: str | None = None
    extra: dict[str, object] = field(default_factory=dict)  # key path -> JSON value

    def with_defaults(self, *, mode: str, connect: Sequence[str] = (), listen: Sequence[str] = ()) -> "ZenohSettings":
        """Fill mode and endpoints that neither file nor flags nor environment set."""
        return replace(
            self,
            # A config file's own mode wins over our default (flags and env still win over the file).
            mode=self.mode or (None if self.config_file else mode),
            connect=self.connect or (() if self.config_file else tuple(connect)),
            listen=self.listen or (() if self.config_file else tuple(listen)),
        )


def settings_from_env(**overrides: object) -> ZenohSettings:
    """Settings from ``$KGADAPT_ZENOH_*``, then ``overrides`` (None values ignored)."""
    env = os.environ
    values: dict[str, object] = {
        "config_file": env.get("KGADAPT_ZENOH_CONFIG") or None,
        "mode": env.get("KGADAPT_ZENOH_MODE") or None,
        "connect": _split(env.get("KGADAPT_ZENOH_CONNECT")),
        "listen": _split(env.get("KGADAPT_ZENOH_LISTEN")),
    }
    values.update({k: v for k, v in overrides.items() if v not in (None, (), [])})
    for key in ("connect", "listen"):
        values[key] = tuple(values[key])  # type: ignore[arg-type]  # _split and the flags give sequences of str
    return ZenohSettings(**values)  # type: ignore[arg-type]  # the keys and kinds written just above


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--zenoh-config``, ``--mode``, ``--connect``, ``--listen`` to a command."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file (TLS, ACL, endpoints)")
    group.add_argument("--mode", choices=MODES, help="Zenoh session mode")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")


def settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    return settings_from_env(
        config_file=getattr(args, "zenoh_config", None),
        mode=getattr(args, "mode", None),
        connect=tuple(getattr(args, "connect", None) or ()),
        listen=tuple(getattr(args, "listen", None) or ()),
    )


def build_config(settings: ZenohSettings) -> zenoh.Config:
    """Make the ``zenoh.Config``; raise ConfigError naming a bad file or value."""
    if settings.config_file:
        try:
            config = zenoh.Config.from_file(settings.config_file)
        except Exception as exc:  # zenoh.ZError, OSError
            raise ConfigError(f"Zenoh config {settings.config_file}: {exc}") from exc
    else:
        config = zenoh.Config()
    if settings.mode is not None and settings.mode not in MODES:
        raise ConfigError(f"Zenoh mode {settings.mode!r}: use one of {', '.join(MODES)}")
    lease_ms = settings.lease_ms
    if lease_ms is None:
        lease_ms = ROUTER_LEASE_MS if (settings.mode or _mode_of(config)) == "router" else HOST_LEASE_MS
    defaults: dict[str, object] = {
        "scouting/multicast/enabled": settings.multicast_scouting,
        "transport/link/tx/lease": lease_ms,
        "transport/link/tx/keep_alive": settings.keep_alive,
    }
    if settings.scouting_delay_ms is not None:
        defaults["scouting/delay"] = settings.scouting_delay_ms
    if settings.shared_memory is not None:
        defaults["transport/shared_memory/enabled"] = settings.shared_memory
    written = _file_tree(settings.config_file)
    inserts = {key: value for key, value in defaults.items() if not _sets(written, key)}
    if settings.mode:
        inserts["mode"] = settings.mode
    if settings.connect:
        inserts["connect/endpoints"] = list(settings.connect)
    if settings.listen:
        inserts["listen/endpoints"] = list(settings.listen)
    elif not settings.config_file and (settings.mode or "peer") == "peer":
        inserts["listen/endpoints"] = [LOOPBACK_LISTEN]
    if settings.exit_on_failure is not None:
        inserts["connect/exit_on_failure"] = settings.exit_on_failure
    if settings.connect_timeout_ms is not None:
        inserts["connect/timeout_ms"] = settings.connect_timeout_ms
    inserts.update(settings.extra)
    for key, value in inserts.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh's errors (ZError, ValueError): translated here
            raise ConfigError(f"Zenoh config key {key!r} = {value!r}: {exc}") from exc
    return config


# Zenoh closes a dead TCP link with a 10 s SO_LINGER, blocking one thread of its
# receive runtime in close(). Measured in the partition tests: a host cut off with
# two links (agent and detector) blocked both default threads, and the router then
# routed nothing until the link came back. More receive threads keep it routing.
# Zenoh reads this when its runtime starts, i.e. at the first open(); the only way
# to set it is the environment, so it is set here, once, unless the user chose.
ZENOH_RUNTIME = "(rx: (worker_threads: 8))"
# The knowledge service's router, which receives every host's statuses (2 Hz each) as separate messages:
# a link accepted by Zenoh's accept runtime stays registered with that runtime's reactor, so each message
# woke the acc thread, which woke an rx thread to read it (two wake-ups a message). Handed over to the
# receive runtime, one rx thread is woken and reads it. Measured (33 services, 330 hosts at 2 Hz, one
# router process): 8.2 % of a core against 11.5-13.0 %, the 8 rx threads kept for the reason above.
SERVICE_RUNTIME = "(rx: (worker_threads: 8), acc: (handover: rx))"
_RUNTIME_SET_BY_US = "KGADAPT_ZENOH_RUNTIME_DEFAULT"  # the value of $ZENOH_RUNTIME that we set, not the user


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a session; raise TransportError (or ConfigError) on failure."""
    _choose_runtime(settings.runtime or ZENOH_RUNTIME)
    config = build_config(settings)
    try:
        session = zenoh.open(config)
    except Exception as exc:  # whatever zenoh raises: translated here
        raise TransportError(
            f"cannot open Zenoh session (mode {settings.mode}, connect {list(settings.connect)}, "
            f"listen {list(settings.listen)}): {exc}"
        ) from exc
    log.debug("zenoh session %s open (mode %s)", session.info.zid(), settings.mode)
    return session


def _choose_runtime(wanted: str) -> None:
    """Set $ZENOH_RUNTIME to ``wanted`` unless the user set it. A value we set ourselves is marked, so that
    a child (e.g. a knowledge service started by a process with a session open) does not take the
    parent's inherited default for the user's choice."""
    env = os.environ
    current = env.get("ZENOH_RUNTIME")
    if current is None or current == env.get(_RUNTIME_SET_BY_US):
        env["ZENOH_RUNTIME"] = env[_RUNTIME_SET_BY_US] = wanted
    if env["ZENOH_RUNTIME"] != wanted:
        log.debug("ZENOH_RUNTIME %s holds for this process (asked for %s)", env["ZENOH_RUNTIME"], wanted)


def _mode_of(config: zenoh.Config) -> str:
    """The mode a configuration (a file's, or Zenoh's default) sets."""
    try:
        return str(json.loads(config.get_json("mode")))
    except Exception as exc:  # zenoh's errors: translated here
        raise ConfigError(f"Zenoh config: cannot read its mode: {exc}") from exc


def _file_tree(path: str | None) -> dict[str, object]:
    """What the config file itself says (Zenoh read it above, so it exists), without Zenoh's defaults.

    Read with pyjson5 (a C parser: 0.1 ms for the shipped router file, where the pure-Python json5
    takes 100 ms of every process start). Zenoh also reads YAML files; we take JSON5 only, so that
    what the file says is known and is never overridden by our defaults.
    """
    if not path:
        return {}
    if not path.endswith((".json5", ".json")):
        raise ConfigError(f"Zenoh config {path}: give a JSON5 file (.json5 or .json)")
    try:
        with open(path, encoding="utf-8") as handle:
            tree: dict[str, object] = pyjson5.loads(handle.read())
    except (OSError, pyjson5.Json5Exception) as exc:
        raise ConfigError(f"Zenoh config {path}: {exc}") from exc
    return tree  # an object: Zenoh refused anything else above


def _sets(tree: dict[str, object], key: str) -> bool:
    """Whether ``tree`` (a config file's own content) names ``key`` (a path such as ``transport/link/tx/lease``)."""
    node: object = tree
    for part in key.split("/"):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def _split(value: str | None) -> tuple[str, ...]:
    return tuple(v.strip() for v in (value or "").split(",") if v.strip())
