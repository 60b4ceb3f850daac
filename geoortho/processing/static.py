"""Read a core function's signature and docstring from its source, without importing it.

The registry names each algorithm's function as ``"geoortho.elevation.gridding:dem"``. Building
the CLI or the QGIS description needs only the parameters' defaults, their choices
(``Literal[...]`` annotations) and the docstring: reading them from the syntax tree
keeps ``python -m geoortho --help`` from loading OpenCV, pycolmap, GDAL and SciPy.
A test checks that what is read here equals what :func:`inspect.signature` sees.

What can be read is deliberately small: literals, tuples, ``Path("...")``, negative
numbers, module-level names bound to those (followed through ``from .x import y``),
``Literal[...]`` and ``get_args(Alias)``. Anything else is an error naming the
function and the parameter, so the declaration is made readable, not guessed at.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

__all__ = ["StaticFunction", "StaticParam", "StaticReadError", "read_function", "split_ref"]

_PACKAGE_DIR = Path(__file__).resolve().parents[1]


class StaticReadError(ValueError):
    """The declaration cannot be read without running the module."""


@dataclass(frozen=True)
class _Literal:
    """A ``Literal[...]`` type as read from the source."""

    values: tuple[Any, ...]


@dataclass(frozen=True)
class StaticParam:
    name: str
    has_default: bool
    default: Any
    choices: tuple[Any, ...]  # from a Literal annotation; () when there is none
    keyword_only: bool


@dataclass(frozen=True)
class StaticFunction:
    module: str
    name: str
    doc: str
    params: tuple[StaticParam, ...]
    returns_doc: str  # docstring of the result class the function is annotated to return

    def param(self, name: str) -> StaticParam:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)


def split_ref(ref: str) -> tuple[str, str]:
    module, sep, name = ref.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"function reference {ref!r} must read 'package.module:function'")
    return module, name


def _module_path(module: str) -> Path:
    parts = module.split(".")
    if parts[0] != _PACKAGE_DIR.name:
        raise StaticReadError(f"{module}: only geoortho's own modules are read statically")
    base = _PACKAGE_DIR.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    raise StaticReadError(f"no source for module {module}")


# A top-level statement starts at column 0 with a name, a decorator or a keyword; closing
# brackets at column 0 continue the statement before.
_TOP = re.compile(r"^[A-Za-z_@]", re.M)
# What such a statement binds: a def or class, an assignment, or (parsed) an import.
_BINDS = re.compile(r"(?:def|class) (?P<def>\w+)\b|(?P<assign>[A-Za-z_]\w*)\s*(:[^=\n]*)?=(?!=)|from ")


@cache
def _module_index(module: str) -> dict[str, str]:
    """Name -> the source of the top-level statement that binds it (defs, assignments, imports).

    Parsing every module whole costs more than the rest of ``--help`` together, so the
    text is cut at column-0 lines and a piece is parsed only when its name is asked for.
    """
    text = _module_path(module).read_text(encoding="utf-8")
    starts = [m.start() for m in _TOP.finditer(text)] + [len(text)]
    index: dict[str, str] = {}
    for a, b in zip(starts, starts[1:]):
        piece = text[a:b]
        m = _BINDS.match(piece)
        if m is None:
            continue
        name = m.group("def") or m.group("assign")
        if name:
            index.setdefault(name, piece)
        else:  # an import: a few short lines, parsed now for the names it binds
            try:
                node = ast.parse(piece).body[0]
            except (SyntaxError, IndexError):
                continue
            if isinstance(node, ast.ImportFrom):
                for alias in node.names:
                    index.setdefault(alias.asname or alias.name, piece)
    return index


@cache
def _statement(module: str, name: str) -> ast.stmt | None:
    piece = _module_index(module).get(name)
    if piece is None:
        return None
    try:
        return ast.parse(piece).body[0]
    except SyntaxError as e:
        raise StaticReadError(f"{module}: cannot read the statement binding {name!r}: {e}") from None


def _absolute(module: str, level: int, name: str | None) -> str:
    """The absolute module of ``from {'.' * level}{name} import ...`` written in ``module``."""
    is_package = _module_path(module).name == "__init__.py"
    parts = module.split(".")
    keep = len(parts) - level + (1 if is_package else 0)
    base = parts[:keep]
    return ".".join(base + ([name] if name else []))


def _resolve(module: str, name: str) -> tuple[str, ast.stmt] | None:
    """The statement that defines module-level ``name``, and its module: imports from
    geoortho's own modules are followed to the definition."""
    node = _statement(module, name)
    if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("geoortho")):
        for alias in node.names:
            if (alias.asname or alias.name) == name:
                source = _absolute(module, node.level, node.module) if node.level else node.module
                assert source is not None
                return _resolve(source, alias.name)
    return None if node is None else (module, node)


