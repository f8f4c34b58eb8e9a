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
import itertools
import re
from pathlib import Path

import torch_brdf

#: low to high; a module may import its own layer or a lower one.
LAYERS = (
    {"errors", "_checks", "parallel", "data", "io", "sphere", "frame", "metrics", "linalg"},
    {"brdf", "scene", "export"},
    {"records"},
    {"transport", "manifold", "inverse", "denoise"},
    {"render"},
    {"planner"},
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


def _folder_edges(root: Path) -> dict[str, set[str]]:
    """Top-level folder (or module) -> the other top-level folders its modules import."""
    out: dict[str, set[str]] = {}
    for m, t, *_ in imports(modules(root)):
        a, b = m.split("."), t.split(".")
        if len(a) > 1 and len(b) > 1 and a[1] != b[1]:
            out.setdefault(a[1], set()).add(b[1])
    return out


def _folder_cycles(edges: dict[str, set[str]]) -> list[str]:
    """Folders that reach themselves through other folders' imports."""

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for w in edges.get(todo.pop(), ()):
                if w not in seen:
                    seen.add(w)
                    todo.append(w)
        return seen

    return sorted(f for f in edges if f in reach(f))


#: the packages below the planner (the producers it measures and what they build on); none may ask it
PRODUCERS = tuple(sorted(f for layer in LAYERS[: LAYERS.index({"planner"})] for f in layer))


def test_folder_level_flow():
    """At folder level the imports run one way: no producer imports the planner, and no folder
    reaches itself through others (as transport -> planner -> inverse -> transport once did)."""
    edges = _folder_edges(PACKAGE)
    asking = sorted(f for f in PRODUCERS if "planner" in edges.get(f, ()))
    assert not asking, f"producers that import the planner: {asking}"
    assert not _folder_cycles(edges), f"folders in an import cycle: {_folder_cycles(edges)}"


def test_the_folder_check_finds_a_producer_asking_the_planner(tmp_path):
    root = _write(
        tmp_path,
        {
            "torch_brdf/__init__.py": "",
            "torch_brdf/planner/__init__.py": "from ..inverse import solve\n",
            "torch_brdf/inverse/__init__.py": "from ..transport import run\n",
            "torch_brdf/transport/__init__.py": "def f():\n    from ..planner import gi\n",
        },
    )
    edges = _folder_edges(root)
    assert [f for f in PRODUCERS if "planner" in edges.get(f, ())] == ["transport"]
    assert _folder_cycles(edges) == ["inverse", "planner", "transport"]


#: the longest function the library may have (lines from ``def`` to its last line)
MAX_FUNCTION_LINES = 120


def _long_functions(root: Path) -> list[str]:
    out = []
    for m, path in modules(root).items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    out.append(f"{m}.{node.name} ({n} lines, line {node.lineno})")
    return sorted(out)


def test_no_function_is_over_120_lines(tmp_path):
    long = _long_functions(PACKAGE)
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (split them):\n  " + "\n  ".join(long)
    body = "".join("    x = 1\n" for _ in range(MAX_FUNCTION_LINES))
    root = _write(tmp_path, {"torch_brdf/__init__.py": "", "torch_brdf/m.py": f"def f():\n{body}"})
    assert _long_functions(root) == [f"torch_brdf.m.f ({MAX_FUNCTION_LINES + 1} lines, line 1)"]


#: the lowest layer the call-flow check follows: the producers (transport, inverse, manifold,
#: denoise) and above. The layers below are libraries every layer calls, and they call back what
#: they are handed (the tile executor a producer's tile function, a record's methods): that is
#: not the flow between the command line, the planner and the producers
FLOW_LAYER = 3


class _FolderStack:
    """A profiler that follows the torch_brdf folder (of the producers' layer and above, see
    :data:`FLOW_LAYER`) of every Python frame on this thread's stack and keeps each distinct
    folder path (consecutive frames of one folder counted once) that enters a folder twice or
    climbs back up the layers on the way down."""

    def __init__(self):
        self.stack: list[str | None] = []  # the folder of each frame (None: not torch_brdf)
        self.bad: set[tuple[str, ...]] = set()
        self.paths: set[tuple[str, ...]] = set()

    def path(self) -> tuple[str, ...]:
        out: list[str] = []
        for f in self.stack:
            if f is not None and (not out or out[-1] != f):
                out.append(f)
        return tuple(out)

    def __call__(self, frame, event, arg):
        if event == "call":
            name = frame.f_globals.get("__name__", "")
            parts = name.split(".")
            folder = parts[1] if parts[0] == "torch_brdf" and len(parts) > 1 else None
            if frame.f_code.co_name == "<module>":  # an import runs module code: not the call flow
                folder = None
            if folder is not None and (layer_of(f"torch_brdf.{folder}") or 0) < FLOW_LAYER:
                folder = None
            self.stack.append(folder)
            if folder is not None:
                path = self.path()
                self.paths.add(path)
                layers = [layer_of(f"torch_brdf.{f}") for f in path]
                if len(set(path)) < len(path) or any(b > a for a, b in itertools.pairwise(layers)):
                    self.bad.add(path)
        elif event == "return" and self.stack:
            self.stack.pop()


def test_a_planned_precompute_goes_down_once(tmp_path):
    """``torch-brdf precompute --error`` on a tiny scene: the calls go CLI -> planner ->
    transport (and lower) and back; along every call stack no folder is entered twice and the
    layers never climb back up (the planner runs the transport's pilots, not the reverse)."""
    import sys

    from typer.testing import CliRunner

    import torch_brdf.planner.gi  # noqa: F401 (imported before profiling: imports are not calls)
    from torch_brdf.cli import app

    args = ["precompute", "cornell_box_glossy", "--resolution", "8", "--error", "0.3", "--no-progress"]
    prof = _FolderStack()
    sys.setprofile(prof)
    try:
        res = CliRunner().invoke(app, [*args, "--no-resume", "--out", str(tmp_path / "t.npz")])
    finally:
        sys.setprofile(None)
    assert res.exit_code == 0, res.output
    assert not prof.bad, "call paths that enter a folder twice or climb up:\n  " + "\n  ".join(
        " -> ".join(p) for p in sorted(prof.bad)
    )
    into_transport = {p[: p.index("transport") + 1] for p in prof.paths if "transport" in p}
    assert ("cli", "planner", "transport") in into_transport


def test_the_call_check_finds_a_climb_and_a_second_entry():
    """Functions whose globals name torch_brdf folders: transport -> planner (a climb) ->
    transport (a second entry) is caught; planner -> transport -> inverse is not, nor a
    producer's function called back by a lower layer (transport -> records -> transport)."""
    import sys

    def made(folder: str):
        ns = {"__name__": f"torch_brdf.{folder}.m"}
        exec("def f(g):\n    return g()\n", ns)
        return ns["f"]

    inverse, transport, planner, records = made("inverse"), made("transport"), made("planner"), made("records")
    prof = _FolderStack()
    sys.setprofile(prof)
    try:
        planner(lambda: transport(lambda: records(lambda: transport(lambda: inverse(lambda: 1)))))
        transport(lambda: planner(lambda: transport(lambda: inverse(lambda: 1))))
    finally:
        sys.setprofile(None)
    assert ("planner", "transport", "inverse") in prof.paths
    assert not {p for p in prof.bad if p[0] == "planner"}
    assert ("transport", "planner") in prof.bad  # a climb
    assert ("transport", "planner", "transport", "inverse") in prof.bad  # a second entry
