"""Refine Marepo's 7-Scenes poses: the loop of refine_ace_7scenes.py run with localizer "marepo".

Usage: python examples/refine_marepo_7scenes.py --dataset /data/7scenes --maps /data/3dgs_7scenes --out out/marepo
    [--prior-error 2.9cm --prior-rotation-error 1.04deg]
"""

import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    sys.exit(runpy.run_path(str(Path(__file__).with_name("refine_ace_7scenes.py")), run_name="example")["main"](
        "marepo"))
