"""Refine Marepo's 7-Scenes poses: the same loop as refine_ace_7scenes.py with LOCALIZER = "marepo".

Usage: python examples/refine_marepo_7scenes.py --dataset /data/7scenes --maps /data/3dgs_7scenes --out out/marepo
"""

import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    mod = runpy.run_path(str(Path(__file__).with_name("refine_ace_7scenes.py")), run_name="example")
    mod["LOCALIZER"] = "marepo"
    mod["main"].__globals__["LOCALIZER"] = "marepo"
    sys.exit(mod["main"]())
