"""The package's layers only point down (docs/architecture.md): no import cycle anywhere, and the
library never imports its tools (`jaxpbr.cli`). The import graph is read from the source with
`ast`, function-local imports included, so a cycle hidden inside a function still fails."""

from __future__ import annotations

import ast
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
    mods = _modules(root)
    graph: dict[str, set[str]] = {m: set() for m in mods}
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
            for t in targets:
                # `import jaxpbr.cli.scene_file` -> the longest known module prefix
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    graph[name].add(t)
    return graph


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


@pytest.mark.parametrize("module", ["jaxpbr._numerics", "jaxpbr.brdf_terms", "jaxpbr.material"])
def test_kernels_are_leaves(module):
    """The kernel layer depends on nothing above it (no precompute, scene, I/O or tools)."""
    graph = import_graph()
    upper = {"jaxpbr.scene", "jaxpbr.renderer", "jaxpbr.image", "jaxpbr.cubeio", "jaxpbr.specular", "jaxpbr.diffuse"}
    assert not (graph[module] & upper)
