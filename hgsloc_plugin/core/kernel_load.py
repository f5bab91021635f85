"""Faster kernel loading: Taichi's Python front end memoised where it repeats itself.

Taichi 1.7 translates every kernel's Python AST in each new process, also when its offline cache then finds the
compiled kernel on disk. For each AST node it visits, the translator first formats the node's source position
(``ASTTransformerContext.get_pos_info``: the source line wrapped by ``textwrap`` with a caret line under it, the
text of a compile error), and it visits a node once per unrolled iteration (``ti.static`` loops) and per inlined
call of a ``ti.func``: in the pose-derivative kernels the same few hundred nodes are formatted about 100,000
times (what that costs: ``benchmarks/defaults.md``).

:func:`memoize_source_info` wraps ``get_pos_info`` with a cache keyed on everything the text is made of (file,
function, line offset, indentation, node type and span, the source lines of the span), so each distinct text
is formatted once; the strings, and so compile errors, are unchanged. It is applied by ``backend.init``
before Taichi starts, only on Taichi 1.7 (the version this package pins, whose internals it was written
against); ``HGSLOC_TAICHI_MEMO=0`` turns it off.
"""

from __future__ import annotations

import logging
import os

logger = logging.getLogger("hgsloc_plugin")

_installed = False


def memoize_source_info() -> bool:
    """Install the cache on Taichi's ``get_pos_info``; True when it is (or already was) installed."""
    global _installed
    if _installed:
        return True
    if os.environ.get("HGSLOC_TAICHI_MEMO", "1") == "0":
        return False
    try:
        import taichi
        from taichi.lang.ast import ast_transformer_utils as utils
    except ImportError:  # pragma: no cover - taichi is a dependency
        return False
    ctx_cls = getattr(utils, "ASTTransformerContext", None)
    original = getattr(ctx_cls, "get_pos_info", None)
    version = tuple(getattr(taichi, "__version__", ()))[:2]
    if version != (1, 7) or original is None:
        logger.debug("Taichi %s: source-position cache not installed", version)
        return False
    cache: dict = {}

    def get_pos_info(self, node):
        lo = node.lineno - 1
        hi = getattr(node, "end_lineno", None) or node.lineno
        key = (self.file, self.func.func.__name__, self.lineno_offset, self.indent, type(node).__name__,
               node.lineno, hi, node.col_offset, getattr(node, "end_col_offset", None), tuple(self.src[lo:hi]))
        text = cache.get(key)
        if text is None:
            text = cache[key] = original(self, node)
        return text

    get_pos_info.__wrapped__ = original
    get_pos_info.cache = cache
    ctx_cls.get_pos_info = get_pos_info
    _installed = True
    return True
