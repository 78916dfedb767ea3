"""The settings of a training run: a dataclass base whose fields carry their
own checks, so that every bad value is refused naming its field, and the
rule by which a run directory is resumed only by the settings that made it.

A family's settings subclass :class:`RunConfig` and declare each checked
field with :func:`setting`::

    @dataclass
    class GridTrainConfig(RunConfig):
        out: str
        steps: int = setting(20000, integer(1))
        lr: float = setting(1e-3, number(0, low_open=True))

:meth:`RunConfig.validate` runs every field's check in declaration order, then
the subclass's :meth:`RunConfig.check` (rules between fields), and raises
:class:`~hybridmpm.errors.InvalidInputError` whose ``field`` is the field's
name.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import MISSING, asdict, dataclass
from typing import Any, ClassVar

from hybridmpm.errors import InvalidInputError
from hybridmpm.train.distributed import check_nproc

#: A field's check: ``check(value, name)`` raises :class:`InvalidInputError` naming ``name``, or returns.
Check = Callable[[Any, str], None]


def setting(default: Any = MISSING, check: Check | None = None, *, factory: Callable[[], Any] | None = None) -> Any:
    """A dataclass field with ``default`` (or a ``factory`` for a mutable
    default) whose value :meth:`RunConfig.validate` checks with ``check``."""
    meta = {"check": check} if check is not None else {}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def integer(low: int, high: int | None = None) -> Check:
    """An int (not a bool) in ``[low, high]`` (``high`` None: no upper bound)."""

    def check(v: Any, name: str) -> None:
        if isinstance(v, bool) or not isinstance(v, int) or v < low or (high is not None and v > high):
            span = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise InvalidInputError(f"{name}: must be an integer {span}, got {v!r}", name)

    return check


def number(low: float | None = None, high: float | None = None, *, low_open: bool = False, high_open: bool = False, unit: str = "") -> Check:
    """A finite int or float (not a bool) within the bounds given (each closed
    unless ``low_open``/``high_open``); ``unit`` is named in the message."""

    def check(v: Any, name: str) -> None:
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
        if ok and low is not None:
            ok = v > low if low_open else v >= low
        if ok and high is not None:
            ok = v < high if high_open else v <= high
        if not ok:
            if low is not None and high is not None:
                span = f" in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            elif low is not None:
                span = f" {'>' if low_open else '>='} {low:g}"
            elif high is not None:
                span = f" {'<' if high_open else '<='} {high:g}"
            else:
                span = ""
            raise InvalidInputError(f"{name}: must be a number{span}{f' {unit}' if unit else ''}, got {v!r}", name)

    return check


def optional(inner: Check) -> Check:
    """None, or a value that passes ``inner``."""

    def check(v: Any, name: str) -> None:
        if v is not None:
            inner(v, name)

    return check


def flag(v: Any, name: str) -> None:
    """A bool."""
    if not isinstance(v, bool):
        raise InvalidInputError(f"{name}: must be true or false, got {v!r}", name)


def one_of(choices: Sequence[Any]) -> Check:
    """One of ``choices``."""

    def check(v: Any, name: str) -> None:
        if v not in choices:
            raise InvalidInputError(f"{name}: must be one of {', '.join(repr(c) for c in choices)}, got {v!r}", name)

    return check


def processes(v: Any, name: str) -> None:
    """Local processes of data-parallel training (:func:`~hybridmpm.train.distributed.check_nproc`)."""
    check_nproc(v, name)


@dataclass
class RunConfig:
    """Base of a training family's settings (module doc). ``RESUMABLE``
    names the settings a run may resume with changed; ``batch`` (windows,
    pairs per step and rank) is compared as the global batch, ``batch`` times
    the ranks. Subclasses are dataclasses; their ``steps``, ``batch`` and
    ``seed`` fields are what :class:`~hybridmpm.train.scaffold.loop.TrainingLoop`
    reads."""

    #: Settings a run may resume with changed (the global batch is compared apart).
    RESUMABLE: ClassVar[tuple[str, ...]] = ("steps", "threads", "out", "nproc", "ranks", "batch")

    def validate(self) -> Any:
        """Check every field (its :func:`setting`'s check), then :meth:`check`; returns ``self``.
        Raises :class:`InvalidInputError` naming the first bad field."""
        for f in dataclasses.fields(self):
            check = f.metadata.get("check")
            if check is not None:
                check(getattr(self, f.name), f.name)
        self.check()
        return self

    def check(self) -> None:
        """Rules between fields (a subclass's; none here). Raises :class:`InvalidInputError`."""

    def to_dict(self) -> dict[str, Any]:
        """The settings as plain JSON values (what ``train_config.json`` holds)."""
        return {k: (str(v) if hasattr(v, "__fspath__") else v) for k, v in asdict(self).items()}

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """The fields that have a default, with it (what a run saved before the field existed used)."""
        out = {}
        for f in dataclasses.fields(cls):
            if f.default is not MISSING:
                out[f.name] = f.default
            elif f.default_factory is not MISSING:
                out[f.name] = f.default_factory()
        return out

    def resume_error(self, saved: dict[str, Any], ranks: int, where: Any) -> InvalidInputError | None:
        """Why the run in ``where`` made with the settings ``saved`` (a
        :meth:`to_dict`, with ``ranks``) cannot be resumed by these settings on
        ``ranks`` ranks, naming the first setting that differs; None if it can.
        A setting added since the run was made counts with its default."""
        defaults = self.defaults()
        for key, v in self.to_dict().items():
            if key in self.RESUMABLE:
                continue
            old = saved.get(key, defaults.get(key))
            if old != v:
                return InvalidInputError(f"{key}: {where} holds a run with {key} = {old!r}, not {v!r}; use another --out", key)
        batch = int(getattr(self, "batch", 1))
        old_batch, old_ranks = int(saved.get("batch", defaults.get("batch", batch))), int(saved.get("ranks", 1))
        if old_batch * old_ranks != batch * ranks:
            return InvalidInputError(
                f"batch: {where} holds a run of {old_batch * old_ranks} per step ({old_batch} on each of {old_ranks} ranks), "
                f"not {batch * ranks} ({batch} on each of {ranks}); use another --out",
                "batch",
            )
        return None


__all__ = ["Check", "RunConfig", "flag", "integer", "number", "one_of", "optional", "processes", "setting"]
