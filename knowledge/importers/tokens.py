"""A small line lexer shared by the block notations (perception graphs, platforms, features).

It reads one line into values: bare words, ``"strings"`` (``\\"``, ``\\\\``,
``\\n``, ``\\t`` escapes; single quotes too), numbers, Ruby-style ``:symbols``,
``key:`` option names, ``,`` separators and the AADL arrow ``=>``. ``#`` and
``--`` start a comment. It never evaluates anything.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from kgadapt.knowledge.importers.model import Origin


class Symbol(str):
    """A Ruby-style ``:symbol`` (kept apart from strings: ``:out`` is a keyword, ``"out"`` a name)."""


class Word(str):
    """A bare word (a keyword, or a name written without quotes)."""


@dataclass(frozen=True)
class Token:
    kind: str  # word | string | number | symbol | key | comma | arrow | semicolon
    value: Any
    column: int


@dataclass
class Statement:
    """``keyword arg, arg, key: value`` or ``keyword => value`` on one line."""

    keyword: str
    args: list[Any]
    options: dict[str, Any]
    origin: Origin
    arrow: bool = False
    option_order: list[str] = field(default_factory=list)


_NUMBER = re.compile(r"[-+]?(\d+\.\d*|\.\d+|\d+)([eE][-+]?\d+)?(?![A-Za-z0-9_.])")
_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")
_ESCAPES = {"n": "\n", "t": "\t", "\\": "\\", '"': '"', "'": "'"}


def tokenize(text: str, origin: Origin) -> list[Token]:
    """Split one line into tokens; raise ModelError at ``origin`` on a character it cannot read."""
    tokens: list[Token] = []
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        col = i + 1
        if ch in " \t\r":
            i += 1
        elif ch == "#" or text.startswith("--", i):
            break
        elif ch in "\"'":
            value, i = _string(text, i, origin)
            tokens.append(Token("string", value, col))
        elif text.startswith("=>", i):
            tokens.append(Token("arrow", "=>", col))
            i += 2
        elif ch == ",":
            tokens.append(Token("comma", ",", col))
            i += 1
        elif ch == ";":
            tokens.append(Token("semicolon", ";", col))
            i += 1
        elif ch == ":" and i + 1 < n and (symbol := _WORD.match(text, i + 1)):
            tokens.append(Token("symbol", Symbol(symbol.group()), col))
            i = symbol.end()
        elif (m := _NUMBER.match(text, i)) and (ch.isdigit() or ch in "+-." ):
            literal = m.group()
            number: float = float(literal) if any(c in literal for c in ".eE") else int(literal)
            tokens.append(Token("number", number, col))
            i = m.end()
        elif m := _WORD.match(text, i):
            word = m.group()
            i = m.end()
            if i < n and text[i] == ":" and not text.startswith("::", i):
                tokens.append(Token("key", word, col))
                i += 1
            else:
                tokens.append(Token("word", Word(word), col))
        else:
            raise origin.error(f"unexpected character {ch!r} at column {col}")
    return tokens


def _string(text: str, start: int, origin: Origin) -> tuple[str, int]:
    quote = text[start]
    out: list[str] = []
    i = start + 1
    while i < len(text):
        ch = text[i]
        if ch == "\\":
            if i + 1 >= len(text) or text[i + 1] not in _ESCAPES:
                raise origin.error(f"unknown escape in string at column {i + 1}")
            out.append(_ESCAPES[text[i + 1]])
            i += 2
        elif ch == quote:
            return "".join(out), i + 1
        else:
            out.append(ch)
            i += 1
    raise origin.error(f"string opened at column {start + 1} is not closed")


def statement(tokens: list[Token], origin: Origin) -> Statement:
    """Group a line's tokens into a statement (the first token must be a word)."""
    first = tokens[0]
    if first.kind != "word":
        raise origin.error(f"a statement starts with a keyword, not {_show(first)}")
    rest = list(tokens[1:])
    while rest and rest[-1].kind == "semicolon":
        rest.pop()
    arrow = bool(rest) and rest[0].kind == "arrow"
    if arrow:
        rest = rest[1:]
    args: list[Any] = []
    options: dict[str, Any] = {}
    order: list[str] = []
    expect_value = True
    i = 0
    while i < len(rest):
        tok = rest[i]
        if tok.kind == "comma":
            if expect_value:
                raise origin.error(f"unexpected ',' at column {tok.column}")
            expect_value = True
            i += 1
            continue
        if tok.kind == "key":
            if i + 1 >= len(rest) or rest[i + 1].kind not in ("word", "string", "number", "symbol"):
                raise origin.error(f"option {tok.value!r} has no value")
            if tok.value in options:
                raise origin.error(f"option {tok.value!r} given twice")
            options[tok.value] = _value(rest[i + 1])
            order.append(tok.value)
            i += 2
        elif tok.kind in ("word", "string", "number", "symbol"):
            if options:
                raise origin.error(f"positional value {_show(tok)} after options")
            args.append(_value(tok))
            i += 1
        else:
            raise origin.error(f"unexpected {_show(tok)}")
        expect_value = False
    if rest and expect_value:
        raise origin.error("statement ends with ','")
    return Statement(str(first.value), args, options, origin, arrow, order)