def _binding(module: str, name: str) -> tuple[str, ast.expr] | None:
    """The expression a module-level ``name`` is bound to, and the module it lives in."""
    found = _resolve(module, name)
    if found is None:
        return None
    where, node = found
    if isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
        return where, node.value
    return None


def _value(module: str, node: ast.expr) -> Any:
    """Evaluate the small language declarations are written in (see the module docstring)."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_value(module, e) for e in node.elts)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        return -_value(module, node.operand)
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
        return _field_default(module, node.value.id, node.attr)
    if isinstance(node, ast.Name):
        bound = _binding(module, node.id)
        if bound is None:
            raise StaticReadError(f"{module}: cannot read the name {node.id!r}")
        return _value(*bound)
    if isinstance(node, ast.Subscript) and _name_of(node.value) == "Literal":
        inner = node.slice
        items = inner.elts if isinstance(inner, ast.Tuple) else [inner]
        return _Literal(tuple(_value(module, e) for e in items))
    if isinstance(node, ast.Call) and len(node.args) == 1 and not node.keywords:
        fn, arg = _name_of(node.func), _value(module, node.args[0])
        if fn == "Path":
            return Path(arg)
        if fn == "get_args" and isinstance(arg, _Literal):
            return arg.values
        if fn == "tuple" and isinstance(arg, tuple):
            return arg
    raise StaticReadError(f"{module}: cannot read {ast.unparse(node)!r} without running it")


def _field_default(module: str, class_name: str, field: str) -> Any:
    """``Options.field`` in a signature: the default of a dataclass field (one declaration)."""
    where, node = _resolve(module, class_name) or (module, None)
    if isinstance(node, ast.ClassDef):
        for item in node.body:
            if (
                isinstance(item, ast.AnnAssign)
                and isinstance(item.target, ast.Name)
                and item.target.id == field
                and item.value is not None
            ):
                return _value(where, item.value)
    raise StaticReadError(f"{module}: cannot read {class_name}.{field}")


def _name_of(node: ast.expr) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return ""


def _choices(module: str, annotation: ast.expr | None) -> tuple[Any, ...]:
    """The values of a ``Literal`` annotation (or ``Alias``, or ``Alias | None``)."""
    if annotation is None:
        return ()
    if isinstance(annotation, ast.Constant) and isinstance(annotation.value, str):
        annotation = ast.parse(annotation.value, mode="eval").body
    if isinstance(annotation, ast.BinOp) and isinstance(annotation.op, ast.BitOr):
        return _choices(module, annotation.left) or _choices(module, annotation.right)
    if isinstance(annotation, ast.Subscript) and _name_of(annotation.value) == "Literal":
        return tuple(_value(module, annotation).values)
    if isinstance(annotation, ast.Name):
        bound = _binding(module, annotation.id)
        if bound is not None:
            bound_module, expr = bound
            if isinstance(expr, ast.Subscript) and _name_of(expr.value) == "Literal":
                return tuple(_value(bound_module, expr).values)
    return ()


#: What :func:`read_function` reads, made ready (``python tools/write_described.py``): the
#: registry's description at start-up without parsing the sources (half of ``--help``'s import).
#: It holds the digest of every source file of the package and is used only while they match; a
#: test keeps it fresh.
READY_MADE = Path(__file__).with_name("described.json")


def source_digest() -> str:
    """Digest of every ``.py`` file of the package (names and contents)."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    for path in sorted(_PACKAGE_DIR.rglob("*.py")):
        h.update(path.relative_to(_PACKAGE_DIR).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _encode(v: Any) -> Any:
    if isinstance(v, Path):
        return {"path": str(v)}
    if isinstance(v, tuple):
        return {"tuple": [_encode(x) for x in v]}
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    raise StaticReadError(f"cannot keep {v!r} ready-made")


def _decode(v: Any) -> Any:
    if isinstance(v, dict):
        return Path(v["path"]) if "path" in v else tuple(_decode(x) for x in v["tuple"])
    return v


def ready_made_text(refs: list[str]) -> str:
    """The ready-made file's text for these function references (the registry's: this module is
    below the registry and does not import it), read from the sources now."""
    import json

    functions = {}
    for ref in sorted(set(refs)):
        f = _read_source(ref)
        functions[ref] = {
            "doc": f.doc,
            "returns_doc": f.returns_doc,
            "params": [
                [p.name, p.has_default, _encode(p.default), _encode(p.choices), p.keyword_only] for p in f.params
            ],
        }
    return json.dumps({"source_digest": source_digest(), "functions": functions}, indent=1, sort_keys=True) + "\n"


@cache
def _ready_made() -> dict[str, Any]:
    import json
    import os

    if os.environ.get("GEOORTHO_NO_READY_MADE"):  # for a benchmark of what it saves
        return {}
    try:
        data = json.loads(READY_MADE.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("source_digest") != source_digest():
        return {}  # a source changed since it was made: read the sources
    return dict(data.get("functions") or {})


@cache
def read_function(ref: str) -> StaticFunction:
    """The signature and docstring of ``"module:function"``: ready-made when the sources are
    those it was made from, else read from the source."""
    entry = _ready_made().get(ref)
    if entry is None:
        return _read_source(ref)
    module, name = split_ref(ref)
    params = tuple(
        StaticParam(n, bool(has), _decode(default), _decode(choices), bool(kw))
        for n, has, default, choices, kw in entry["params"]
    )
    return StaticFunction(module, name, entry["doc"], params, entry["returns_doc"])


def _read_source(ref: str) -> StaticFunction:
    """The signature and docstring of ``"module:function"``, read from its source."""
    module, name = split_ref(ref)
    node = _statement(module, name)
    if not isinstance(node, ast.FunctionDef):
        raise StaticReadError(f"{module} defines no function {name!r}")
    args = node.args
    positional = args.posonlyargs + args.args
    pos_defaults: list[ast.expr | None] = [None] * (len(positional) - len(args.defaults)) + list(args.defaults)
    params: list[StaticParam] = []
    pairs = [(a, d, False) for a, d in zip(positional, pos_defaults)]
    pairs += [(a, d, True) for a, d in zip(args.kwonlyargs, args.kw_defaults)]
    for arg, default, kw_only in pairs:
        try:
            value = _value(module, default) if default is not None else None
            choices = _choices(module, arg.annotation)
        except StaticReadError as e:
            raise StaticReadError(f"{ref}, parameter {arg.arg}: {e}") from None
        params.append(StaticParam(arg.arg, default is not None, value, tuple(choices), kw_only))
    returns = node.returns
    if isinstance(returns, ast.Constant) and isinstance(returns.value, str):
        returns = ast.parse(returns.value, mode="eval").body
    returns_doc = _class_doc(module, returns.id) if isinstance(returns, ast.Name) else ""
    return StaticFunction(module, name, ast.get_docstring(node) or "", tuple(params), returns_doc)


def _class_doc(module: str, name: str) -> str:
    found = _resolve(module, name)
    node = found[1] if found is not None else None
    return (ast.get_docstring(node) or "") if isinstance(node, ast.ClassDef) else ""
