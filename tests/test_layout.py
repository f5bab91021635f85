"""The package reads top to bottom: no import goes up a layer or closes a circle, no module is a hub, scenes
are not kept alive."""

from __future__ import annotations

import ast
import gc
import weakref
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp

ROOT = Path(__file__).resolve().parents[1]
# lower number = lower layer; a module may import only its own layer or lower ones (function-level imports too).
# The layers are the package's folders (``hgsloc_plugin/<folder>/``), ``kernels`` and ``adapters`` installed as
# subpackages, and the two modules at the root: the public surface and the hloc step.
LAYERS = {
    "kernels": 0,
    "core": 1,
    "render": 2,
    "adapters": 3,
    "refine": 4, "evaluation": 4,
    "run": 5,
    "cli": 6, "hloc_step": 6, "__init__": 6,
}
#: the command and batch layer, which nothing in adapters/, kernels/ or refine/ may import
TOP = {"cli", "hloc_step", "run"}
#: what adapters/ may import besides itself: the core types
ADAPTER_DEPS = {("core", "pose"), ("core", "camera"), ("core", "fileio"), ("core", "prior")}
#: modules at the package's root (the rest lives in the layer folders)
ROOT_MODULES = {"__init__", "hloc_step"}
MAX_LINES = 400


def _modules():
    for folder, pkg in ((ROOT / "hgsloc_plugin", ""), (ROOT / "kernels", "kernels"), (ROOT / "adapters", "adapters")):
        for f in sorted(folder.rglob("*.py")):
            rel = f.relative_to(folder).with_suffix("").parts
            yield f, ((pkg,) if pkg else ()) + rel


MODULES = dict((parts, f) for f, parts in _modules())


def _layer(parts: tuple[str, ...]) -> int:
    return LAYERS[parts[0]]


def _as_module(parts: tuple[str, ...]) -> tuple[str, ...]:
    """An import target as a module of the package: a package's ``__init__`` for a package."""
    return parts if parts in MODULES else parts + ("__init__",)


