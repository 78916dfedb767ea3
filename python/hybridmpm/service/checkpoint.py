"""A simulator state (:meth:`Simulator.state`, a tree of dicts, lists, arrays,
bytes and scalars) as a safe file: an ``.npz`` of plain numeric arrays plus one
JSON document (``__tree__``) that references them. No pickle either way: the
archive is read with ``allow_pickle=False``, its members' sizes are checked
before they are decompressed, and the tree's shape is bounded; the simulator's
own ``restore`` then validates the content."""

from __future__ import annotations

import io
import json
import math
import zipfile
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError

FORMAT = "hybridmpm-checkpoint"
VERSION = 1
MAX_NODES = 100_000
MAX_DEPTH = 16
MAX_MEMBERS = 10_000


def _bad(msg: str) -> InvalidInputError:
    return InvalidInputError(f"checkpoint: {msg}", "checkpoint")


def dumps(state: dict[str, Any], meta: dict[str, Any]) -> bytes:
    """``state`` and ``meta`` (session settings, JSON) → npz bytes."""
    arrays: dict[str, np.ndarray] = {}

    def enc(v: Any) -> Any:
        if isinstance(v, dict):
            return {str(k): enc(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return {"__list__": [enc(x) for x in v]}
        if isinstance(v, (bytes, bytearray)):
            key = f"a{len(arrays)}"
            arrays[key] = np.frombuffer(bytes(v), np.uint8)
            return {"__bytes__": key}
        if isinstance(v, np.ndarray):
            if v.dtype.kind not in "biuf":
                raise TypeError(f"checkpoint: cannot store dtype {v.dtype}")
            key = f"a{len(arrays)}"
            arrays[key] = v
            return {"__array__": key}
        if isinstance(v, np.generic):
            return v.item()
        if v is None or isinstance(v, (str, int, float, bool)):
            return v
        raise TypeError(f"checkpoint: cannot store {type(v).__name__}")

    tree = {"format": FORMAT, "version": VERSION, "meta": meta, "state": enc(state)}
    buf = io.BytesIO()
    members: dict[str, Any] = {"__tree__": np.frombuffer(json.dumps(tree).encode(), np.uint8), **arrays}
    np.savez(buf, **members)
    return buf.getvalue()


def loads(data: bytes, max_bytes: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """npz bytes → ``(state, meta)``. Raises :class:`InvalidInputError`
    (field ``checkpoint``) for anything but a well-formed checkpoint whose
    arrays total at most ``max_bytes`` once decompressed."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
        infos = zf.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise _bad(f"not an npz archive ({e})") from None
    if len(infos) > MAX_MEMBERS:
        raise _bad(f"more than {MAX_MEMBERS} arrays")
    if sum(i.file_size for i in infos) > max_bytes:
        raise _bad(f"arrays larger than {max_bytes} bytes once decompressed")
    names = {i.filename for i in infos}
    if "__tree__.npy" not in names:
        raise _bad("no __tree__ member (not written by GET /checkpoint)")
    arrays: dict[str, np.ndarray] = {}
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            for key in npz.files:
                arrays[key] = np.asarray(npz[key])
    except Exception as e:  # noqa: BLE001 - numpy/zipfile raise many types on malformed input
        raise _bad(f"unreadable array ({type(e).__name__}: {e})") from None
    raw = arrays.pop("__tree__")
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise _bad("__tree__ must be uint8 bytes of JSON")
    try:
        tree = json.loads(raw.tobytes().decode())
    except (ValueError, UnicodeDecodeError) as e:
        raise _bad(f"__tree__ is not JSON ({e})") from None
    if not isinstance(tree, dict) or tree.get("format") != FORMAT or tree.get("version") != VERSION:
        raise _bad(f"not a {FORMAT} version {VERSION}")
    meta = tree.get("meta")
    if not isinstance(meta, dict):
        raise _bad("meta must be an object")
    count = [0]

    def dec(v: Any, depth: int) -> Any:
        count[0] += 1
        if count[0] > MAX_NODES or depth > MAX_DEPTH:
            raise _bad("state tree too large or too deep")
        if isinstance(v, dict):
            if len(v) == 1 and "__list__" in v:
                items = v["__list__"]
                if not isinstance(items, list):
                    raise _bad("__list__ must be a list")
                return [dec(x, depth + 1) for x in items]
            for tag in ("__array__", "__bytes__"):
                if len(v) == 1 and tag in v:
                    key = v[tag]
                    if not isinstance(key, str) or key not in arrays:
                        raise _bad(f"{tag} references a missing array {key!r}")
                    a = arrays[key]
                    if a.dtype.kind not in "biuf":
                        raise _bad(f"array {key} has dtype {a.dtype}")
                    if tag == "__bytes__":
                        if a.dtype != np.uint8 or a.ndim != 1:
                            raise _bad(f"bytes {key} must be a uint8 vector")
                        return a.tobytes()
                    return a
            return {str(k): dec(x, depth + 1) for k, x in v.items()}
        if isinstance(v, list):
            raise _bad("bare lists are not part of the format")
        if isinstance(v, float) and math.isinf(v):
            raise _bad("infinite number")
        return v

    state = dec(tree.get("state"), 0)
    if not isinstance(state, dict):
        raise _bad("state must be an object")
    return state, meta


__all__ = ["FORMAT", "VERSION", "dumps", "loads"]
