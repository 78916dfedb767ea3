"""The materials' parameters as the Rust core declares them (each model's file in ``rust/mpm/src/material/``, exported as
:func:`hybridmpm._core.material_schema`): per model, each parameter's name, the user's key (``E`` for
``youngs_modulus``, ``nu`` for ``poisson_ratio``), unit, range, default, description and source.

Every range check of a material's parameter in Python is :meth:`Param.check`: the value as the user
gave it, in float64, against the core's range, then its float32 rounding (what the solver computes
with) against the same range, so that what Python accepts the core accepts too. ``nu = 0.49999999``
is in [0, 0.5) but is 0.5 in float32: it is refused, naming the user's key and value.

>>> SCHEMA["elastic"][2].key, SCHEMA["elastic"][2].range
('nu', 'in [0, 0.5)')
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import F32_MAX


@dataclass(frozen=True)
class Param:
    """One parameter of a model (a row of ``_core.material_schema()``): ``name`` in the parameter
    dict, ``key`` the user's name of it, ``unit`` (SI; ``-`` dimensionless), ``lower``/``upper`` bounds
    (None: unbounded) and whether each is ``*_inclusive``, ``choices`` (the names a named parameter
    takes; empty for a number), ``range`` (the words a refusal uses), ``default`` (the core's),
    ``description`` and ``source``."""

    name: str
    key: str
    unit: str
    lower: float | None
    lower_inclusive: bool | None
    upper: float | None
    upper_inclusive: bool | None
    choices: tuple[str, ...]
    range: str
    default: Any
    description: str
    source: str

    def contains(self, x: float) -> bool:
        """Whether the number ``x`` is finite and in the range."""
        if not math.isfinite(x):
            return False
        if self.lower is not None and not (x > self.lower or (self.lower_inclusive and x == self.lower)):
            return False
        return self.upper is None or x < self.upper or bool(self.upper_inclusive and x == self.upper)

    def check(self, field: str, value: Any) -> Any:
        """``value`` (the user's, for ``field``: ``blocks[2].nu``) if it is in the range in float64 and
        so is its float32 rounding (the solver's precision: ``E = 1e39`` is infinite there, ``density =
        1e-300`` is 0, both refused; ``nu = 1e-110`` is 0, accepted), or one of ``choices``; else
        :class:`InvalidInputError` naming ``field`` with the value as given."""
        if self.choices:
            if not (isinstance(value, str) and value in self.choices):
                raise InvalidInputError(f"{field}: must be {self.range}, got {value!r}", field)
            return value
        ok_type = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
        if not ok_type or not math.isfinite(float(value)):
            raise InvalidInputError(f"{field}: must be a finite number, got {value!r}", field)
        if not self.contains(float(value)):
            raise InvalidInputError(f"{field}: must be {self.range}, got {value!r}", field)
        with np.errstate(over="ignore"):  # past float32's range: inf, refused just below
            f32 = float(np.float32(value))
        if not math.isfinite(f32):
            raise InvalidInputError(f"{field}: {value!r} is past float32's largest number ({F32_MAX:.4g}), the solver's precision", field)
        if not self.contains(f32):
            raise InvalidInputError(f"{field}: must be {self.range}, got {value!r} ({f32!r} in float32, the precision the solver computes in)", field)
        return value


#: Each model's parameters by model name (water, sand, elastic, snow, viscoplastic), in the order of
#: the core's parameter struct (and of the dataclasses of :mod:`hybridmpm.mpm.params`).
SCHEMA: dict[str, tuple[Param, ...]] = {
    model: tuple(Param(**{**p, "choices": tuple(p["choices"])}) for p in params) for model, params in _core.material_schema().items()
}


def check_set(where: str, model: str, values: dict[str, Any], *, by_key: bool) -> None:
    """Check every parameter of ``model`` in ``values`` (by the user's ``key`` when ``by_key``, else by
    ``name``), naming a bad one ``{where}{key or name}``. Raises :class:`InvalidInputError`."""
    for p in SCHEMA[model]:
        k = p.key if by_key else p.name
        if k in values:
            p.check(where + k, values[k])


__all__ = ["SCHEMA", "Param", "check_set"]
