"""The package layout: subpackages along the data flow, and no import cycles between modules
(imports inside functions count too: they are layering all the same)."""

from __future__ import annotations

import ast
import pathlib

import jaxplush
import jaxplush.fitting

CORE = ("jaxplush.scene", "jaxplush.model", "jaxplush.stepping", "jaxplush.io")


def _modules():
    """{module name: source path} of every module of jaxplush and jaxplush.fitting."""
    out = {}
    for pkg in (jaxplush, jaxplush.fitting):
        root = pathlib.Path(pkg.__path__[0])
        for path in root.rglob("*.py"):
            if pkg is jaxplush and "fitting" in path.relative_to(root).parts:
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([pkg.__name__] + parts)] = path
    return out


def _imports(name, path, known):
    """Modules of ``known`` that ``name`` imports anywhere in its source."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_pkg else name.split(".")[:-1]
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        out |= {t for t in targets if t in known and t != name and t != "jaxplush"}
    return out


def test_no_import_cycles():
    mods = _modules()
    graph = {m: _imports(m, p, mods) for m, p in mods.items()}
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == "open":
                cycle = stack[stack.index(n):] + [n]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_the_core_never_imports_fitting_and_lower_layers_never_import_higher_ones():
    mods = _modules()
    order = ["jaxplush.model", "jaxplush.scene", "jaxplush.io", "jaxplush.stepping"]     # lowest first
    rank = {p: i for i, p in enumerate(order)}
    for m, p in mods.items():
        pkg = next((c for c in CORE if m == c or m.startswith(c + ".")), None)
        if pkg is None:
            continue
        for n in _imports(m, p, mods):
            assert not n.startswith("jaxplush.fitting"), f"{m} imports {n}"
            npkg = next((c for c in CORE if n == c or n.startswith(c + ".")), None)
            if npkg is not None and npkg != pkg:
                assert rank[npkg] < rank[pkg], f"{m} ({pkg}) imports {n} ({npkg}), a layer above it"
