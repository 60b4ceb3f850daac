"""Param / Output / Algorithm: the declarative description of an algorithm."""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

__all__ = ["PARAM_TYPES", "ParamType", "REQUIRED", "Param", "Output", "Algorithm", "parse_docstring"]

ParamType = Literal[
    "folder", "file", "raster", "vector", "pointcloud",
    "number", "integer", "enum", "bool", "crs", "string",
]
#: Every parameter type; the CLI and QGIS lookup tables must cover each one.
PARAM_TYPES: tuple[str, ...] = get_args(ParamType)
#: Types whose value is a path (input that must exist, or an output destination).
PATH_TYPES = frozenset({"folder", "file", "raster", "vector", "pointcloud"})


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: Sentinel default of a parameter that must be given.
REQUIRED: Any = _Required()


@dataclass(frozen=True)
class Param:
    """One typed parameter of an algorithm.

    ``help`` may be left empty: it is then taken from the core function's
    numpydoc ``Parameters`` section, so it is written once.
    ``output=True`` marks a destination (file or folder to be written).
    """

    name: str
    type: ParamType
    default: Any = REQUIRED
    help: str = ""
    unit: str | None = None
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    extensions: tuple[str, ...] = ()
    output: bool = False
    advanced: bool = False

    def __post_init__(self) -> None:
        if self.type not in PARAM_TYPES:
            raise ValueError(f"parameter {self.name}: unknown type {self.type!r}")
        if self.type == "enum" and not self.choices:
            raise ValueError(f"parameter {self.name}: enum needs choices")
        if self.output and self.type not in PATH_TYPES:
            raise ValueError(f"parameter {self.name}: only path types can be outputs")

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @property
    def cli_flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def qgis_name(self) -> str:
        return self.name.upper()


@dataclass(frozen=True)
class Output:
    """One output of an algorithm: an attribute of the core function's result."""

    name: str
    type: Literal["folder", "file", "raster", "vector", "pointcloud", "number", "integer", "string", "json"]
    help: str = ""


@dataclass(frozen=True)
class Algorithm:
    """An algorithm: id, title, group, typed params and outputs, and its core function.

    The core function takes the params as keyword arguments plus ``feedback``,
    and returns a result object whose attributes are named by ``outputs``.
    """

    id: str
    title: str
    group: str
    function: Callable[..., Any]
    params: tuple[Param, ...]
    outputs: tuple[Output, ...] = ()
    param_help: dict[str, str] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z][a-z0-9-]*", self.id):
            raise ValueError(f"algorithm id {self.id!r} must be lowercase kebab-case")
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError(f"algorithm {self.id}: duplicate parameter names")
        doc = parse_docstring(self.function.__doc__ or "")
        object.__setattr__(self, "param_help", doc["params"])
        # Fill each param's help from the docstring when the spec left it empty.
        filled = tuple(
            p if p.help else _replace(p, help=doc["params"].get(p.name, "")) for p in self.params
        )
        object.__setattr__(self, "params", filled)

    @property
    def help(self) -> str:
        return parse_docstring(self.function.__doc__ or "")["description"]

    @property
    def short_help(self) -> str:
        return parse_docstring(self.function.__doc__ or "")["summary"]

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def signature(self) -> inspect.Signature:
        return inspect.signature(self.function)


def _replace(p: Param, **changes: Any) -> Param:
    from dataclasses import replace

    return replace(p, **changes)


_SECTION = re.compile(r"^\s*(Parameters|Returns|Raises|Yields|Notes|Examples|See Also|References|Warns)\s*\n\s*-{3,}\s*$", re.M)


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
    params: dict[str, str] = {}
    for i, m in enumerate(sections):
        if m.group(1) != "Parameters":
            continue
        end = sections[i + 1].start() if i + 1 < len(sections) else len(text)
        block = text[m.end():end]
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
    return {"summary": summary, "description": description, "params": params}
