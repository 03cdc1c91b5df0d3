"""The house rules of the package layout (docs/architecture.md), checked on the source: imports go down the stage
path and never round in a circle, the method never imports the tools, and no module holds two jobs' worth of lines.

Every ``import`` statement counts, at module level or inside a function, because a function-level import is still
a dependency; only imports of optional third-party packages are exempt, and they are not ours.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "splatreplace_ns"

# the stage path, lowest first: a module may import its own package and any package of a lower or equal rank
RANK = {
    "render": 0,
    "datamanager": 1,
    "features": 2,
    "instances": 3,
    "poses": 4,
    "template": 5,
    "eval": 6,
    "viewer": 7,
    "user_errors": 7,
    "method": 8,
    "export": 9,
    "cli": 11,  # the command line: the method and the tools side by side
    "tools": 10,
}
MAX_LINES = 500


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports_of(name: str, path: Path, known: dict) -> set:
    """The package's modules that ``name`` imports anywhere in its file (``from pkg import module`` resolved)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        for target in targets:
            while target not in known and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in known and target != name and target.startswith("splatreplace_ns."):
                out.add(target)
    return out


def graph() -> dict:
    known = modules()
    return {name: imports_of(name, path, known) for name, path in known.items()}


def stage_of(module: str) -> str:
    return module.split(".")[1]


def test_every_subpackage_and_top_module_has_a_rank():
    tops = {stage_of(m) for m in modules() if m != "splatreplace_ns"}
    assert tops <= set(RANK), f"give these a place on the stage path: {sorted(tops - set(RANK))}"


def test_imports_go_down_the_stage_path():
    upward = sorted(
        f"{a} -> {b}"
        for a, targets in graph().items() if a != "splatreplace_ns"
        for b in targets
        if RANK[stage_of(b)] > RANK[stage_of(a)]
    )
    assert not upward, "imports up the stage path:\n" + "\n".join(upward)


def test_the_method_never_imports_the_tools():
    into_tools = sorted(
        f"{a} -> {b}" for a, targets in graph().items()
        if a != "splatreplace_ns" and stage_of(a) != "tools" and stage_of(a) != "cli"
        for b in targets if stage_of(b) == "tools"
    )
    assert not into_tools, "\n".join(into_tools)


def test_no_import_circles():
    edges = graph()
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


def test_the_checker_sees_a_circle_and_an_upward_import(tmp_path, monkeypatch):
    """The rules above are only as good as the import graph they read: a planted circle and an upward import
    must show up in it."""
    pkg = tmp_path / "splatreplace_ns"
    for sub in ("render", "poses"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "render" / "a.py").write_text("def f():\n    from splatreplace_ns.poses import b\n")
    (pkg / "poses" / "b.py").write_text("from splatreplace_ns.render.a import f\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", pkg)
    edges = graph()
    assert edges["splatreplace_ns.render.a"] == {"splatreplace_ns.poses.b"}
    assert edges["splatreplace_ns.poses.b"] == {"splatreplace_ns.render.a"}


def test_no_module_holds_two_jobs():
    long = sorted(
        (n, str(p.relative_to(PACKAGE.parent))) for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    )
    assert not long, f"files over {MAX_LINES} lines: {long}"
