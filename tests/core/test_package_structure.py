"""The package's shape, checked from its source (no Blender needed): no import cycle, no bpy below the
Blender layer, no function of 100 lines or more, no module over 700 lines, blender/ grouped into
subpackages by role, and docs/DEVELOPING.md's module map naming exactly the modules in the tree."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "affine_deformers"
MAX_FUNCTION_LINES = 100
MAX_MODULE_LINES = 700  # issue #49: no module over 700 lines anywhere in the package
MAX_LOOSE_BLENDER_MODULES = 12  # issue #49: blender/ is grouped into subpackages by role


def _modules() -> dict[str, Path]:
    """Dotted name under the package ('blender.kinds.probe', 'core', …) → file."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules `name` imports, anywhere in the file (function-level imports included:
    they are cycles too, only deferred)."""
    is_package = path.name == "__init__.py"
    base = name.split(".") if is_package else name.split(".")[:-1]
    if name == "":
        base = []
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom) or node.level == 0:
            continue
        anchor = base[: len(base) - (node.level - 1)] if node.level > 1 else list(base)
        target = ".".join([*anchor, *(node.module.split(".") if node.module else [])])
        for alias in node.names:
            # `from .pkg import name`: the submodule pkg.name when there is one, else pkg itself
            sub = f"{target}.{alias.name}".lstrip(".")
            candidate = sub if sub in modules else target
            if candidate in modules and candidate != name:
                found.add(candidate)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def test_the_import_walk_sees_imports():
    graph = _graph()
    assert "blender.kinds.base" in graph["blender.kinds.probe"]
    assert "core.aff3" in graph["blender.update.params"]
    assert "blender.kinds" in graph["blender.binding"]


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (a list of modules, first repeated last), or None. A package importing its own
    submodules (kinds/__init__ → kinds.probe) is not a cycle unless a submodule imports it back."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_no_import_cycle():
    assert _cycle(_graph()) is None


def test_the_cycle_finder_finds_one():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


@pytest.mark.parametrize("layer", ["core", "accel"])
def test_no_bpy_below_the_blender_layer(layer):
    for path in (PACKAGE / layer).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            assert not any(n.split(".")[0] in ("bpy", "mathutils", "bmesh") for n in names), path


def _functions():
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                yield path.relative_to(ROOT), node.name, node.end_lineno - node.lineno + 1


def test_no_function_of_100_lines_or_more():
    long = [f"{path}:{name} ({n} lines)" for path, name, n in _functions() if n >= MAX_FUNCTION_LINES]
    assert not long


def test_no_module_over_700_lines():
    long = [f"{path.relative_to(ROOT)} ({n} lines)" for path in sorted(PACKAGE.rglob("*.py"))
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES]
    assert not long


def test_the_blender_layer_is_grouped_by_role():
    """At most 12 modules lie loose in blender/; the rest sit in subpackages named for their role."""
    blender = PACKAGE / "blender"
    loose = sorted(p.name for p in blender.glob("*.py"))
    assert len(loose) <= MAX_LOOSE_BLENDER_MODULES, loose
    groups = sorted(p.name for p in blender.iterdir() if (p / "__init__.py").exists())
    assert groups == ["files", "kinds", "tools", "ui", "update"], groups


def _module_map() -> dict[str, set[str]]:
    """Module files named in DEVELOPING.md, per layer section ('## affine_deformers.<layer>'), from
    its bullets starting with `file.py` (or `pkg/file.py`)."""
    text = (ROOT / "docs" / "DEVELOPING.md").read_text()
    out: dict[str, set[str]] = {}
    for section in re.split(r"^## ", text, flags=re.MULTILINE):
        match = re.match(r"affine_deformers\.(\w+)", section)
        if match:
            out[match.group(1)] = set(re.findall(r"^- `([\w/]+\.py)`", section, flags=re.MULTILINE))
    return out


def test_developing_module_map_matches_the_tree():
    named = _module_map()
    layers = sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert layers == ["accel", "blender", "core"]
    for layer in layers:
        files = {str(p.relative_to(PACKAGE / layer)) for p in (PACKAGE / layer).rglob("*.py")}
        assert named.get(layer) == files, (layer, sorted(files - named.get(layer, set())),
                                           sorted(named.get(layer, set()) - files))
