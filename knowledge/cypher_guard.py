"""The Cypher other robots may send: a tokenizer and a parser of the subset we accept.

Free Cypher from outside the robot (the ``knowledge/cypher`` endpoint, ``kgadapt
knowledge cypher``) is parsed here before it reaches any store. Only this
grammar passes::

    query      = part { "UNION" ["ALL"] part }
    part       = { reading } "RETURN" projection
    reading    = ["OPTIONAL"] "MATCH" pattern {"," pattern} ["WHERE" expr]
               | "UNWIND" expr "AS" name
               | "WITH" projection ["WHERE" expr]
    projection = ["DISTINCT"] ("*" | item {"," item}) ["ORDER" "BY" expr [ASC|DESC] {...}]
                 ["SKIP" expr] ["LIMIT" expr]
    pattern    = [name "="] node { rel node }
    rel        = ("-" | "<-") ["[" [name] [":" TYPE {"|" TYPE}] ["*" [min] [".." max]] [map] "]"] ("-" | "->")
    expr       = the usual operators, literals, $parameters, lists, maps, CASE,
                 list comprehensions, any/all/none/single(x IN l WHERE p), and
                 calls of the functions in FUNCTIONS

Everything else is refused with the offending token and its offset: CALL (no
procedures, no subqueries), LOAD CSV, every writing clause, ``;``, regular
expressions (``=~``), pattern predicates, unbounded or long variable-length
relations (``*`` needs an upper bound of at most ``max_hops``) and functions
outside the list (``range`` builds lists of any size). Size is bounded before
parsing (characters, tokens) and while parsing (nesting depth), so
``RETURN [[[[...]]]]`` is refused here in microseconds instead of costing the
store seconds per level.

The parser is ours because no maintained Python Cypher parser exists that we
could depend on: the openCypher grammar (ANTLR) would need the ANTLR runtime
and generated code, and still accept CALL and LOAD CSV, which we would then
have to refuse by walking its tree anyway.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from kgadapt.shared.errors import ReadOnlyViolation


class CypherRefused(ReadOnlyViolation):
    """Cypher outside the accepted subset; the message names the token and its offset."""


@dataclass(frozen=True, kw_only=True)
class CypherLimits:
    """How big an accepted query may be."""

    max_chars: int = 4000
    max_tokens: int = 600
    max_depth: int = 8  # brackets and sub-expressions nested in each other
    max_hops: int = 6  # upper bound of a variable-length relation
    max_clauses: int = 16
    max_rows: int = 1000  # RETURN ... LIMIT at most this; appended when a single RETURN has none


FUNCTIONS = frozenset(
    """
    count collect sum avg min max stdev percentilecont percentiledisc
    size length tostring tointeger tofloat toboolean tostringornull tointegerornull tofloatornull
    coalesce labels type id keys properties exists head last tail isempty
    abs ceil floor round sign sqrt exp log log10 e pi
    tolower toupper lower upper trim ltrim rtrim left right substring replace split reverse
    startnode endnode nodes relationships timestamp
    """.split()
)
QUANTIFIERS = frozenset({"any", "all", "none", "single"})

_CLAUSES = {"match", "optional", "where", "with", "return", "order", "skip", "limit", "unwind", "union"}

_TOKEN = re.compile(
    r"""
    (?P<space>\s+|//[^\n]*|/\*.*?\*/)
  | (?P<string>'(?:[^'\\]|\\.)*'|"(?:[^"\\]|\\.)*")
  | (?P<name>`(?:[^`]|``)+`|[A-Za-z_][A-Za-z0-9_]*)
  | (?P<param>\$(?:[A-Za-z_][A-Za-z0-9_]*|[0-9]+))
  | (?P<number>0x[0-9A-Fa-f]+|(?:[0-9]+\.[0-9]+|\.[0-9]+|[0-9]+)(?:[eE][-+]?[0-9]+)?)
  | (?P<punct>\.\.|<>|!=|<=|>=|=~|->|<-|[-+*/%^=<>(),.:|\[\]{};])
    """,
    re.VERBOSE | re.DOTALL,
)


@dataclass(frozen=True)
class Token:
    kind: str  # "string" | "name" | "param" | "number" | "punct" | "end"
    text: str
    offset: int

    @property
    def word(self) -> str:
        """Lower-case text of a bare (not back-quoted) name; "" otherwise."""
        return self.text.lower() if self.kind == "name" and not self.text.startswith("`") else ""


