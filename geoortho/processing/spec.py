"""Param / Output / Algorithm: the declarative description of an algorithm.

A spec says what only a face needs (the parameter's type for a file picker, its
unit, range, whether it is written or advanced); what the core function already
says is read from it, never typed twice: defaults and required-ness from the
signature, choices from ``Literal[...]`` annotations, help from the numpydoc
docstring. The function is named as ``"geoortho.module:function"`` and read
from its source (:mod:`.static`), so describing the registry imports nothing heavy.
"""

from __future__ import annotations

import importlib
import inspect
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal, get_args

from geoortho.processing.static import read_function, split_ref

__all__ = ["PARAM_TYPES", "ParamType", "REQUIRED", "Param", "Output", "Algorithm", "parse_docstring"]

ParamType = Literal[
    "folder",
    "file",
    "raster",
    "vector",
    "pointcloud",
    "number",
    "integer",
    "enum",
    "bool",
    "crs",
    "string",
]
#: Every parameter type; the CLI and QGIS lookup tables must cover each one.
PARAM_TYPES: tuple[str, ...] = get_args(ParamType)
#: Types whose value is a path (input that must exist, or an output destination).
PATH_TYPES = frozenset({"folder", "file", "raster", "vector", "pointcloud"})


class _Sentinel:
    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return self.name


#: Sentinel default of a parameter that must be given.
REQUIRED: Any = _Sentinel("REQUIRED")
#: A spec's default before the signature has filled it in.
_FROM_SIGNATURE: Any = _Sentinel("FROM_SIGNATURE")


@dataclass(frozen=True)
class Param:
    """One typed parameter of an algorithm, as the faces need it.

    The default (or that it is required), an enum's choices and the help are the
    core function's: :class:`Algorithm` fills them in from its signature and
    docstring. ``output=True`` marks a destination (file or folder to be written);
    ``aliases`` are older names the CLI still accepts.
    """

    name: str
    type: ParamType
    unit: str | None = None
    minimum: float | None = None
    maximum: float | None = None
    extensions: tuple[str, ...] = ()
    output: bool = False
    advanced: bool = False
    aliases: tuple[str, ...] = ()
    #: a folder given for this file stands for this file in it (a run project: its dem/dsm.tif)
    project_file: str = ""
    # filled in from the core function
    default: Any = _FROM_SIGNATURE
    choices: tuple[str, ...] = ()
    help: str = ""

    def __post_init__(self) -> None:
        if self.type not in PARAM_TYPES:
            raise ValueError(f"parameter {self.name}: unknown type {self.type!r}")
        if self.output and self.type not in PATH_TYPES:
            raise ValueError(f"parameter {self.name}: only path types can be outputs")

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @property
    def cli_flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def cli_aliases(self) -> tuple[str, ...]:
        return tuple("--" + a.replace("_", "-") for a in self.aliases)

    @property
    def qgis_name(self) -> str:
        return self.name.upper()


@dataclass(frozen=True)
class Output:
    """One output of an algorithm: an attribute of the core function's result.

    Its help is the result class's (numpydoc ``Attributes`` section), filled in by :class:`Algorithm`.
    """

    name: str
    type: Literal["folder", "file", "raster", "vector", "pointcloud", "number", "integer", "string", "json"]
    help: str = ""


