"""A simulator state (:meth:`Simulator.state`, a tree of dicts, lists, arrays,
bytes and scalars) as a safe file: an ``.npz`` of plain numeric arrays plus one
JSON document (``__tree__``) that references them. No pickle either way: the
archive is read with ``allow_pickle=False``; every bound is checked before the
work it bounds — the members' number and decompressed sizes before anything
is decompressed, each array's declared shape against its member's size before
it is allocated, the JSON's size and nesting depth before it is parsed, the
tree's node count while it is decoded — and ``meta`` must be a flat object of
short scalar settings. The simulator's own ``restore`` then validates the content."""

from __future__ import annotations

import io
import json
import math
import zipfile
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import json_depth, loads_json, npz_headers, read_npz_member

FORMAT = "hybridmpm-checkpoint"
VERSION = 1
MAX_NODES = 100_000
MAX_DEPTH = 16
MAX_MEMBERS = 10_000
#: Largest ``__tree__`` JSON [bytes] (a hybrid session's is about 1 KiB).
MAX_TREE_BYTES = 1 << 20
#: Deepest nesting of ``[``/``{`` in ``__tree__`` (each list level of the state is two: ``{"__list__": [...]}``).
MAX_JSON_DEPTH = 2 * MAX_DEPTH + 8
#: ``meta`` (the settings a checkpoint was written for): at most this many, each value a scalar, strings at most this long.
MAX_META_KEYS = 16
MAX_META_CHARS = 64


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


def decoded_nbytes(data: bytes) -> int:
    """The decompressed size of the archive's members as its directory
    declares it [bytes] (nothing is decompressed). Raises
    :class:`InvalidInputError` (field ``checkpoint``) for a file that is no zip archive."""
    try:
        return sum(i.file_size for i in zipfile.ZipFile(io.BytesIO(data)).infolist())
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise _bad(f"not an npz archive ({type(e).__name__})") from None


def _read_members(data: bytes, max_bytes: int) -> dict[str, np.ndarray]:
    """The archive's arrays, each checked before it is read
    (:func:`~hybridmpm.files.npz_headers`): a plain numeric ``.npy`` whose
    declared shape fits the member's decompressed size."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
        infos = zf.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise _bad(f"not an npz archive ({type(e).__name__})") from None
    if len(infos) > MAX_MEMBERS:
        raise _bad(f"more than {MAX_MEMBERS} arrays")
    if sum(i.file_size for i in infos) > max_bytes:
        raise _bad(f"arrays larger than {max_bytes} bytes once decompressed")
    if "__tree__.npy" not in {i.filename for i in infos}:
        raise _bad("no __tree__ member (not written by GET /checkpoint)")
    try:
        headers = npz_headers(zf, "checkpoint", MAX_MEMBERS)
    except InvalidInputError as e:
        raise _bad(str(e).removeprefix("checkpoint: ")) from None
    arrays: dict[str, np.ndarray] = {}
    for h in headers:
        shown = h.name if len(h.name) <= 40 else h.name[:40] + "…"
        if h.dtype.kind not in "biuf" or h.dtype.hasobject:
            raise _bad(f"array {shown!r} has dtype {h.dtype.str}")
        try:
            arrays[h.name] = read_npz_member(zf, h)
        except Exception as e:  # noqa: BLE001 - numpy/zipfile raise many types on malformed input
            raise _bad(f"unreadable array {shown!r} ({type(e).__name__})") from None
    return arrays


def check_meta(meta: Any) -> dict[str, Any]:
    """``meta`` as a flat object of at most :data:`MAX_META_KEYS` short keys
    and scalar values (strings at most :data:`MAX_META_CHARS` characters), or
    :class:`InvalidInputError` (field ``checkpoint``)."""
    if not isinstance(meta, dict) or len(meta) > MAX_META_KEYS:
        raise _bad(f"meta must be an object of at most {MAX_META_KEYS} settings")
    for k, v in meta.items():
        if len(k) > MAX_META_CHARS or not (v is None or isinstance(v, (bool, int, float)) or (isinstance(v, str) and len(v) <= MAX_META_CHARS)):
            raise _bad(f"meta: each setting must be a number, a string of at most {MAX_META_CHARS} characters, true, false or null")
    return meta


def loads(data: bytes, max_bytes: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """npz bytes → ``(state, meta)``. Raises :class:`InvalidInputError`
    (field ``checkpoint``, a short message) for anything but a well-formed
    checkpoint whose arrays total at most ``max_bytes`` once decompressed;
    nothing recursive runs on the input before its depth is known to be
    within :data:`MAX_JSON_DEPTH`."""
    arrays = _read_members(data, max_bytes)
    raw = arrays.pop("__tree__")
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise _bad("__tree__ must be uint8 bytes of JSON")
    if raw.nbytes > MAX_TREE_BYTES:
        raise _bad(f"__tree__ larger than {MAX_TREE_BYTES} bytes")
    try:
        tree = loads_json(raw.tobytes(), "checkpoint.__tree__", max_depth=MAX_JSON_DEPTH)
    except InvalidInputError as e:
        raise _bad(str(e).removeprefix("checkpoint.")) from None
    if not isinstance(tree, dict) or tree.get("format") != FORMAT or tree.get("version") != VERSION:
        raise _bad(f"not a {FORMAT} version {VERSION}")
    meta = check_meta(tree.get("meta"))
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
                        raise _bad(f"{tag} references a missing array")
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


__all__ = [
    "FORMAT",
    "MAX_JSON_DEPTH",
    "MAX_TREE_BYTES",
    "MAX_META_CHARS",
    "MAX_META_KEYS",
    "VERSION",
    "check_meta",
    "decoded_nbytes",
    "dumps",
    "json_depth",
    "loads",
]
