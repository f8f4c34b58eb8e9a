"""The import layers of torch_brdf: read every module's imports with
``ast`` -- absolute and relative, at module level and inside functions -- and fail on an
import that runs back up the layers, on an import cycle between modules, and on a
subpackage or top-level module that belongs to no layer.

Importing ``a.b.c`` runs ``a/__init__`` and ``a/b/__init__`` first, so an import also
depends on the target's parent packages. A package's ``__init__`` importing its own
submodules, and a submodule importing a package it lives in, is how packages work, not a
cycle: an edge from a module to one of its own enclosing packages is left out of the cycle
search (the edge from the ``__init__`` down to the submodule stays, so a cycle that enters a
package through its ``__init__`` from outside is still found).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import torch_brdf

#: low to high; a module may import its own layer or a lower one.
LAYERS = (
    {"errors", "_checks", "parallel", "data", "io", "sphere", "frame", "metrics", "linalg"},
    {"brdf", "scene", "export"},
    {"records"},
    {"transport", "manifold", "inverse", "denoise", "planner"},
    {"render"},
    {"cli", "editor", "report", "__main__"},
)


def layer_of(module: str) -> int | None:
    """Layer of a dotted module name ``torch_brdf.<top>...`` by its top component (None: none)."""
    parts = module.split(".")
    if len(parts) < 2:
        return None
    return next((i for i, names in enumerate(LAYERS) if parts[1] in names), None)


def modules(root: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of the package at ``root`` (a package's name is its ``__init__``)."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts) + 1)]


def imports(mods: dict[str, Path]) -> list[tuple[str, str, int, bool]]:
    """Every (importer, imported module, line, named) between the package's modules: the modules
    an import names (``named``) and the parent packages that it runs as well."""
    edges = set()
    for m, path in mods.items():
        package = m.split(".") if path.name == "__init__.py" else m.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                named = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    if node.level - 1 > len(package):
                        raise AssertionError(f"{path}:{node.lineno}: relative import beyond the top package")
                    base = package[: len(package) - (node.level - 1)]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                named = [source] + [f"{source}.{a.name}" for a in node.names]
            else:
                continue
            for name in named:
                for target in _with_parents(name):
                    if target in mods and target != m:
                        edges.add((m, target, node.lineno, target == name))
    return sorted(edges)


def upward(edges) -> list[str]:
    """Imports of a higher layer than the importer's, as ``importer -> imported (line n)``."""
    out = []
    for m, t, line, named in edges:
        lm, lt = layer_of(m), layer_of(t)
        if named and lm is not None and lt is not None and lt > lm:
            out.append(f"{m} -> {t} (line {line})")
    return out


def cycles(edges) -> list[list[str]]:
    """Strongly connected groups of more than one module (iterative Tarjan), each sorted,
    without the edges from a module to its own enclosing packages."""
    graph: dict[str, set[str]] = {}
    for m, t, *_ in edges:
        graph.setdefault(t, set())
        if not m.startswith(t + "."):
            graph.setdefault(m, set()).add(t)
        else:
            graph.setdefault(m, set())
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                group = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    group.append(w)
                    if w == v:
                        break
                if len(group) > 1:
                    found.append(sorted(group))
    return sorted(found)


def unlayered(mods: dict[str, Path]) -> list[str]:
    """Top-level modules and subpackages of the package that belong to no layer."""
    return sorted({m.split(".")[1] for m in mods if "." in m and layer_of(m) is None})


def _report(root: Path) -> tuple[list[str], list[list[str]], list[str]]:
    mods = modules(root)
    edges = imports(mods)
    return upward(edges), cycles(edges), unlayered(mods)


PACKAGE = Path(torch_brdf.__file__).parent


def test_no_import_runs_up_the_layers():
    up, _, _ = _report(PACKAGE)
    assert not up, "imports that run back up the layers:\n  " + "\n  ".join(up)


def test_no_import_cycles():
    _, found, _ = _report(PACKAGE)
    assert not found, "import cycles:\n  " + "\n  ".join(" <-> ".join(c) for c in found)


def test_every_subpackage_is_in_a_layer():
    _, _, loose = _report(PACKAGE)
    assert not loose, f"in no layer (add them to LAYERS here and in STYLE.md): {loose}"


def test_package_docstring_lists_every_subpackage():
    """One line per public subpackage and top-level module, and no line for one that is gone."""
    mods = modules(PACKAGE)
    public = {m.split(".")[1] for m in mods if "." in m and not m.split(".")[1].startswith("_")}
    cited = set(re.findall(r"^\* :mod:`torch_brdf\.(\w+)`", torch_brdf.__doc__, re.MULTILINE))
    assert cited == public, f"missing from the package docstring: {public - cited}; gone: {cited - public}"


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root / "torch_brdf"


def test_the_checker_finds_upward_imports_cycles_and_loose_packages(tmp_path):
    """A made-up package with one of each fault: upward
    imports (absolute, one inside a function), a cycle hidden in a function body, a loose subpackage;
    and the patterns that are fine: an __init__ importing its submodules that import it back."""
    root = _write(
        tmp_path,
        {
            "torch_brdf/__init__.py": "from . import errors\n",
            "torch_brdf/errors.py": "def f():\n    import torch_brdf.brdf.bands\n",
            "torch_brdf/metrics.py": "from .errors import *\nimport torch_brdf\n",
            "torch_brdf/render/__init__.py": "from .record import BasisImage\n",
            "torch_brdf/render/record.py": "from ..errors import *\nfrom ..render import helper\n",
            "torch_brdf/transport/__init__.py": "from . import polynomial\n",
            "torch_brdf/transport/polynomial.py": "from torch_brdf.render.record import BasisImage\n",
            "torch_brdf/brdf/__init__.py": "from .bands import *\nfrom .band_albedo import *\n",
            "torch_brdf/brdf/bands.py": "def f():\n    from .band_albedo import g\n",
            "torch_brdf/brdf/band_albedo.py": "from . import bands\n",
            "torch_brdf/brdf/base.py": "from .. import metrics\n",
            "torch_brdf/gizmo/__init__.py": "",
        },
    )
    up, found, loose = _report(root)
    assert up == [
        "torch_brdf.errors -> torch_brdf.brdf.bands (line 2)",
        "torch_brdf.transport.polynomial -> torch_brdf.render.record (line 1)",
    ]
    assert found == [["torch_brdf.brdf.band_albedo", "torch_brdf.brdf.bands"]]
    assert loose == ["gizmo"]
    # a cycle that enters a package through its __init__ from outside is a cycle
    (root / "render" / "record.py").write_text("from ..transport import polynomial\n")
    _, found, _ = _report(root)
    assert [
        "torch_brdf.render",
        "torch_brdf.render.record",
        "torch_brdf.transport",
        "torch_brdf.transport.polynomial",
    ] in found
