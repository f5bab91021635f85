"""The ``hgsloc`` command: its parser and entry point (``parser``), one function per subcommand (``commands``),
the map/pose check (``check``) and the demo (``demo``)."""

from .parser import main

__all__ = ["main"]
