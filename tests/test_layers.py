"""The package's rooms only point down (docs/architecture.md): foundations (the modules at the top of
`jaxpbr/`) <- `geometry` <- `io` <- `shading` <- `ibl` <- `rendering` <- `reference` <- `batch` <- `cli`. No import cycle anywhere, no room
imports a room above it, no private name crosses from one room into another, and the library never
imports its tools (`jaxpbr.cli`). The import graph is read from the source with `ast`,
function-local imports included, so an import hidden inside a function still counts."""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "jaxpbr"


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = p
    return out


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """module -> the package modules it imports (anywhere in its body, relative or absolute)."""
    return _read_imports(root)[0]


def _read_imports(root: Path = PACKAGE):
    """(graph, names): the module graph, and for each module the (source module, imported name)
    pairs of its `from ... import name` statements. Fresh copies of `_parsed_imports` (the package
    is parsed once per process and root: about a second)."""
    graph, names = _parsed_imports(root)
    return {m: set(v) for m, v in graph.items()}, {m: set(v) for m, v in names.items()}


@functools.lru_cache(maxsize=None)
def _parsed_imports(root: Path):
    mods = _modules(root)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    names: dict[str, set[tuple[str, str]]] = {m: set() for m in mods}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                # `from . import x` imports the submodule x when there is one
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in mods else mod for a in node.names]
                names[name] |= {(mod, a.name) for a in node.names if f"{mod}.{a.name}" not in mods}
            for t in targets:
                # `import jaxpbr.cli.scene_file` -> the longest known module prefix
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    graph[name].add(t)
    return graph, names


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle as a list of modules (first == last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(v):
        state[v] = 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state:
                c = visit(w)
                if c:
                    return c
        stack.pop()
        state[v] = 2
        return None

    for v in sorted(graph):
        if v not in state:
            c = visit(v)
            if c:
                return c
    return None


def test_cycle_finder_finds_cycles():
    """The checker itself can fail: a planted cycle is reported, an acyclic graph is not."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_graph_reader_sees_function_local_imports(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from . import b\n")
    (pkg / "b.py").write_text("def f():\n    from .a import x\n")
    g = import_graph(pkg)
    assert g["pkg.a"] == {"pkg.b"} and g["pkg.b"] == {"pkg.a"}
    assert find_cycle(g) is not None


def test_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_library_never_imports_the_tools():
    graph = import_graph()
    tools = {m for m in graph if m == "jaxpbr.cli" or m.startswith("jaxpbr.cli.")}
    entry = {"jaxpbr.__main__"}  # `python -m jaxpbr` is the command line's entry point
    bad = {m: sorted(graph[m] & tools) for m in graph if m not in tools | entry and graph[m] & tools}
    assert not bad, f"library modules importing jaxpbr.cli: {bad}"


def test_importing_the_library_loads_no_tool_module():
    """At run time too: `import jaxpbr` (and using it) does not load argparse-level tool code."""
    code = "import sys, jaxpbr; print(sorted(m for m in sys.modules if m.startswith('jaxpbr.cli')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("module", ["jaxpbr._numerics", "jaxpbr.shading.brdf_terms", "jaxpbr.shading.material"])
def test_kernels_are_leaves(module):
    """The kernel layer depends on nothing above it (no precompute, scene, I/O or tools)."""
    graph = import_graph()
    upper = {"jaxpbr.rendering.scene", "jaxpbr.rendering.renderer", "jaxpbr.io.image", "jaxpbr.ibl.cubeio", "jaxpbr.ibl.specular", "jaxpbr.ibl.diffuse"}
    assert not (graph[module] & upper)


#: The rooms from the bottom up; a module of a room imports only its own room and the rooms below.
ROOMS = ("jaxpbr", "jaxpbr.geometry", "jaxpbr.io", "jaxpbr.shading", "jaxpbr.ibl", "jaxpbr.rendering", "jaxpbr.reference", "jaxpbr.batch", "jaxpbr.cli")
#: Modules at the top of the package that sit above the rooms: the public namespace and entry points.
TOP = {"jaxpbr", "jaxpbr.__main__"}


def room_of(module: str) -> str:
    """The room of a module: its first-level subpackage, or the foundations (`jaxpbr`)."""
    parts = module.split(".")
    if len(parts) > 2 or (len(parts) == 2 and (PACKAGE / parts[1]).is_dir()):
        return ".".join(parts[:2])
    return "jaxpbr"


def test_every_subpackage_is_a_room():
    subpackages = {f"jaxpbr.{p.name}" for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    data = {"jaxpbr._luts", "jaxpbr._demo_sky"}  # data only: the shipped tables and the demo's baked sky
    assert subpackages - data == set(ROOMS[1:]), "add the new room to ROOMS (and docs/architecture.md)"


def test_rooms_point_down():
    graph = import_graph()
    rank = {r: i for i, r in enumerate(ROOMS)}
    bad = sorted(
        f"{m} -> {t}" for m, ts in graph.items() if m not in TOP for t in ts
        if t not in TOP and rank[room_of(t)] > rank[room_of(m)]
    )
    assert not bad, "imports pointing up the rooms: " + ", ".join(bad)
    assert not any(t in TOP for m, ts in graph.items() if m not in TOP for t in ts), "a room imports the top namespace"


def test_no_private_names_cross_rooms():
    """A name starting with `_` (or a private module) is used only inside its own room; the
    foundations' private modules (`_numerics`, `_pytree`, ...) are the shared base every room builds on."""
    graph, names = _read_imports()
    bad = sorted(
        f"{m}: {src}.{n}" for m, pairs in names.items() for src, n in pairs
        if n.startswith("_") and not n.startswith("__") and room_of(src) != room_of(m) and m not in TOP
    )
    bad += sorted(
        f"{m}: {t}" for m, ts in graph.items() for t in ts
        if t.rpartition(".")[2].startswith("_") and t.count(".") > 1 and room_of(t) != room_of(m) and m not in TOP
    )
    assert not bad, "private names imported across rooms: " + ", ".join(bad)


def test_room_checks_can_fail(tmp_path):
    """The room reader sees a planted upward import and a private name crossing rooms."""
    global PACKAGE
    pkg = tmp_path / "jaxpbr"
    for d in ("", "io", "shading"):
        (pkg / d).mkdir(exist_ok=True)
        (pkg / d / "__init__.py").write_text("")
    (pkg / "io" / "a.py").write_text("from ..shading.b import _helper\n")
    (pkg / "shading" / "b.py").write_text("def _helper(): pass\n")
    saved = PACKAGE
    PACKAGE = pkg
    try:
        graph, names = _read_imports(pkg)
        assert graph["jaxpbr.io.a"] == {"jaxpbr.shading.b"}
        assert room_of("jaxpbr.io.a") == "jaxpbr.io" and room_of("jaxpbr.shading.b") == "jaxpbr.shading"
        assert ("jaxpbr.shading.b", "_helper") in names["jaxpbr.io.a"]
    finally:
        PACKAGE = saved