def tokenize(text: str, *, limits: CypherLimits = CypherLimits()) -> list[Token]:
    """Split Cypher text into tokens, comments and blanks dropped; refuse what is not Cypher."""
    if len(text) > limits.max_chars:
        raise CypherRefused(f"query refused: {len(text)} characters, at most {limits.max_chars}")
    tokens: list[Token] = []
    pos = depth = 0
    while pos < len(text):
        match = _TOKEN.match(text, pos)
        if match is None:
            raise CypherRefused(f"query refused: unexpected character {text[pos]!r} at offset {pos}")
        kind = match.lastgroup or ""
        if kind == "punct" and match.group() in "([{":
            depth += 1
            if depth > limits.max_depth:
                raise CypherRefused(f"query refused: brackets nested deeper than {limits.max_depth} at offset {pos}")
        elif kind == "punct" and match.group() in ")]}":
            depth -= 1
        if kind != "space":
            tokens.append(Token(kind, match.group(), pos))
            if len(tokens) > limits.max_tokens:
                raise CypherRefused(f"query refused: more than {limits.max_tokens} tokens")
        pos = match.end()
    tokens.append(Token("end", "", len(text)))
    return tokens


def writing_clause(text: str) -> str | None:
    """The first clause word that writes or reaches outside the graph, or None.

    A token-level check for our own (trusted) read-only queries: a word counts
    only where it can be a clause, not as a property (``x.set``), a map key
    (``{call: 1}``), an alias (``AS load``) or inside a string.
    """
    tokens = tokenize(text, limits=CypherLimits(max_chars=1 << 20, max_tokens=1 << 20))
    for i, token in enumerate(tokens):
        word = token.word
        if word not in _WRITES:
            continue
        before = tokens[i - 1] if i else None
        after = tokens[i + 1]
        if before is not None and (before.text == "." or before.word == "as" and not _is_property(tokens, i - 1)):
            continue
        if after.text == ":" and before is not None and before.text in ("{", ","):
            continue  # a map key
        return word.upper()
    return None


_WRITES = frozenset({"create", "merge", "set", "delete", "detach", "remove", "drop", "call", "load", "foreach",
                     "alter", "grant", "revoke"})


def _is_property(tokens: list[Token], i: int) -> bool:
    return i > 0 and tokens[i - 1].text == "."


def check_cypher(text: str, *, limits: CypherLimits = CypherLimits()) -> str:
    """The text to run for ``text``, or :class:`CypherRefused` if it is outside the accepted subset.

    The rows are bounded too: a query with one RETURN and no LIMIT gets
    ``LIMIT max_rows`` appended; a RETURN's own LIMIT must be a whole number of
    at most ``max_rows``, and each part of a UNION needs one.
    """
    if not isinstance(text, str) or not text.strip():
        raise CypherRefused("query refused: the Cypher text is empty")
    parser = _Parser(tokenize(text, limits=limits), limits)
    parser.query()
    if all(parser.return_limits):
        return text
    if len(parser.return_limits) > 1:
        raise CypherRefused(f"query refused: every part of a UNION needs RETURN ... LIMIT n (n at most {limits.max_rows})")
    return f"{text.rstrip()}\nLIMIT {limits.max_rows}"


