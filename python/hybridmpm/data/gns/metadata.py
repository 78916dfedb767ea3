"""``metadata.json`` of a GNS dataset: the keys GNS readers need, validated, written and read."""

from __future__ import annotations

import json
import math
import numbers
import os
from collections.abc import Mapping
from typing import IO, Any

import numpy as np

from hybridmpm.data.gns.io import PathLike, atomic_write
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json

METADATA_FILE = "metadata.json"

REQUIRED_METADATA: tuple[str, ...] = (
    "bounds",
    "sequence_length",
    "default_connectivity_radius",
    "dim",
    "dt",
    "vel_mean",
    "vel_std",
    "acc_mean",
    "acc_std",
)
"""Keys ``metadata.json`` must hold (GNS readers use all of them)."""


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def _is_real(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def validate_metadata(meta: Mapping[str, Any], *, source: str | None = None) -> None:
    """Check a GNS metadata mapping (see :data:`REQUIRED_METADATA`).

    ``dim`` is 2 or 3; ``sequence_length`` an int ≥ 1;
    ``default_connectivity_radius`` and ``dt`` (seconds) finite numbers > 0;
    ``bounds`` ``dim`` pairs ``[lo, hi]`` of finite numbers with lo < hi;
    ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std`` lists of ``dim``
    finite numbers, the stds ≥ 0. Other keys are allowed and not checked.

    Raises
    ------
    InvalidInputError
        ``field`` is the offending key; the message gives the allowed range
        (and ``source``, the file, when given).
    """
    prefix = f"{source}: " if source else ""
    if not isinstance(meta, Mapping):
        raise InvalidInputError(f"{prefix}metadata must be a JSON object, got {type(meta).__name__}", None)
    missing = [k for k in REQUIRED_METADATA if k not in meta]
    if missing:
        raise InvalidInputError(f"{prefix}metadata is missing {', '.join(missing)} (required: {', '.join(REQUIRED_METADATA)})", missing[0])

    def bad(field: str, want: str) -> InvalidInputError:
        return InvalidInputError(f"{prefix}metadata {field} must be {want}, got {meta[field]!r}", field)

    dim = meta["dim"]
    if not _is_int(dim) or dim not in (2, 3):
        raise bad("dim", "2 or 3")
    if not _is_int(meta["sequence_length"]) or meta["sequence_length"] < 1:
        raise bad("sequence_length", "an integer >= 1")
    for key in ("default_connectivity_radius", "dt"):
        v = meta[key]
        if not _is_real(v) or not math.isfinite(v) or v <= 0:
            raise bad(key, "a finite number > 0")
    bounds = meta["bounds"]
    if (
        not isinstance(bounds, (list, tuple))
        or len(bounds) != dim
        or not all(isinstance(b, (list, tuple)) and len(b) == 2 and all(_is_real(x) and math.isfinite(x) for x in b) and b[0] < b[1] for b in bounds)
    ):
        raise bad("bounds", f"dim = {dim} pairs [lo, hi] of finite numbers with lo < hi")
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        v = meta[key]
        if not isinstance(v, (list, tuple)) or len(v) != dim or not all(_is_real(x) and math.isfinite(x) for x in v):
            raise bad(key, f"a list of dim = {dim} finite numbers")
        if key.endswith("_std") and any(x < 0 for x in v):
            raise bad(key, "non-negative")


def write_metadata(path: PathLike, meta: Mapping[str, Any]) -> None:
    """Write ``metadata.json``: validated, sorted keys, indent 2, atomic.

    numpy scalars and arrays are converted to JSON numbers and lists; extra
    keys are written as given. See :func:`validate_metadata` for the fields.

    Raises
    ------
    InvalidInputError
        A required field is missing or malformed (``field`` names it), or a
        value is not JSON-serialisable / not finite. Nothing is written then.
    """
    data = _jsonable(meta)
    validate_metadata(data)
    try:
        text = json.dumps(data, sort_keys=True, indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"metadata is not JSON-serialisable: {exc}", None) from exc
    payload = text.encode("utf-8")

    def write(fh: IO[bytes]) -> None:
        fh.write(payload)

    atomic_write(path, write)


def read_metadata(path: PathLike) -> dict[str, Any]:
    """Read and validate a GNS ``metadata.json``; extra keys are kept.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    InvalidInputError
        Not JSON (``field="path"``) or a field is missing / malformed
        (``field`` names it; see :func:`validate_metadata`).
    """
    source = os.fspath(path)
    with open(source, "rb") as fh:
        raw = fh.read()
    try:
        meta = loads_json(raw, "path")  # nesting checked before parsing
    except InvalidInputError as exc:
        raise InvalidInputError(f"{source}: {str(exc).removeprefix('path: ')}", "path") from None
    validate_metadata(meta, source=source)
    assert isinstance(meta, dict)
    return meta


# --------------------------------------------------------------------------- dataset
