"""Kernel loading (``hgsloc_plugin/core/kernel_load.py``): the memoised source positions change no compile error and
are reused across the repeated visits of unrolled loops; the CPU backend compiles without Taichi's
control-flow-graph pass (``backend.py``).

No ``from __future__ import annotations`` here: Taichi reads the kernel annotations as objects."""


import os
import subprocess
import sys
import textwrap

import pytest
import taichi as ti

import hgsloc_plugin as hp

BROKEN = textwrap.dedent("""
    import taichi as ti
    import hgsloc_plugin as hp
    from hgsloc_plugin.core import kernel_load

    hp.init("cpu")

    @ti.kernel
    def broken(n: ti.i32) -> ti.f32:
        s = 0.0
        for i in ti.static(range(4)):
            s += ti.cast(n, ti.f32) * i
        for i in ti.static(range(3)):
            s += not_defined_anywhere * i
        return s

    print("memo", kernel_load._installed)
    try:
        broken(3)
    except Exception as exc:
        print(type(exc).__name__)
        print(str(exc))
""")


def _compile_error(tmp_path, memo: str) -> list[str]:
    script = tmp_path / "broken_kernel.py"
    script.write_text(BROKEN)
    env = dict(os.environ, HGSLOC_TAICHI_MEMO=memo, HGSLOC_ARCH="cpu")
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    return p.stdout.splitlines()


def test_compile_errors_read_the_same_with_the_memo(tmp_path):
    off = _compile_error(tmp_path, "0")
    on = _compile_error(tmp_path, "1")
    assert off[0] == "memo False" and on[0] == "memo True"
    assert on[1:] == off[1:]  # the same exception and text
    text = "\n".join(on[1:])
    line = BROKEN.splitlines().index("        s += not_defined_anywhere * i") + 1
    assert "broken_kernel.py" in text and f"line {line}" in text and "not_defined_anywhere" in text


def test_unrolled_visits_reuse_the_formatted_positions():
    import taichi as ti
    from taichi.lang.ast import ast_transformer_utils as utils

    hp.init()
    memo = utils.ASTTransformerContext.get_pos_info
    assert hasattr(memo, "cache"), "the memo is installed by hp.init on Taichi 1.7"
    calls = []

    def counting(self, node):
        calls.append(1)
        return memo(self, node)

    @ti.kernel
    def unrolled(x: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(x.shape[0]):
            s = 0.0
            for k in ti.static(range(24)):
                s += x[i] * k + ti.sin(x[i] + k)
            x[i] = s

    before = len(memo.cache)
    utils.ASTTransformerContext.get_pos_info = counting
    try:
        a = ti.ndarray(ti.f32, (3,))
        unrolled(a)
    finally:
        utils.ASTTransformerContext.get_pos_info = memo
    added = len(memo.cache) - before
    assert len(calls) > 24 * 5  # every unrolled iteration visits the body's nodes again
    assert 0 < added < len(calls) / 10  # ... but each distinct node is formatted once


def test_cpu_backend_starts_without_the_cfg_pass():
    """The pass took most of the compile time (``benchmarks/startup_cold.md``); CUDA keeps Taichi's default."""
    arch = hp.init()
    if arch != "cpu":
        pytest.skip("the setting is the CPU backend's")
    assert ti.lang.impl.current_cfg().cfg_optimization is False