@dataclass(frozen=True)
class Algorithm:
    """An algorithm: id, title, group, typed params and outputs, and its core function.

    ``function`` names the core function as ``"geoortho.module:function"``; it takes
    the params as keyword arguments plus ``feedback`` and returns a result object
    whose attributes are named by ``outputs``. Every parameter of the function
    (but ``feedback``) must have a spec and every spec a parameter, so the two
    cannot drift apart.
    """

    id: str
    title: str
    group: str
    function_ref: str
    params: tuple[Param, ...]
    outputs: tuple[Output, ...] = ()

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z][a-z0-9-]*", self.id):
            raise ValueError(f"algorithm id {self.id!r} must be lowercase kebab-case")
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError(f"algorithm {self.id}: duplicate parameter names")
        static = read_function(self.function_ref)
        signature = {p.name for p in static.params} - {"feedback"}
        if set(names) != signature:
            raise ValueError(
                f"algorithm {self.id}: spec and {self.function_ref} disagree: "
                f"only in the spec {sorted(set(names) - signature)}, "
                f"only in the function {sorted(signature - set(names))}"
            )
        doc = parse_docstring(static.doc)
        object.__setattr__(self, "params", tuple(self._complete(p, static.param(p.name), doc) for p in self.params))
        fields = parse_docstring(static.returns_doc)["attributes"]
        for o in self.outputs:
            if o.help:
                raise ValueError(f"algorithm {self.id}, output {o.name}: its help is the result class's docstring")
            if o.name not in fields:
                raise ValueError(f"algorithm {self.id}: output {o.name} is not documented by the result class")
        object.__setattr__(self, "outputs", tuple(replace(o, help=fields[o.name]) for o in self.outputs))

    def _complete(self, p: Param, sig: Any, doc: dict[str, Any]) -> Param:
        where = f"algorithm {self.id}, parameter {p.name}"
        if p.default is not _FROM_SIGNATURE or p.choices or p.help:
            raise ValueError(f"{where}: default, choices and help come from {self.function_ref}, not the spec")
        choices = tuple(str(c) for c in sig.choices)
        if (p.type == "enum") != bool(choices):
            raise ValueError(f"{where}: an enum is exactly a parameter annotated Literal[...]")
        default = sig.default if sig.has_default else REQUIRED
        if not isinstance(default, (type(None), bool, int, float, str)) and p.type not in PATH_TYPES:
            raise ValueError(f"{where}: default {default!r} is not a plain value")
        return replace(p, default=default, choices=choices, help=doc["params"].get(p.name, ""))

    @property
    def function(self) -> Callable[..., Any]:
        """The core function (imported on first use: only the algorithm run pays for its stack)."""
        module, name = split_ref(self.function_ref)
        return getattr(importlib.import_module(module), name)  # type: ignore[no-any-return]

    @property
    def help(self) -> str:
        return str(parse_docstring(read_function(self.function_ref).doc)["description"])

    @property
    def short_help(self) -> str:
        return str(parse_docstring(read_function(self.function_ref).doc)["summary"])

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def signature(self) -> inspect.Signature:
        return inspect.signature(self.function)


_SECTION = re.compile(
    r"^\s*(Parameters|Attributes|Returns|Raises|Yields|Notes|Examples|See Also|References|Warns)\s*\n\s*-{3,}\s*$", re.M
)


def parse_docstring(doc: str) -> dict[str, Any]:
    """Split a numpydoc docstring into summary, description and parameter help.

    >>> d = parse_docstring('''Do it.
    ...
    ...     More words.
    ...
    ...     Parameters
    ...     ----------
    ...     size_m : float
    ...         Size in metres,
    ...         on two lines.
    ...     ''')
    >>> d["summary"], d["params"]["size_m"]
    ('Do it.', 'Size in metres, on two lines.')
    """
    text = inspect.cleandoc(doc)
    sections = list(_SECTION.finditer(text))
    body_end = sections[0].start() if sections else len(text)
    description = text[:body_end].strip()
    summary = description.split("\n\n", 1)[0].replace("\n", " ").strip()
    found: dict[str, dict[str, str]] = {"Parameters": {}, "Attributes": {}}
    for i, m in enumerate(sections):
        if m.group(1) not in found:
            continue
        params = found[m.group(1)]
        end = sections[i + 1].start() if i + 1 < len(sections) else len(text)
        block = text[m.end() : end]
        current: str | None = None
        lines: list[str] = []
        for line in block.splitlines():
            if line and not line[0].isspace():
                if current is not None:
                    params[current] = " ".join(lines).strip()
                current = line.split(":", 1)[0].strip()
                lines = []
            elif line.strip() and current is not None:
                lines.append(line.strip())
        if current is not None:
            params[current] = " ".join(lines).strip()
    return {
        "summary": summary,
        "description": description,
        "params": found["Parameters"],
        "attributes": found["Attributes"],
    }
