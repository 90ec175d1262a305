"""Query parameters: the one check every backend (and the knowledge service) applies.

A parameter is a name of letters, digits and ``_`` (not starting with a
digit) and a graph value: None, a bool, a 64-bit integer, a finite float, a
string without NUL, or a list or string-keyed map of those, nested at most
:data:`MAX_DEPTH` deep. Anything else is refused before it reaches a store,
with an error naming the parameter: stores differ in what they do with the
rest (FalkorDB reads query text as a C string, so a NUL would cut a value;
inf and nan have no Cypher literal; the Bolt drivers refuse bytes), and a
batch must fail before its first statement, not half way.
"""

from __future__ import annotations

import math
import numbers
import re
from typing import Any, Mapping

from kgadapt.shared.errors import KgadaptError, QueryError

MAX_DEPTH = 8
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_INT64 = (-(2**63), 2**63)


def check_params(
    params: Mapping[Any, Any] | None, *, what: str = "", error: type[KgadaptError] = QueryError
) -> dict[str, Any]:
    """A plain copy of ``params`` (tuples as lists, numbers as int/float), or ``error`` naming what is wrong.

    ``what`` prefixes the messages (e.g. ``"query 'deployment'"``); the store
    raises :class:`QueryError`, the service :class:`MessageError`.
    """
    prefix = f"{what}: " if what else ""
    clean: dict[str, Any] = {}
    for name, value in (params or {}).items():
        if not isinstance(name, str) or not _NAME.match(name):
            raise error(f"{prefix}bad parameter name {name!r}: use letters, digits and _")
        clean[name] = _value(value, f"{prefix}parameter {name!r}", error, 0)
    return clean


def _value(value: Any, where: str, error: type[KgadaptError], depth: int) -> Any:
    if depth > MAX_DEPTH:
        raise error(f"{where}: nested more than {MAX_DEPTH} deep")
    # The built-in types first, by exact type: the ABC checks below (numbers, Mapping) cost several
    # times more, and a status batch's rows are a few hundred such values a statement.
    kind = type(value)
    if kind is float:
        if not math.isfinite(value):
            raise error(f"{where}: {value} is not a finite number")
        return value
    if kind is int:
        if not _INT64[0] <= value < _INT64[1]:
            raise error(f"{where}: {value} does not fit in 64 bits")
        return value
    if kind is dict:
        return _map(value, where, error, depth)
    if value is None or isinstance(value, (bool, str)):
        if isinstance(value, str) and "\x00" in value:
            raise error(f"{where}: a NUL character is not allowed in a string")
        return value
    if isinstance(value, numbers.Integral):  # int, and numpy's integers
        if not _INT64[0] <= int(value) < _INT64[1]:
            raise error(f"{where}: {value} does not fit in 64 bits")
        return int(value)
    if isinstance(value, numbers.Real):  # float, and numpy's floats
        if not math.isfinite(value):
            raise error(f"{where}: {value} is not a finite number")
        return float(value)
    if isinstance(value, (list, tuple)):
        return [_value(item, where, error, depth + 1) for item in value]
    if isinstance(value, Mapping):
        return _map(value, where, error, depth)
    raise error(f"{where}: a {type(value).__name__} is not a graph value")


def _map(value: Mapping[Any, Any], where: str, error: type[KgadaptError], depth: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, item in value.items():
        if not isinstance(key, str):
            raise error(f"{where}: map key {key!r} is not a string")
        out[key] = _value(item, where, error, depth + 1)
    return out


def cypher_literal(value: Any, *, name: str = "") -> str:
    """``value`` (a checked graph value) as Cypher text that FalkorDB and Memgraph read back unchanged.

    Written for an export script and for FalkorDB's ``CYPHER name=value`` parameter header.
    Strings are single-quoted with ``\\``, ``'``, newline, CR and tab escaped (FalkorDB reads
    no ``\\u`` escapes, and a script is split on newlines only, so other characters stay as they
    are); floats are written exactly, without a ``+`` in the exponent, which openCypher's grammar
    (and Memgraph's lexer) lacks; map keys are back-quoted, and may be neither empty nor hold a
    backquote, which FalkorDB cannot escape. Errors name the parameter ``name`` when given.
    """
    kind = type(value)
    if kind is float and math.isfinite(value):  # the common cases first, by exact type (as _value)
        return repr(value).replace("e+", "e")
    if kind is dict:
        return _map_literal(value, name)
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise QueryError(f"{_where(name)}: {value} is not a finite number")
        return repr(value).replace("e+", "e")  # shortest round trip: 0.1, 1e-07, 1e20
    if isinstance(value, str):
        # Five C-level replaces beat str.translate on the short strings parameters are.
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'").replace("\n", "\\n").replace(
            "\r", "\\r").replace("\t", "\\t") + "'"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join([cypher_literal(item, name=name) for item in value]) + "]"
    if isinstance(value, dict):
        return _map_literal(value, name)
    raise QueryError(f"{_where(name)}: a {type(value).__name__} is not a graph value")


def _map_literal(value: dict[Any, Any], name: str) -> str:
    for key in value:
        if not isinstance(key, str) or not key or "`" in key:
            raise QueryError(f"{_where(name)}: map key {key!r} cannot be written for FalkorDB "
                             "(empty, or with a backquote)")
    return "{" + ", ".join([f"`{key}`: {cypher_literal(item, name=name)}" for key, item in value.items()]) + "}"


def _where(name: str) -> str:
    return f"parameter {name!r}" if name else "value"
