"""The package's structure in numbers (issue 50): long functions, imports inside functions between
geoortho's modules, import cycles, private names imported across modules.

A function's length is counted twice: all its lines, and its code (the lines after the docstring).
A function whose code is over 80 lines is listed, and marked when a ``# One piece:`` comment in it
says why it is not split.

``python tools/structure_numbers.py [PACKAGE_DIR]`` prints them; run it before and after a change
of layout to show what the change did. It reads the sources only (nothing is imported).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

LONG_LINES = 80


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def resolve(node: ast.ImportFrom, here: str, is_package: bool) -> str:
    """The absolute module an ``from X import`` names."""
    if not node.level:
        return node.module or ""
    base = here.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
    return ".".join([*base, node.module] if node.module else base)


def main(package_dir: str = "geoortho") -> None:
    root = Path(package_dir).resolve()
    top = root.name
    modules = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    long_functions: list[tuple[int, str]] = []
    long_code: list[tuple[int, str, bool]] = []
    local_imports = 0
    private: list[str] = []
    graph: dict[str, set[str]] = {m: set() for m in modules}

    def target_module(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    for mod, path in modules.items():
        source = path.read_text()
        lines = source.splitlines()
        tree = ast.parse(source, str(path))
        is_package = path.name == "__init__.py"
        parents: dict[ast.AST, ast.AST] = {}
        for node in ast.walk(tree):
            for child in ast.iter_child_nodes(node):
                parents[child] = node
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                long_functions.append((n, f"{mod}.{node.name}"))
                has_doc = ast.get_docstring(node) is not None
                start = (node.body[0].end_lineno or 0) + 1 if has_doc else node.body[0].lineno
                code = lines[start - 1 : node.end_lineno]
                if len(code) > LONG_LINES:
                    one_piece = any(ln.strip().startswith("# One piece:") for ln in code)
                    long_code.append((len(code), f"{mod}.{node.name}", one_piece))
            targets: list[tuple[str, list[str]]] = []
            if isinstance(node, ast.ImportFrom):
                src = resolve(node, mod, is_package)
                targets.append((src, [a.name for a in node.names]))
            elif isinstance(node, ast.Import):
                targets += [(a.name, []) for a in node.names]
            for src, names in targets:
                if not (src == top or src.startswith(top + ".")):
                    continue
                # "from geoortho.pkg import module" names a module, not an attribute
                dests = [target_module(f"{src}.{n}") if f"{src}.{n}" in modules else target_module(src) for n in names]
                dests = [d for d in (dests or [target_module(src)]) if d and d != mod]
                graph[mod].update(dests)
                p = parents.get(node)
                while p is not None and not isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    p = parents.get(p)
                if p is not None and dests:
                    local_imports += 1
                for n in names:
                    if n.startswith("_") and not n.startswith("__") and target_module(src) != mod:
                        private.append(f"{mod} <- {src}.{n}")
    long_functions.sort(reverse=True)
    cycles = strongly_connected(graph)
    print(f"modules: {len(modules)}")
    print(f"largest function: {long_functions[0][1]} ({long_functions[0][0]} lines)")
    print(f"functions over {LONG_LINES} lines: {sum(n > LONG_LINES for n, _ in long_functions)}")
    long_code.sort(reverse=True)
    print(
        f"functions whose code (docstring excluded) is over {LONG_LINES} lines: {len(long_code)}, "
        f"{sum(one for *_, one in long_code)} of them saying why they are one piece"
        + "".join(f"\n  {name} ({n}){' one piece' if one else ''}" for n, name, one in long_code)
    )
    print(f"imports inside functions between {top}'s modules: {local_imports}")
    print(f"import cycles: {len(cycles)}" + "".join(f"\n  {' <-> '.join(sorted(c))}" for c in cycles))
    print(f"private names imported across modules: {len(private)}" + "".join(f"\n  {p}" for p in private))


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's strongly connected components of more than one module: the import cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[set[str]] = []
    sys.setrecursionlimit(10_000)

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in graph:
        if v not in index:
            visit(v)
    return out


if __name__ == "__main__":
    main(*sys.argv[1:])
