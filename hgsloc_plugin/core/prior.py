"""QueryPrior: what one query may set for itself, from the API, a batch, a pose file's inlier count or Ray."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace


@dataclass(frozen=True)
class QueryPrior:
    """A query's trust region and its prior's expected (median) error; None: not set (the config's applies, else
    the automatic one). Each length has an absolute form (scene units) and a depth-relative one (a fraction of
    the query's median depth, which the refiner computes anyway); the absolute one wins when both are given.

    Attributes:
        max_shift / max_shift_depth: the camera-centre shift the refinement may make.
        max_rotation_deg: the rotation it may make (degrees).
        prior_error / prior_error_depth: the prior's expected camera-centre error; prior_error_deg: its expected
            rotation error (degrees). Given, an accepted refined pose is fused with the prior.
    """

    max_shift: float | None = None
    max_rotation_deg: float | None = None
    max_shift_depth: float | None = None
    prior_error: float | None = None
    prior_error_deg: float | None = None
    prior_error_depth: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{f.name} must be a positive number, got {v}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The field names (the per-query keywords of ``Refiner.refine`` and of a query dict)."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_mapping(cls, values: Mapping, where: str = "query") -> QueryPrior:
        """From a mapping of field names (None values: not set); an unknown name is an error naming ``where``."""
        unknown = sorted(set(values) - set(cls.names()))
        if unknown:
            raise ValueError(f"{where}: unknown keys {unknown}; per-query settings are {sorted(cls.names())}")
        return cls(**{k: v for k, v in values.items() if v is not None})

    def as_dict(self) -> dict[str, float]:
        """The fields that are set."""
        return {k: getattr(self, k) for k in self.names() if getattr(self, k) is not None}

    def shift_bound(self, depth: float) -> float | None:
        """The trust region's shift in scene units at median depth ``depth`` (None: not set)."""
        return _absolute(self.max_shift, self.max_shift_depth, depth)

    def centre_error(self, depth: float) -> float | None:
        """The prior's expected camera-centre error in scene units at median depth ``depth`` (None: not set)."""
        return _absolute(self.prior_error, self.prior_error_depth, depth)

    def deferring_to(self, config) -> QueryPrior:
        """This prior without the settings that ``config`` (a ``RefineConfig``) fixes for every query: a value
        in the config wins over one derived per query (e.g. from an inlier count)."""
        drop = {k: None for k in self.names() if getattr(config, _CONFIG_FIELD.get(k, k)) is not None}
        return replace(self, **drop)


#: the config field that fixes each depth-relative setting
_CONFIG_FIELD = {"max_shift_depth": "max_shift", "prior_error_depth": "prior_error"}


def _absolute(value: float | None, of_depth: float | None, depth: float) -> float | None:
    if value is not None:
        return value
    return None if of_depth is None else of_depth * depth
