"""The package's layout: imports point down the stages (docs/architecture.md) and form no cycle, imports inside functions included."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "tactiled"

# what each stage may import besides itself; "base" is the package's top-level modules (errors, config, extras, version)
ALLOWED: dict[str, set[str]] = {
    "base": set(),
    "board": {"base"},
    "files": {"base", "board"},
    "core": {"base"},
    "run": {"base", "board", "files", "core"},
    "learn": {"base", "core", "files", "run"},
    "sim": {"base", "board", "files"},
    "service": {"base", "board", "files", "core", "run", "learn"},
    "apps": {"base"},
    "cli": {"base", "board", "files", "core", "run", "learn", "sim", "service", "apps"},
}


def module_name(path: Path) -> str:
    """``tactiled.core.pipeline`` for tactiled/core/pipeline.py; a package's ``__init__`` is the package."""
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def stage_of(module: str) -> str:
    """The stage folder a module lives in (``base`` for tactiled's top-level modules; ``python -m tactiled`` is the CLI)."""
    if module == "tactiled.__main__":
        return "cli"
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and (PKG / parts[1]).is_dir() else "base"


def import_graph() -> dict[str, set[str]]:
    """Module -> the tactiled modules it imports anywhere in its body (``from pkg import module`` resolves to the module)."""
    paths = {module_name(p): p for p in PKG.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for mod, path in paths.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.split(".")[0] == "tactiled":
                names = [f"{node.module}.{a.name}" for a in node.names]
                deps.update(n for n in names if n in paths)
                if not any(n in paths for n in names):
                    deps.add(node.module)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.split(".")[0] == "tactiled")
        graph[mod] = {d for d in deps if d in paths and d != mod}
    return graph


def test_imports_point_down_the_stages() -> None:
    graph = import_graph()
    upward = [f"{a} -> {b}" for a, deps in graph.items() for b in deps
              if stage_of(a) != stage_of(b) and stage_of(b) not in ALLOWED[stage_of(a)]]
    assert not upward, "imports against the stages: " + ", ".join(sorted(upward))
    assert set(ALLOWED) >= {stage_of(m) for m in graph}, "a stage folder without rules in ALLOWED"


def test_no_import_cycle() -> None:
    graph = import_graph()
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(" -> ".join([*stack[stack.index(d):], d]))
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles: " + "; ".join(cycles)


def test_the_graph_sees_function_level_imports() -> None:
    graph = import_graph()
    assert graph["tactiled.cli.cmd_live"] >= {"tactiled.service.daemon"} and graph["tactiled.cli.cmd_learn"] >= {"tactiled.learn.train"}


def missing_docstrings(root: Path) -> list[str]:
    """``path: module`` and ``path:line: Class.name`` of every public definition under ``root`` without a docstring.

    Modules, module-level functions and classes, and the methods and nested classes of public classes; a name starting
    with ``_`` (``__init__`` included) is skipped, with whatever it holds.
    """
    missing: list[str] = []

    def walk(path: Path, body: list[ast.stmt], prefix: str) -> None:
        for node in body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef) and not node.name.startswith("_"):
                if not ast.get_docstring(node):
                    missing.append(f"{path}:{node.lineno}: {prefix}{node.name}")
                if isinstance(node, ast.ClassDef):
                    walk(path, node.body, f"{prefix}{node.name}.")

    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        shown = path.relative_to(PKG.parent)
        if not ast.get_docstring(tree):
            missing.append(f"{shown}: module")
        walk(shown, tree.body, "")
    return missing


def test_every_public_definition_has_a_docstring() -> None:
    missing = [m for root in (PKG, PKG.parent / "clients" / "tactiled_client") for m in missing_docstrings(root)]
    assert not missing, f"{len(missing)} public definitions without a docstring:\n" + "\n".join(missing)