class _Parser:
    def __init__(self, tokens: list[Token], limits: CypherLimits) -> None:
        self.tokens = tokens
        self.i = 0
        self.limits = limits
        self.depth = 0
        self.clauses = 0
        self.return_limits: list[bool] = []  # per RETURN: has its own (checked) LIMIT

    # -- token helpers ------------------------------------------------------

    @property
    def tok(self) -> Token:
        return self.tokens[self.i]

    def peek(self, ahead: int = 1) -> Token:
        return self.tokens[min(self.i + ahead, len(self.tokens) - 1)]

    def at(self, *words: str) -> bool:
        t = self.tok
        return t.word in words or (t.kind == "punct" and t.text in words)

    def accept(self, *words: str) -> bool:
        if self.at(*words):
            self.i += 1
            return True
        return False

    def expect(self, *words: str) -> Token:
        if not self.at(*words):
            self.fail(f"expected {' or '.join(w.upper() if w.isalpha() else repr(w) for w in words)}")
        token = self.tok
        self.i += 1
        return token

    def fail(self, why: str) -> None:
        t = self.tok
        shown = "the end of the query" if t.kind == "end" else repr(t.text[:40])
        if t.word in ("call", "load", "foreach") or t.word in _WRITES:
            why = f"{t.text.upper()} is not allowed here (read-only subset: MATCH, OPTIONAL MATCH, WHERE, WITH, " \
                  "UNWIND, RETURN, ORDER BY, SKIP, LIMIT, UNION)"
        raise CypherRefused(f"query refused at offset {t.offset} ({shown}): {why}")

    def nest(self) -> "_Nesting":
        return _Nesting(self)

    def name(self) -> Token:
        t = self.tok
        if t.kind != "name":
            self.fail("expected a name")
        self.i += 1
        return t

    # -- clauses ------------------------------------------------------------

    def query(self) -> None:
        self.part()
        while self.accept("union"):
            self.accept("all")
            self.part()
        if self.tok.kind != "end":
            self.fail("expected the end of the query")

    def part(self) -> None:
        while True:
            self.clauses += 1
            if self.clauses > self.limits.max_clauses:
                self.fail(f"more than {self.limits.max_clauses} clauses")
            if self.accept("optional"):
                self.expect("match")
                self.match_body()
            elif self.accept("match"):
                self.match_body()
            elif self.accept("unwind"):
                self.expr()
                self.expect("as")
                self.name()
            elif self.accept("with"):
                self.projection()
                if self.accept("where"):
                    self.expr()
            elif self.accept("return"):
                self.return_limits.append(self.projection(final=True))
                return
            else:
                self.fail("expected MATCH, OPTIONAL MATCH, UNWIND, WITH or RETURN")

    def match_body(self) -> None:
        self.pattern()
        while self.accept(","):
            self.pattern()
        if self.accept("where"):
            self.expr()

    def projection(self, *, final: bool = False) -> bool:
        self.accept("distinct")
        if not self.accept("*"):
            self.item()
            while self.accept(","):
                self.item()
        if self.accept("order"):
            self.expect("by")
            self.sort_item()
            while self.accept(","):
                self.sort_item()
        if self.accept("skip"):
            self.expr()
        if not self.accept("limit"):
            return False
        if not final:
            self.expr()
            return True
        t = self.tok
        if t.kind != "number" or not t.text.isdigit() or int(t.text) > self.limits.max_rows:
            self.fail(f"RETURN ... LIMIT must be a whole number of at most {self.limits.max_rows}")
        self.i += 1
        return True

    def item(self) -> None:
        self.expr()
        if self.accept("as"):
            self.name()

    def sort_item(self) -> None:
        self.expr()
        self.accept("asc", "ascending", "desc", "descending")

    # -- patterns -----------------------------------------------------------

    def pattern(self) -> None:
        if self.tok.kind == "name" and self.peek().text == "=":
            self.i += 2
        self.node()
        while self.at("-", "<-"):
            self.relation()
            self.node()

    def node(self) -> None:
        with self.nest():
            self.expect("(")
            if self.tok.kind == "name" and not self.at(":"):
                self.name()
            while self.accept(":"):
                self.name()
            if self.at("{"):
                self.map_literal()
            elif self.at("$"):
                self.fail("a node's properties must be a map")
            self.expect(")")

    def relation(self) -> None:
        self.expect("-", "<-")
        if self.at("["):
            with self.nest():
                self.expect("[")
                if self.tok.kind == "name":
                    self.name()
                if self.accept(":"):
                    self.name()
                    while self.accept("|"):
                        self.accept(":")
                        self.name()
                if self.accept("*"):
                    self.hops()
                if self.at("{"):
                    self.map_literal()
                self.expect("]")
        self.expect("-", "->")

    def hops(self) -> None:
        star = self.i - 1
        low = int(self.expect_number()) if self.tok.kind == "number" else 1
        high: int | None = low if self.tokens[star + 1].kind == "number" else None
        if self.accept(".."):
            high = int(self.expect_number()) if self.tok.kind == "number" else None
        if high is None or high > self.limits.max_hops or high < low:
            self.i = star
            self.fail(f"a variable-length relation needs an upper bound of at most {self.limits.max_hops} "
                      "(write *1..N)")

    def expect_number(self) -> str:
        t = self.tok
        if t.kind != "number" or not t.text.isdigit():
            self.fail("expected a whole number")
        self.i += 1
        return t.text

    # -- expressions --------------------------------------------------------

    def expr(self) -> None:
        with self.nest():
            self.binary(0)

    _LEVELS = (
        ("or",), ("xor",), ("and",),
    )

    def binary(self, level: int) -> None:
        if level < 3:
            words = self._LEVELS[level]
            self.binary(level + 1)
            while self.accept(*words):
                self.binary(level + 1)
            return
        self.negation()

    def negation(self) -> None:
        if self.accept("not"):
            with self.nest():
                self.negation()
            return
        self.comparison()

    def comparison(self) -> None:
        self.additive()
        while True:
            if self.at("=~"):
                self.fail("regular expressions (=~) are not allowed")
            if self.accept("=", "<>", "!=", "<", ">", "<=", ">=", "in", "contains"):
                self.additive()
            elif self.accept("starts", "ends"):
                self.expect("with")
                self.additive()
            elif self.accept("is"):
                self.accept("not")
                self.expect("null")
            else:
                return

    def additive(self) -> None:
        self.multiplicative()
        while self.at("+", "-"):
            # (a)--(b) and (a)-[r]-(b) would otherwise read as arithmetic (a minus minus b, a minus a list):
            # Cypher reads them as pattern predicates, which are refused like every pattern outside MATCH.
            after_parenthesis = self.tokens[self.i - 1].kind == "punct" and self.tokens[self.i - 1].text == ")"
            if self.tok.text == "-" and after_parenthesis and self.peek().text in ("-", "[", "->"):
                self.fail("pattern predicates are not allowed (match the pattern in MATCH)")
            self.i += 1
            self.multiplicative()

    def multiplicative(self) -> None:
        self.power()
        while self.accept("*", "/", "%"):
            self.power()

    def power(self) -> None:
        self.unary()
        while self.accept("^"):
            self.unary()

    def unary(self) -> None:
        if self.accept("-", "+"):
            with self.nest():
                self.unary()
            return
        self.postfix()

    def postfix(self) -> None:
        self.atom()
        while True:
            if self.accept("."):
                self.name()
            elif self.at("["):
                with self.nest():
                    self.i += 1
                    if not self.at(".."):
                        self.expr()
                    if self.accept(".."):
                        if not self.at("]"):
                            self.expr()
                    self.expect("]")
            elif self.at(":") and self.tokens[self.i - 1].kind == "name":
                while self.accept(":"):  # label test: n:Label
                    self.name()
            else:
                return

    def atom(self) -> None:
        t = self.tok
        if t.kind in ("string", "number", "param"):
            self.i += 1
            return
        if t.word in ("true", "false", "null"):
            self.i += 1
            return
        if self.at("("):
            with self.nest():
                self.i += 1
                self.expr()
                self.expect(")")
            return
        if self.at("["):
            self.list_literal()
            return
        if self.at("{"):
            self.map_literal()
            return
        if t.word == "case":
            self.case()
            return
        if t.kind == "name":
            if t.word in _CLAUSES or t.word in _WRITES:
                self.fail("expected an expression")
            self.call_or_variable()
            return
        self.fail("expected an expression")

    def call_or_variable(self) -> None:
        start = self.tok
        parts = [self.name().text]
        while self.at(".") and self.peek().kind == "name" and self._call_follows():
            self.i += 1
            parts.append(self.name().text)
        if not self.at("("):
            if len(parts) > 1:
                self.i -= 1
            return
        function = ".".join(parts)
        lowered = function.lower()
        if lowered in QUANTIFIERS and self.peek().kind == "name" and self.peek(2).word == "in":
            with self.nest():
                self.expect("(")
                self.name()
                self.expect("in")
                self.expr()
                self.expect("where")
                self.expr()
                self.expect(")")
            return
        if lowered not in FUNCTIONS:
            self.i -= 1
            while self.tok.offset > start.offset:
                self.i -= 1
            self.fail(f"function {function}() is not allowed (only the functions in kgadapt.knowledge.cypher_guard.FUNCTIONS)")
        with self.nest():
            self.expect("(")
            self.accept("distinct")
            if lowered == "count" and self.accept("*"):
                self.expect(")")
                return
            if not self.accept(")"):
                self.expr()
                while self.accept(","):
                    self.expr()
                self.expect(")")

    def _call_follows(self) -> bool:
        """At "." in a dotted name: True if the dotted name ends in a call (ns.fn(...))."""
        j = self.i
        while self.tokens[j].text == "." and self.tokens[j + 1].kind == "name":
            j += 2
        return self.tokens[j].text == "("

    def list_literal(self) -> None:
        with self.nest():
            self.expect("[")
            if self.tok.kind == "name" and self.peek().word == "in":
                self.name()
                self.expect("in")
                self.expr()
                if self.accept("where"):
                    self.expr()
                if self.accept("|"):
                    self.expr()
                self.expect("]")
                return
            if not self.accept("]"):
                self.expr()
                while self.accept(","):
                    self.expr()
                self.expect("]")

    def map_literal(self) -> None:
        with self.nest():
            self.expect("{")
            if not self.accept("}"):
                self.map_entry()
                while self.accept(","):
                    self.map_entry()
                self.expect("}")

    def map_entry(self) -> None:
        if self.tok.kind not in ("name", "string"):
            self.fail("expected a map key")
        self.i += 1
        self.expect(":")
        self.expr()

    def case(self) -> None:
        with self.nest():
            self.expect("case")
            if not self.at("when"):
                self.expr()
            self.expect("when")
            self.expr()
            self.expect("then")
            self.expr()
            while self.accept("when"):
                self.expr()
                self.expect("then")
                self.expr()
            if self.accept("else"):
                self.expr()
            self.expect("end")


class _Nesting:
    def __init__(self, parser: _Parser) -> None:
        self.parser = parser

    def __enter__(self) -> None:
        p = self.parser
        p.depth += 1
        if p.depth > p.limits.max_depth * 4:  # a bracket opens a few parser levels; unary minus one each
            p.fail(f"nested deeper than {p.limits.max_depth} levels")

    def __exit__(self, *exc: object) -> None:
        self.parser.depth -= 1
