"""The one exception tree of kgadapt.

Every error a caller can act on is one of these; each library's own
exceptions (redis, neo4j, zenoh, pymavlink, OSError) are
translated at the boundary where we call it, with ``raise ... from exc``.

    KgadaptError
     ├── ConfigError              bad settings: a store URL, a Zenoh config file, a flag
     │    └── MissingExtra        the command needs an optional part that is not installed
     ├── ModelError               a domain model file is malformed (names file and line)
     ├── StoreError               the graph store failed
     │    ├── StoreUnavailable    cannot start, reach or connect to the store
     │    ├── QueryError          the store rejected a query (syntax, runtime)
     │    │    ├── StoreTimeout   the store itself stopped the query at its timeout_ms
     │    │    └── QueryTimeLimit past its hard limit: abandoned (its server killed where ours)
     │    └── ReadOnlyViolation   a write was sent through a read-only path
     ├── NamedQueryError          unknown named query, missing or ill-typed parameter
     │    └── UnknownHost         a write, status or token names a host no model names
     ├── MessageError             a wire message is malformed, of an unknown version, or too big
     ├── TransportError           Zenoh failed (open, declare, get)
     │    └── RequestTimeout      no (good) reply in time
     │         └── NoResponder    nobody serves the key: the request ended without a reply
     ├── RemoteError              the far side answered a request with an error reply
     ├── DeploymentError          the deployer refused or failed a start, stop or migration
     │    └── NotReady            a child exited before it said it was ready (shared/readiness)
     │         └── ReadinessTimeout   ... or did not say so in time
     └── FlightLinkError          the MAVLink link could not be opened or used
"""

from __future__ import annotations


class KgadaptError(Exception):
    """Base of every error kgadapt raises on purpose."""


class ConfigError(KgadaptError):
    """A setting, URL, flag or configuration file is wrong."""


class MissingExtra(ConfigError):
    """A command needs an optional part of kgadapt (an extra) that is not installed."""

    def __init__(self, extra: str, what: str, module: str) -> None:
        self.extra = extra
        self.module = module
        super().__init__(
            f"{what} needs the '{extra}' extra (module {module!r} is not installed): "
            f"pip install 'kgadapt[{extra}]'"
        )


class ModelError(KgadaptError):
    """A domain model file is malformed.

    ``str(error)`` reads ``FILE:LINE: what is wrong`` so editors can jump to it.
    """

    def __init__(self, path: str, line: int | None, message: str) -> None:
        self.path = str(path)
        self.line = line
        self.message = message
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")


class StoreError(KgadaptError):
    """The graph store failed."""


class StoreUnavailable(StoreError):
    """The store could not be started, reached or connected to."""


class QueryError(StoreError):
    """The store rejected a query."""


class StoreTimeout(QueryError):
    """The store itself stopped a query at the ``timeout_ms`` it was given (every backend that has timeouts)."""


class QueryTimeLimit(QueryError):
    """A query ran past its hard time limit and was abandoned (its server killed where we own it)."""


class ReadOnlyViolation(StoreError):
    """A write was attempted through a read-only path."""


class NamedQueryError(KgadaptError):
    """A named query does not exist, or its parameters are missing or ill-typed."""


class UnknownHost(NamedQueryError):
    """A run-time fact names a host that no model names: only the models add Platforms."""

    def __init__(self, host: str, message: str) -> None:
        self.host = host
        super().__init__(message)


class MessageError(KgadaptError):
    """A wire message is malformed, of an unknown version, or oversized."""


class TransportError(KgadaptError):
    """Zenoh failed: opening a session, declaring, or querying."""


class RequestTimeout(TransportError):
    """No reply (or no good reply) arrived in time."""


class NoResponder(RequestTimeout):
    """The request ended without any reply: no queryable serves its key (or none is known yet)."""


class RemoteError(KgadaptError):
    """The far side of a request answered with an error reply."""


class DeploymentError(KgadaptError):
    """The deployer refused or failed to start, stop or migrate a process."""


class NotReady(DeploymentError):
    """A started process did not become ready: it ended first (or, as ReadinessTimeout, took too long)."""


class ReadinessTimeout(NotReady):
    """A started process did not say it was ready within its timeout."""


class SourceNotStopped(DeploymentError):
    """A migration's new instance runs and detects, but its source could not be stopped.

    ``report`` is the migration's report (``source_returncode`` None); the source
    is a twin to stop once its host answers again.
    """

    def __init__(self, message: str, *, report: object) -> None:
        super().__init__(message)
        self.report = report


class FlightLinkError(KgadaptError):
    """The MAVLink link to the flight controller could not be opened or used."""