def _value(tok: Token) -> Any:
    if tok.kind == "word" and tok.value in ("true", "false"):
        return tok.value == "true"
    return tok.value


def _show(tok: Token) -> str:
    return f"{tok.value!r} (column {tok.column})"


def read_statements(text: str, path: str) -> list[Statement]:
    """Every non-empty line of ``text`` as a statement."""
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        origin = Origin(path, number)
        tokens = tokenize(line, origin)
        if tokens:
            out.append(statement(tokens, origin))
    return out


# --- typed argument access, each failing with the statement's file and line ---

def expect_args(st: Statement, count: int, usage: str, *, options: tuple[str, ...] = ()) -> None:
    """Exactly ``count`` positional values and only the listed options."""
    if len(st.args) != count:
        raise st.origin.error(f"{st.keyword}: expected {usage}")
    for key in st.options:
        if key not in options:
            allowed = ", ".join(options) or "none"
            raise st.origin.error(f"{st.keyword}: unknown option {key!r} (allowed: {allowed})")


def name_arg(st: Statement, value: Any, what: str = "name") -> str:
    """A name: a string or a bare word, non-empty, without quotes or backslashes."""
    if isinstance(value, bool) or not isinstance(value, str) or isinstance(value, Symbol):
        raise st.origin.error(f"{st.keyword}: {what} must be a string or a word, not {value!r}")
    if not value.strip():
        raise st.origin.error(f"{st.keyword}: {what} is empty")
    if any(c in value for c in "'\\\n\"/") or value != value.strip():
        raise st.origin.error(f"{st.keyword}: {what} {value!r} may not contain quotes, slashes, "
                              "backslashes or surrounding spaces")
    return str(value)


def text_arg(st: Statement, value: Any, what: str = "text") -> str:
    """Free text (descriptions). Quotes and backslashes are refused: some Bolt servers splice them."""
    if isinstance(value, bool) or not isinstance(value, str):
        raise st.origin.error(f"{st.keyword}: {what} must be a string, not {value!r}")
    if "'" in value or "\\" in value:
        raise st.origin.error(f"{st.keyword}: {what} may not contain ' or \\")
    return str(value)


def number_arg(st: Statement, value: Any, what: str, *, minimum: float | None = 0.0,
               positive: bool = False, integer: bool = False) -> float | int:
    """A number, checked against its range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise st.origin.error(f"{st.keyword}: {what} must be a number, not {value!r}")
    if integer and not isinstance(value, int):
        raise st.origin.error(f"{st.keyword}: {what} must be a whole number, not {value!r}")
    if positive and value <= 0:
        raise st.origin.error(f"{st.keyword}: {what} must be positive, not {value!r}")
    if minimum is not None and value < minimum:
        raise st.origin.error(f"{st.keyword}: {what} must not be negative ({value!r})"
                              if minimum == 0 else f"{st.keyword}: {what} must be at least {minimum}, not {value!r}")
    return value
