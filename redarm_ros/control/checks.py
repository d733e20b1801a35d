"""Validation shared by the controller's parameter dataclasses (a leaf module: imports no other
part of ``control/``, so every parameter module may use it).

The dataclasses' field lists (one ``name: float = default`` a line) look alike by shape; they are
declarations of different parameters, not repeated logic.
"""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any

from redarm_ros.errors import InvalidInputError


def check_positive(obj: Any, names: tuple[str, ...], allow_zero: tuple[str, ...] = ()) -> None:
    """Raise InvalidInputError unless every named field is finite and > 0 (>= 0 for ``allow_zero``)."""
    for name in names + allow_zero:
        v = getattr(obj, name)
        ok = isinstance(v, int | float) and math.isfinite(v) and (v >= 0.0 if name in allow_zero else v > 0.0)
        if not ok:
            bound = ">= 0" if name in allow_zero else "> 0"
            raise InvalidInputError(f"{type(obj).__name__}.{name} must be finite and {bound}, got {v!r}",
                                    field=name, value=v)


def field_names(obj: Any) -> tuple[str, ...]:
    """The names of a dataclass instance's fields, in declaration order."""
    return tuple(f.name for f in fields(obj))
