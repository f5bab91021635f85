"""The embedded default: a procedural room scene, synthetic queries, and the ``hgsloc demo`` runner."""

from .scene import make_room_scene

__all__ = ["make_room_scene"]
