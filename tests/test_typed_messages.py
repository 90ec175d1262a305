"""Runtime code sends and receives msgspec Structs only, and never decides anything by an error's text.

An AST scan of the runtime packages (shared, knowledge, onboard, remote, deploy and the
package root's modules; shared/messages.py itself aside): no ``encode`` of a kind name and a
map, no ``decode`` (which returns the map as sent), no msgpack decoder of its own beside the
contract's, and every kind of docs/CONTRACTS.md built as its Struct by some producer and handed
as a type to some consumer. Tests, the simulator and the benchmarks write the wire as outsiders
do and may use the map forms.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

from kgadapt.shared import messages
from tests.conftest import REPO

RUNTIME = ("shared", "knowledge", "onboard", "remote", "deploy")
MESSAGES = REPO / "shared" / "messages.py"
MODULE = "kgadapt.shared.messages"
STRUCTS = {cls.__name__: cls for cls in messages.KINDS.values()}  # the kinds of docs/CONTRACTS.md


def runtime_files() -> list[Path]:
    files = [p for d in RUNTIME for p in sorted((REPO / d).rglob("*.py"))]
    files += sorted(p for p in (REPO / "kgadapt").glob("*.py")) + sorted((REPO / "kgadapt" / "operator").rglob("*.py"))
    return [p for p in files if p != MESSAGES]


@dataclass(frozen=True)
class Use:
    """What one file does with the contract's module."""

    problems: list[str]
    built: set[str]  # Struct names called (constructed)
    handed: set[str]  # Struct names passed to a call as a type (decode_as, decode_with_unknown, a helper)


def scan(path: Path) -> Use:
    tree = ast.parse(path.read_text(), filename=str(path))
    where = path.relative_to(REPO)
    modules: set[str] = set()  # names bound to the messages module
    functions: dict[str, str] = {}  # local name -> function of the messages module
    problems: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "kgadapt.shared":
            modules |= {a.asname or a.name for a in node.names if a.name == "messages"}
        elif isinstance(node, ast.ImportFrom) and node.module == MODULE:
            functions |= {a.asname or a.name: a.name for a in node.names}
        elif isinstance(node, ast.Import):
            modules |= {a.asname for a in node.names if a.name == MODULE and a.asname}
            if any(a.name == "msgpack" or a.name.startswith("msgpack.") for a in node.names):
                problems.append(f"{where}:{node.lineno}: imports msgpack (decode through kgadapt.shared.messages)")
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "msgpack":
            problems.append(f"{where}:{node.lineno}: imports msgpack (decode through kgadapt.shared.messages)")

    def of_messages(func: ast.expr) -> str | None:
        """The messages-module name ``func`` refers to (``messages.encode``, an imported ``encode``), else None."""
        if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) and func.value.id in modules:
            return func.attr
        if isinstance(func, ast.Name) and func.id in functions:
            return functions[func.id]
        return None

    built: set[str] = set()
    handed: set[str] = set()
    for node in ast.walk(tree):
        name = of_messages(node) if isinstance(node, (ast.Attribute, ast.Name)) else None
        if name == "decode":
            problems.append(f"{where}:{node.lineno}: messages.decode returns a map; receive a Struct (decode_as)")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr" \
                and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id in modules:
            problems.append(f"{where}:{node.lineno}: getattr on the messages module hides what is used")
        if isinstance(node, ast.Attribute) and node.attr in ("msgpack",) and isinstance(node.value, ast.Name) \
                and node.value.id == "msgspec":
            problems.append(f"{where}:{node.lineno}: msgspec.msgpack beside the contract's own decoders")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "convert" \
                and any(of_messages(a) in STRUCTS for a in node.args[1:] if isinstance(a, (ast.Attribute, ast.Name))):
            problems.append(f"{where}:{node.lineno}: msgspec.convert builds a message from a map")
        if not isinstance(node, ast.Call):
            continue
        called = of_messages(node.func)
        if called == "encode":
            arg = node.args[0] if node.args else None
            if len(node.args) != 1 or node.keywords or isinstance(arg, (ast.Constant, ast.Dict, ast.DictComp,
                                                                          ast.JoinedStr)) \
                    or (isinstance(arg, ast.Call) and isinstance(arg.func, ast.Name) and arg.func.id == "dict"):
                problems.append(f"{where}:{node.lineno}: encode takes one Struct, not a kind and a map")
        elif called in STRUCTS:
            built.add(called)
        for arg in [*node.args, *(k.value for k in node.keywords)]:
            handed_name = of_messages(arg) if isinstance(arg, (ast.Attribute, ast.Name)) else None
            if handed_name in STRUCTS:
                handed.add(handed_name)
    return Use(problems, built, handed)


@pytest.fixture(scope="module")
def uses() -> dict[Path, Use]:
    return {path: scan(path) for path in runtime_files()}


# msgpack outside the wire: the knowledge service's pipe to its own lower-priority child (knowledge/public_worker.py)
# frames settings, questions and already-encoded answers; no message of docs/CONTRACTS.md crosses it.
PRIVATE_PIPES = {"knowledge/public_worker.py"}


