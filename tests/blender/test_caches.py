"""One cache registry: `caches.forget()` empties every module-level cache of the Blender layer.

The caches are found from the source, so a new one is checked without being listed anywhere: a
module-level name bound to an empty container (`{}`, `[]`, `set()`, `dict()`, `list()`,
`OrderedDict()`, `defaultdict(…)`, `deque()`, weak dictionaries) is state that fills at run time, and
a module-level function under `functools.lru_cache` / `functools.cache` is a memo. Each container
gets an entry, `caches.forget()` runs, and every entry must be gone: a memo whose module does not
register a clear function for it (`caches.register`) fails. A functools memo must be cleared
(`<name>.cache_clear()`) by a function of its module registered with `caches.register`.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BLENDER = ROOT / "affine_deformers" / "blender"

#: Module-level containers that are not caches (a forget must keep them), and why.
NOT_CACHES = {
    "caches._clears": "the registry of clear functions itself",
    "update.hooks._before_object": "a registry of update hooks, filled when the modules are imported",
    "update.hooks._inputs_read": "a registry of update hooks, filled when the modules are imported",
    "update.shape_pass._factors": "factors keyed on a digest of every input (never stale), kept through undo "
                           "and reload so they do not factor again; bounded, freed at unregister",
}

_EMPTY_CALLS = {"dict", "list", "set", "OrderedDict", "defaultdict", "deque", "WeakValueDictionary",
                "WeakKeyDictionary", "WeakSet"}
_FUNCTOOLS_CACHES = {"lru_cache", "cache"}
_KEY = ("entry left by tests/blender/test_caches.py",)


def _called(node: ast.expr) -> str:
    """The name a call or decorator refers to ('lru_cache' for functools.lru_cache(maxsize=4))."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _empty_container(node: ast.expr | None) -> bool:
    if isinstance(node, ast.Dict):
        return not node.keys
    if isinstance(node, ast.List | ast.Set):
        return not node.elts
    if isinstance(node, ast.Call) and _called(node) in _EMPTY_CALLS:
        # defaultdict(list) is empty; dict(a=1) or list(values) start with content
        return _called(node) == "defaultdict" or not (node.args or node.keywords)
    return False


def found_in(source: str) -> dict[str, str]:
    """The module-level caches of one module's source: name → 'container' or 'functools'."""
    found = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign | ast.AnnAssign) and _empty_container(node.value):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            found.update({t.id: "container" for t in targets if isinstance(t, ast.Name)})
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and any(
                _called(d) in _FUNCTOOLS_CACHES for d in node.decorator_list):
            found[node.name] = "functools"
    return found


def _module_name(path: Path) -> str:
    """'kinds.probe' for blender/kinds/probe.py, 'kinds' for its __init__.py, '' for blender's."""
    parts = list(path.relative_to(BLENDER).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def found_caches() -> dict[str, tuple[str, Path]]:
    """Every module-level cache of affine_deformers/blender: 'module.name' → (its kind, its file)."""
    found = {}
    for path in sorted(BLENDER.rglob("*.py")):
        module = _module_name(path)
        for name, kind in found_in(path.read_text()).items():
            found[f"{module}.{name}" if module else name] = (kind, path)
    return found


def _containers() -> list[str]:
    """The container caches (not the exempted registries), by qualified name."""
    found = found_caches()
    return sorted(n for n, (kind, _path) in found.items() if kind == "container" and n not in NOT_CACHES)


def _registered_clears_calling(path: Path, name: str) -> bool:
    """Whether a function of the module at `path` registered with `caches.register` calls
    `<name>.cache_clear()`."""
    for node in ast.parse(path.read_text()).body:
        if not isinstance(node, ast.FunctionDef) or not any(
                _called(d) == "register" for d in node.decorator_list):
            continue
        for call in ast.walk(node):
            if (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                    and call.func.attr == "cache_clear" and isinstance(call.func.value, ast.Name)
                    and call.func.value.id == name):
                return True
    return False


def _module(installed, module: str):
    return importlib.import_module(f"{installed.package}.blender" + (f".{module}" if module else ""))


def left_after_forget(installed, names: list[str]) -> list[str]:
    """Put an entry into each of the containers `names` ('module.name'), run `caches.forget()`, and
    return the names whose entry is still there (their entries are removed again)."""
    containers = {}
    for qualified in names:
        module, _, attr = qualified.rpartition(".")
        containers[qualified] = getattr(_module(installed, module), attr)
    for container in containers.values():
        if isinstance(container, dict):
            container[_KEY] = None
        elif isinstance(container, set):
            container.add(_KEY)
        else:
            container.append(_KEY)
    _module(installed, "caches").forget()
    left = []
    for qualified, container in containers.items():
        if _KEY in container:
            left.append(qualified)
            if isinstance(container, dict):
                del container[_KEY]
            else:
                container.remove(_KEY)
    return left


def test_the_scan_finds_caches_and_only_caches():
    found = found_in("a = {}\nb: dict[int, str] = {}\nc = set()\nd = []\ne = collections.OrderedDict()\n"
                     "f = defaultdict(list)\nCONSTANT = {'x': 1}\nNAMES = ['a']\ng = dict(a=1)\n"
                     "T = ()\n@functools.lru_cache(maxsize=8)\ndef h(x): return x\n"
                     "@cache\ndef i(x): return x\ndef j(): k = {}\n")
    assert found == {"a": "container", "b": "container", "c": "container", "d": "container",
                     "e": "container", "f": "container", "h": "functools", "i": "functools"}
    everything = found_caches()
    known = {"caches.signatures", "caches.errors", "update.bound._bound", "update.outputs._modifiers",
             "update.params._param_rows",
             "files.nodes._identifier_memo", "tools.weight_groups._modes", "tools.weight_groups._pending",
             "tools.weight_preview._written", "kinds.probe._rows", "kinds.probe._rest_inverses",
             "kinds.probe_tools._recorded", "kinds.weighting._surface_memo", "kinds.bone._rows",
             "kinds.bone._rest_frames", "kinds.bone._rest_inverses", "kinds.cage._last_motions",
             "kinds.cage._node_data", "kinds.cage._topologies"}
    assert known <= set(everything), sorted(known - set(everything))
    assert set(NOT_CACHES) <= set(everything), "an exemption names a container that no longer exists"


def test_forget_empties_every_module_level_cache(installed):
    containers = _containers()
    assert len(containers) >= 19
    assert left_after_forget(installed, containers) == []
    for qualified, (kind, path) in found_caches().items():
        if kind == "functools":
            name = qualified.rpartition(".")[2]
            assert _registered_clears_calling(path, name), f"{qualified}: no registered clear function"


@pytest.mark.parametrize("memo", ["tools.weight_preview._written", "kinds.probe_tools._recorded"])
def test_an_unregistered_cache_fails_the_check(installed, memo):
    """Without its module's registered clear function, the check reports the memo (and only it)."""
    caches = _module(installed, "caches")
    module = memo.rpartition(".")[0]
    prefix = f"{installed.package}.blender.{module}."
    removed = {name: clear for name, clear in caches._clears.items() if name.startswith(prefix)}
    assert removed
    containers = _containers()
    try:
        for name in removed:
            del caches._clears[name]
        assert left_after_forget(installed, containers) == [memo]
    finally:
        caches._clears.update(removed)
    assert left_after_forget(installed, containers) == []
