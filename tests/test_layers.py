"""Layering (docs/design.md "Layers"): every ``import`` / ``from ... import`` of an mmpa module,
at any depth (function-level imports included), points down the layer table, and the import
graph of mmpa's modules has no cycle. Checked on the source with ``ast``."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "mmpa"

#: the capabilities, lowest first: each may import the ones before it
CAPABILITIES = [
    "registration",
    "perception",
    "planning",
    "fiducial_search",
    "localization",
    "calibration",
    "navigation",
    "ipe",
    "servo",
    "tasks",
]
BASE = {"core": set(), "robot": {"core"}, "maps": {"core", "robot"}}
LOWER = {"core", "robot", "maps"}
#: top-level package -> the top-level packages it may import (itself always allowed)
ALLOWED: dict[str, set[str]] = {
    **BASE,
    **{c: LOWER | set(CAPABILITIES[:i]) for i, c in enumerate(CAPABILITIES)},
    "missions": LOWER | set(CAPABILITIES),
    "backends": set(LOWER),
    "harness": LOWER | set(CAPABILITIES) | {"missions", "backends"},
    "experiments": LOWER | set(CAPABILITIES) | {"missions", "backends", "harness"},
    "apps": LOWER | set(CAPABILITIES) | {"missions", "backends", "harness", "experiments"},
    # the CLI parses, loads config and calls one app; the experiment runner, the sweep and
    # the task store are apps of their own
    "cli": {"core", "robot", "apps", "harness", "tasks"},
}
#: every layer may import the package root (``mmpa.__version__``; it imports nothing)
ROOT_PACKAGE = ""
#: imports inside functions are allowed only of the optional extras (and of mmpa modules that
#: import one at module level), and in cli/
OPTIONAL_EXTRAS = ("torch", "ray", "pyrealsense2", "rtde_control", "rtde_receive", "rtde_io")
OPTIONAL_EXTRAS += ("rclpy", "foxglove", "foxglove_sdk")


def _top_level_roots(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    roots = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def needs_an_extra(modules: dict[str, Path]) -> set[str]:
    """mmpa modules that import an optional extra at module level (so are imported lazily)."""
    return {m for m, p in modules.items() if _top_level_roots(p) & set(OPTIONAL_EXTRAS)}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def mmpa_imports(path: Path) -> list[tuple[str, str]]:
    """(imported mmpa module, where) for every import statement in ``path``, where is "top"
    (module level), "typing" (in a module-level ``if TYPE_CHECKING:`` block) or "function";
    ``from pkg import name`` imports ``pkg`` and, where it is a module, ``pkg.name``."""
    tree = ast.parse(path.read_text(), str(path))
    where = {id(n): "top" for n in tree.body}
    for n in tree.body:
        if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test):
            where |= {id(m): "typing" for m in ast.walk(n) if m is not n}
    found = []
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            subs = [f"{node.module}.{a.name}" for a in node.names]
            names = [node.module] + [m for m in subs if _is_module(m)]
        at = where.get(id(node), "function")
        found += [(n, at) for n in names if n == "mmpa" or n.startswith("mmpa.")]
    return found


def package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(SRC.rglob("*.py"))}


def layer_violations(modules: dict[str, Path]) -> dict[str, list[str]]:
    bad: dict[str, list[str]] = {}
    for mod, path in modules.items():
        pkg = package(mod)
        for imp, _ in mmpa_imports(path):
            target = package(imp)
            if target in (pkg, ROOT_PACKAGE) or target in ALLOWED.get(pkg, set()):
                continue
            bad.setdefault(mod, []).append(imp)
    # the experiments of one paper never import another paper's
    for mod, path in modules.items():
        if mod.startswith("mmpa.experiments.paper"):
            own = mod.split(".")[2]
            for imp, _ in mmpa_imports(path):
                if imp.startswith("mmpa.experiments.paper") and imp.split(".")[2] != own:
                    bad.setdefault(mod, []).append(imp)
    return bad


def _inner_imports(path: Path) -> list[str]:
    """Every module imported inside a function of ``path`` (any library)."""
    tree = ast.parse(path.read_text(), str(path))
    out: list[str] = []
    for fn in ast.walk(tree):
        if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Import):
                out += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = [f"{node.module}.{a.name}" for a in node.names]
                mods = [m for m in subs if m.startswith("mmpa.") and _is_module(m)]
                out += mods or [node.module]
    return out


def _is_module(dotted: str) -> bool:
    sub = SRC.parent / Path(*dotted.split("."))
    return sub.with_suffix(".py").exists() or sub.is_dir()


def function_level_imports(modules: dict[str, Path]) -> dict[str, list[str]]:
    """Imports inside functions outside cli/, other than of an optional extra or of an mmpa
    module that needs one (those are imported lazily on purpose)."""
    bad: dict[str, list[str]] = {}
    lazy_ok = needs_an_extra(modules)
    for mod, path in modules.items():
        if package(mod) == "cli":
            continue
        inner = [
            imp
            for imp in _inner_imports(path)
            if imp.split(".")[0] not in OPTIONAL_EXTRAS and imp not in lazy_ok
        ]
        if inner:
            bad[mod] = sorted(set(inner))
    return bad


def cycles(modules: dict[str, Path]) -> list[list[str]]:
    """Strongly connected components of more than one module in the import graph (every
    import that runs, function level included, ``TYPE_CHECKING`` blocks not; a package's
    ``__init__`` counts as its own module)."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        for imp, at in mmpa_imports(path):
            if at == "typing":
                continue
            while imp and imp not in modules:
                imp = imp.rpartition(".")[0]
            if imp and imp != mod:
                graph[mod].add(imp)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_every_import_points_down_the_layer_table() -> None:
    modules = all_modules()
    unknown = set(map(package, modules)) - set(ALLOWED) - {ROOT_PACKAGE}
    assert not unknown, f"packages missing from the layer table: {unknown}"
    assert layer_violations(modules) == {}


def test_no_import_cycles() -> None:
    assert cycles(all_modules()) == []


def test_no_imports_inside_functions_but_optional_extras_and_the_cli() -> None:
    assert function_level_imports(all_modules()) == {}


def test_the_checker_sees_a_planted_upward_import(tmp_path: Path) -> None:
    """The check can fail: an upward import planted into a copy of a core module, and a cycle
    planted between two modules, are both found."""
    modules = all_modules()
    planted = tmp_path / "geometry.py"
    planted.write_text(
        (SRC / "core" / "geometry.py").read_text() + "\nfrom mmpa.backends.twin import world\n"
    )
    modules["mmpa.core.geometry"] = planted
    assert layer_violations(modules) == {
        "mmpa.core.geometry": ["mmpa.backends.twin", "mmpa.backends.twin.world"]
    }
    planted.write_text("def f():\n    import mmpa.robot.kinematics\n")
    assert any({"mmpa.core.geometry", "mmpa.robot.kinematics"} <= set(c) for c in cycles(modules))
    assert function_level_imports(modules)["mmpa.core.geometry"] == ["mmpa.robot.kinematics"]