def test_no_wire_message_is_a_map_in_runtime_code(uses):
    problems = [p for path, use in uses.items() for p in use.problems
                if not (path.relative_to(REPO).as_posix() in PRIVATE_PIPES and "imports msgpack" in p)]
    assert not problems, "\n".join(problems)


def test_every_kind_has_a_producer_building_its_struct_and_a_consumer_receiving_it(uses):
    built = set().union(*(u.built for u in uses.values()))
    handed = set().union(*(u.handed for u in uses.values()))
    names = set(STRUCTS)
    assert names - built == set(), f"kinds no runtime code builds as a Struct: {sorted(names - built)}"
    assert names - handed == set(), f"kinds no runtime code receives as a Struct: {sorted(names - handed)}"


BAD = '''
from kgadapt.shared import messages as m
from kgadapt.shared.messages import encode, decode as unpack
import msgpack

m.encode("frame", {"seq": 1})
encode("frame", body)
encode(dict(seq=1))
unpack(payload, "frame")
m.decode(payload, "frame")
getattr(m, "decode")
'''


def test_the_scan_catches_what_would_slip_through(tmp_path, monkeypatch):
    # A file of our own with every way around: aliases, imported names, a map built with dict(), getattr.
    path = REPO / "shared" / "_typed_scan_probe.py"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: BAD if self == path else _read(self, *a, **k))
    found = scan(path).problems
    assert len(found) == 7, "\n".join(found)
    assert scan(REPO / "onboard" / "perception" / "detector.py").problems == []


_read = Path.read_text


# -- errors are typed, never recognised by their text ---------------------------------------------------------------

# Where a library gives no type for a failure and its text is the only sign, the text is read once, at the
# boundary, and turned into our own exception: FalkorDB answers a query over its time limit, a write in a
# read-only query and a read of a graph never written with plain redis ResponseErrors. A Neo4j error's
# ``code`` is its status code, a structured name, not text.
TEXT_AT_BOUNDARY = {("knowledge/falkordb_store.py", "timed out"), ("knowledge/falkordb_store.py", "read-only"),
                    ("knowledge/falkordb_store.py", "empty key")}


def error_text_comparisons(path: Path) -> list[tuple[str, int, str]]:
    """(file, line, literal) of each comparison of an error's text with a string: the text of an exception
    caught (``except ... as exc``) or of an error reply (Zenoh's ``reply.err``), or a name holding either."""
    tree = ast.parse(path.read_text(), filename=str(path))
    where = str(path.relative_to(REPO))
    texts = {h.name for h in ast.walk(tree) if isinstance(h, ast.ExceptHandler) and h.name}

    def is_text(node: ast.expr) -> bool:
        if isinstance(node, ast.Name):
            return node.id in texts
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("str", "repr"):
            return any(is_text(a) for a in node.args)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):  # str(exc).lower(), .to_string()
            return is_text(node.func.value)
        if isinstance(node, ast.Attribute):  # exc.args, reply.err.payload (exc.code: a status code, not text)
            return node.attr == "err" or (node.attr != "code" and is_text(node.value))
        if isinstance(node, ast.Subscript):
            return is_text(node.value)
        return False

    for _ in range(3):  # names holding a text, and names made from those
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and is_text(node.value):
                texts |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    found = []
    for node in ast.walk(tree):
        literal = None
        if isinstance(node, ast.Compare) and any(isinstance(o, (ast.In, ast.NotIn, ast.Eq, ast.NotEq))
                                                 for o in node.ops):
            sides = [node.left, *node.comparators]
            if any(is_text(s) for s in sides) and any(isinstance(s, ast.Constant) and isinstance(s.value, str)
                                                      for s in sides):
                literal = next(s.value for s in sides if isinstance(s, ast.Constant) and isinstance(s.value, str))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("startswith", "endswith", "find", "count") and is_text(node.func.value):
            literal = "." + node.func.attr
        if literal is not None and (where, literal) not in TEXT_AT_BOUNDARY:
            found.append((where, node.lineno, literal))
    return sorted(found)


def test_no_runtime_code_recognises_an_error_by_its_text():
    # shared/messages.py aside: msgspec's ValidationError carries the field's path in its text only, which
    # _explain rewords; what is raised is a MessageError either way, decided by the exception's type.
    found = [f for path in runtime_files() for f in error_text_comparisons(path)]
    assert not found, "errors compared by their text (type them in kgadapt.shared.errors): " + repr(found)


def test_the_error_text_scan_sees_a_comparison(monkeypatch):
    probe = REPO / "onboard" / "_error_text_probe.py"
    text = '''
try:
    reply()
except Exception as exc:
    why = str(exc).strip().lower()
    if why == "timeout":
        raise
    if "refused" in str(exc):
        pass
    if str(exc).startswith("busy"):
        pass
said = replies[0].err.payload.to_string()
if said.strip() == "gone":
    pass
'''
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: text if self == probe else _read(self, *a, **k))
    assert [lit for _, _, lit in error_text_comparisons(probe)] == ["timeout", "refused", ".startswith", "gone"]