def _imports(f: Path, parts: tuple[str, ...]):
    """Every import of the package by module ``parts`` (function-level and TYPE_CHECKING ones included): the
    target modules, a ``from pkg import submodule`` resolved to the submodule."""
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    for node in ast.walk(ast.parse(f.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if not (node.module or "").startswith("hgsloc_plugin"):
                    continue
                base = tuple(node.module.split("."))[1:]
            else:
                up = package[:len(package) - (node.level - 1)] if node.level > 1 else package
                base = up + (tuple(node.module.split(".")) if node.module else ())
            subs = [base + (a.name,) for a in node.names if base + (a.name,) in MODULES
                    or base + (a.name, "__init__") in MODULES]
            for t in subs or [base]:
                if t:
                    yield _as_module(t)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("hgsloc_plugin."):
                    yield _as_module(tuple(a.name.split("."))[1:])


GRAPH = {parts: sorted(set(_imports(f, parts)) - {parts}) for parts, f in MODULES.items()}


def test_no_import_goes_up_a_layer():
    bad = []
    for parts, targets in GRAPH.items():
        if parts == ("__init__",):
            continue  # the package's public surface imports everything
        for target in targets:
            if target[0] == "kernels" or parts[0] == "kernels":
                ok = parts[0] != "kernels" or target[0] == "kernels"
            else:
                ok = _layer(target) <= _layer(parts)
            if not ok:
                bad.append(f"{'/'.join(parts)} imports {'.'.join(target)}")
    assert not bad, bad


def test_lower_packages_never_import_the_command_layer():
    lower = ("adapters", "kernels", "refine")
    bad = [f"{'/'.join(p)} imports {'.'.join(t)}" for p, ts in GRAPH.items() if p[0] in lower
           for t in ts if t[0] in TOP]
    assert not bad, bad


def test_adapters_are_pure_io():
    bad = [f"{'/'.join(p)} imports {'.'.join(t)}" for p, ts in GRAPH.items() if p[0] == "adapters"
           for t in ts if t[0] != "adapters" and t[:2] not in ADAPTER_DEPS]
    assert not bad, bad


def test_the_folders_are_the_layers():
    """Every module lives in a layer's folder, but the public surface and the hloc step at the root (at most 10
    modules there)."""
    root = {f.stem for f in (ROOT / "hgsloc_plugin").glob("*.py")}
    folders = {d.name for d in (ROOT / "hgsloc_plugin").iterdir() if (d / "__init__.py").exists()}
    assert root == ROOT_MODULES and len(root) <= 10
    assert folders | {"kernels", "adapters"} | ROOT_MODULES == set(LAYERS)


def test_no_import_circle():
    state: dict = {}
    cycles = []

    def visit(node, path):
        state[node] = 1
        for t in GRAPH.get(node, []):
            if state.get(t) == 1:
                cycles.append(path[path.index(t):] + [t] if t in path else [node, t])
            elif t not in state:
                visit(t, path + [t])
        state[node] = 2

    for m in GRAPH:
        if m not in state:
            visit(m, [m])
    assert not cycles, [" -> ".join("/".join(p) for p in c) for c in cycles]


def test_the_layer_test_sees_function_level_imports(tmp_path):
    """An import inside a function or under TYPE_CHECKING counts (the old module-level test missed them)."""
    f = tmp_path / "m.py"
    f.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..refine import plan\n"
                 "def f():\n    from hgsloc_plugin.cli import main\n")
    assert set(_imports(f, ("adapters", "m"))) == {("cli", "__init__"), ("refine", "plan")}
    assert ("render", "__init__") in GRAPH[("refine", "routes")]


def test_no_module_over_400_lines():
    long = {"/".join(p): n for p, f in MODULES.items() if (n := len(f.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_scene_is_released_when_the_caller_drops_it():
    from .conftest import random_scene

    scene = random_scene(n=50, seed=1)
    ref = weakref.ref(scene)
    refiner = hp.HGSLocPlugin(scene)
    cam = hp.Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    assert np.isfinite(hp.render(scene, cam, hp.Pose.identity())).all()
    del scene, refiner
    gc.collect()
    assert ref() is None, "the renderer cache kept the scene alive"



def _private_reaches(f: Path) -> list[str]:
    """``x._name`` on another object than ``self`` / ``cls`` and ``from m import _name`` in file ``f``; an object of
    the accessing class's own kind (a class that sets or defines ``_name`` itself) may be reached."""
    outside = {"taichi", "gsplat"}  # their privates: the kernels' launcher and the reference renderer need them
    tree = ast.parse(f.read_text())
    found = []
    foreign = {a.asname or a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
               for a in n.names if ((n.module or "") if isinstance(n, ast.ImportFrom) else a.name).split(".")[0]
               in outside}

    def own_names(cls: ast.ClassDef) -> set[str]:
        names = {n.name for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        for n in ast.walk(cls):
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "self":
                names.add(n.attr)
            elif (isinstance(n, ast.Call) and getattr(n.func, "attr", None) == "__setattr__" and len(n.args) > 1
                  and isinstance(n.args[1], ast.Constant)):
                names.add(n.args[1].value)
        return names

    def visit(node, own: set[str]):
        for child in ast.iter_child_nodes(node):
            mine = own | own_names(child) if isinstance(child, ast.ClassDef) else own
            if (isinstance(child, ast.Attribute) and child.attr.startswith("_") and not child.attr.startswith("__")
                    and not (isinstance(child.value, ast.Name) and child.value.id in ("self", "cls", *foreign))
                    and child.attr not in own):
                found.append(f"{f.relative_to(ROOT)}:{child.lineno}: .{child.attr}")
            elif isinstance(child, ast.ImportFrom) and (child.module or "").split(".")[0] not in outside:
                found.extend(f"{f.relative_to(ROOT)}:{child.lineno}: import {a.name}" for a in child.names
                             if a.name.startswith("_") and not a.name.startswith("__"))
            visit(child, mine)

    visit(tree, set())
    return found


def test_no_reach_into_another_modules_or_objects_private_names():
    """A name that starts with ``_`` is used only in its own module, and as an attribute only on ``self``, ``cls`` or
    an object of the same class: in the package, its tests and the benchmarks."""
    bad = [r for folder in ("hgsloc_plugin", "kernels", "adapters", "tests", "benchmarks")
           for f in sorted((ROOT / folder).rglob("*.py")) for r in _private_reaches(f)]
    assert not bad, bad


def test_the_reach_test_sees_a_reach(tmp_path):
    f = ROOT / "tests" / "_reach_probe.py"
    try:
        f.write_text("class A:\n    def __init__(self):\n        self._x = 1\n\n    def same(self, o):\n"
                     "        return o._x\n\n\ndef other(r):\n    return r._workspace\n")
        assert _private_reaches(f) == ["tests/_reach_probe.py:10: ._workspace"]
    finally:
        f.unlink()


#: names a docstring may quote that are not the project's (other packages, data files)
FOREIGN = {"math", "ti", "kernel_impl", "np", "torch", "pycolmap", "kornia", "Ndarray", "taichi", "gsplat", "os", "sys"}


def _defined_names() -> tuple[set[str], set[str]]:
    """(every name the project defines: classes, functions, arguments, assigned names and attributes; every file
    name and module of it)."""
    names, files = set(), set()
    for folder in ("hgsloc_plugin", "kernels", "adapters", "tests", "benchmarks", "examples"):
        for f in (ROOT / folder).rglob("*.py"):
            files |= {f.name, f.stem, f.parent.name}
            for n in ast.walk(ast.parse(f.read_text())):
                if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    names.add(n.name)
                elif isinstance(n, ast.arg):
                    names.add(n.arg)
                elif isinstance(n, (ast.Name, ast.Attribute)) and isinstance(n.ctx, ast.Store):
                    names.add(n.id if isinstance(n, ast.Name) else n.attr)
    files |= {p.name for p in ROOT.rglob("*.md") if ".venv" not in p.parts}
    return names, files


def test_every_name_a_docstring_quotes_exists():
    """A docstring's ``module.name``, ``name()`` and ``file.py`` name something of the project that exists (a
    rename that left its old name in a docstring is found here)."""
    import re

    names, files = _defined_names()
    bad = []
    for parts, f in MODULES.items():
        for n in ast.walk(ast.parse(f.read_text())):
            if not isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                continue
            for m in re.finditer(r"``([A-Za-z_][\w.]*?)(\(\))?``", ast.get_docstring(n) or ""):
                q = m.group(1)
                dotted = q.split(".")
                if dotted[0] in FOREIGN:
                    continue
                if q.endswith((".py", ".md")):
                    ok = q.split("/")[-1] in files
                elif m.group(2) or len(dotted) > 1:
                    ok = dotted[-1] in names | files or q.endswith((".json", ".txt", ".png", ".ply", ".pkl"))
                else:
                    continue
                if not ok:
                    bad.append(f"{'/'.join(parts)}: {q}")
    assert not bad, bad
