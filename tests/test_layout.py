"""The package reads top to bottom: no module-level import goes up a layer; scenes are not kept alive."""

from __future__ import annotations

import ast
import gc
import weakref
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp

ROOT = Path(__file__).resolve().parents[1]
# lower number = lower layer; a module may import only its own layer or lower ones at module level
LAYERS = {
    "kernels": 0,
    "pose": 1, "camera": 1, "fileio": 1, "scene": 1, "image": 1, "backend": 1, "kernel_load": 1,
    "costs": 2, "render": 2,
    "adapters": 3, "working_set": 3, "lod": 3,
    "refine": 4, "evaluate": 4, "noise": 4, "viz": 4,
    "check": 5,
    "distributed": 5,
    "batch": 6,
    "plugin": 7,
    "pipeline": 8,
    "hloc_step": 9, "demo": 9, "cli": 9, "__init__": 9,
}


def _modules():
    for folder, pkg in ((ROOT / "hgsloc_plugin", ""), (ROOT / "kernels", "kernels"), (ROOT / "adapters", "adapters")):
        for f in sorted(folder.rglob("*.py")):
            rel = f.relative_to(folder).with_suffix("").parts
            yield f, ((pkg,) if pkg else ()) + rel


def _layer(parts: tuple[str, ...]) -> int:
    return LAYERS[parts[0]]


def _resolve(mod_parts: tuple[str, ...], node: ast.ImportFrom) -> tuple[str, ...] | None:
    if node.level == 0:
        if not (node.module or "").startswith("hgsloc_plugin"):
            return None
        parts = tuple(node.module.split("."))[1:]
    else:
        parts = mod_parts[:-node.level] + (tuple(node.module.split(".")) if node.module else ())
    return parts or None


def test_no_module_level_import_goes_up_a_layer():
    bad = []
    for f, parts in _modules():
        if parts[-1] == "__init__" and len(parts) == 1:
            continue  # the package's public surface imports everything
        own = _layer(parts)
        for node in ast.parse(f.read_text()).body:  # module level only
            if isinstance(node, ast.ImportFrom):
                target = _resolve(parts, node)
                if target is None:
                    continue
                if target[0] == "kernels" or parts[0] == "kernels":
                    ok = parts[0] != "kernels" or target[0] == "kernels"
                else:
                    ok = _layer(target) <= own
                if not ok:
                    bad.append(f"{f.relative_to(ROOT)} imports {'.'.join(target)}")
    assert not bad, bad


def test_adapters_are_pure_io():
    allowed = {"pose", "camera", "fileio", "adapters"}
    for f, parts in _modules():
        if parts[0] != "adapters":
            continue
        for node in ast.parse(f.read_text()).body:
            if isinstance(node, ast.ImportFrom):
                target = _resolve(parts, node)
                assert target is None or target[0] in allowed, f"{f.name} imports {target}"


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
