"""Reading user files safely: the one place scene files, sketch files, model
files and store records are opened.

:func:`read_regular_file` opens without blocking (a FIFO cannot hang it),
refuses anything but a regular file (a device such as ``/dev/zero``, a FIFO,
a directory) after following links, checks the size bound on the open file
(``fstat``, not the path's ``st_size``) and reads at most that many bytes
(a file that grows while it is read is refused too). :func:`check_nesting`
refuses JSON or TOML text nested deeper than :data:`MAX_NESTING` before a
parser recurses into it; :func:`loads_json` is the one JSON reader (the
depth checked, then parsed). :func:`npz_headers` reads the ``.npy`` headers
of an ``.npz`` archive without its data, so that its arrays are sized
against the memory budget before one is read.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import human

#: Deepest nesting of arrays and tables/objects a scene or sketch file (or any JSON read, unless its reader says otherwise) may have.
MAX_NESTING = 32
#: Most members an ``.npz`` archive read by :func:`npz_headers` may have.
MAX_NPZ_MEMBERS = 10_000
#: Largest model file (ONNX) the library reads [bytes]: 256 MiB, checked on the open file before it is read
#: (:func:`read_model_file`; the shipped models are under 1 MB, protobuf itself stops at 2 GiB).
MAX_MODEL_BYTES = 256 * 2**20

#: What a path that is not a regular file is, by ``stat.S_IFMT`` (for messages).
FILE_KINDS = {
    stat.S_IFIFO: "a FIFO",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFDIR: "a directory",
    stat.S_IFSOCK: "a socket",
}


def _open_regular(path: str | os.PathLike[str], max_bytes: int, field: str, what: str) -> int:
    """A read-only descriptor of the regular file ``path`` (links followed; opened without blocking, so a FIFO
    or a device is refused, not waited on) of at most ``max_bytes``; :class:`InvalidInputError` naming ``field``."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as e:
        raise InvalidInputError(f"{field}: cannot read {what} {path} ({e.strerror or e})", field) from e
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = FILE_KINDS.get(stat.S_IFMT(st.st_mode), "not a regular file")
            raise InvalidInputError(f"{field}: {what} {path} is {kind}, not a regular file", field)
        if st.st_size > max_bytes:
            raise InvalidInputError(f"{field}: {what} {path} has {st.st_size} bytes, more than the {max_bytes} allowed", field)
    except BaseException:
        os.close(fd)
        raise
    return fd


def check_regular_file(path: str | os.PathLike[str], max_bytes: int, field: str, what: str = "file") -> None:
    """Check, without reading it, that ``path`` is a regular file (links followed) of at most ``max_bytes``,
    for a reader that opens it by name (onnxruntime). Raises :class:`InvalidInputError` naming ``field``
    as :func:`read_regular_file` does."""
    os.close(_open_regular(path, max_bytes, field, what))


def read_regular_file(path: str | os.PathLike[str], max_bytes: int, field: str, what: str = "file") -> bytes:
    """The bytes of the regular file ``path`` (links followed), at most
    ``max_bytes``. Raises :class:`InvalidInputError` naming ``field`` for a
    missing or unreadable path, anything that is not a regular file, or a
    file over ``max_bytes`` (checked on the open file, before reading)."""
    fd = _open_regular(path, max_bytes, field, what)
    try:
        chunks: list[bytes] = []
        total = 0
        while True:
            try:
                b = os.read(fd, min(1 << 20, max_bytes + 1 - total))
            except OSError as e:
                raise InvalidInputError(f"{field}: cannot read {what} {path} ({e.strerror or e})", field) from e
            if not b:
                break
            total += len(b)
            if total > max_bytes:
                raise InvalidInputError(f"{field}: {what} {path} grew past the {max_bytes} bytes allowed while it was read", field)
            chunks.append(b)
        return b"".join(chunks)
    finally:
        os.close(fd)


_TOML_SKIPPED = re.compile(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*')


_DEPTH_CHUNK = 1 << 18  # bytes scanned at a time: the arrays stay in cache (whole-text arrays of a 12 MB file took 2-8 s here)
_CHUNK_INDEX = np.arange(_DEPTH_CHUNK, dtype=np.int32)


def json_depth(raw: bytes) -> int:
    """Deepest nesting of arrays and objects in the JSON text ``raw``, found
    without parsing it: vectorised over chunks of 256 KiB (the state between
    them is the depth, whether the text is inside a string and the run of
    backslashes at the chunk's end), linear in ``len(raw)``, never recursive.
    Brackets inside strings do not count (a quote after an odd run of
    backslashes is escaped); exact on every valid prefix of the text, which
    is all a parser reads before it stops at an error."""
    a = np.frombuffer(raw, np.uint8)
    depth = deepest = 0
    in_string = 0  # 1 when the text before the chunk ends inside a string
    backslashes = 0  # the run of backslashes that ends the text before the chunk
    for start in range(0, a.size, _DEPTH_CHUNK):
        c = a[start : start + _DEPTH_CHUNK]
        idx = _CHUNK_INDEX[: c.size]
        last_plain = np.maximum.accumulate(np.where(c == ord("\\"), -1, idx))  # last index <= i that is no backslash
        run = np.empty(c.size, np.int32)  # backslashes right before i
        run[0] = backslashes
        run[1:] = idx[:-1] - last_plain[:-1] + np.where(last_plain[:-1] < 0, backslashes, 0)
        quotes = np.cumsum((c == ord('"')) & (run % 2 == 0), dtype=np.int32) + in_string
        outside = quotes % 2 == 0
        opens = ((c == ord("[")) | (c == ord("{"))) & outside
        closes = ((c == ord("]")) | (c == ord("}"))) & outside
        level = np.cumsum(opens.astype(np.int32) - closes.astype(np.int32), dtype=np.int64) + depth
        deepest = max(deepest, int(level.max()))
        depth, in_string = int(level[-1]), int(quotes[-1] % 2)
        backslashes = backslashes + c.size if last_plain[-1] < 0 else c.size - 1 - int(last_plain[-1])
    return deepest


def check_nesting(text: str, field: str, *, max_depth: int = MAX_NESTING, toml: bool = False) -> None:
    """Refuse JSON (or TOML, ``toml=True``) text whose ``[``/``{`` nesting
    outside strings (and TOML comments) goes deeper than ``max_depth``,
    naming ``field``. Linear in the text: JSON by :func:`json_depth`, TOML
    with its strings and comments removed by a regular expression first."""
    if not toml:
        depth = json_depth(text.encode("utf-8", "replace"))
    else:
        b = np.frombuffer(_TOML_SKIPPED.sub("", text).encode("utf-8", "replace"), np.uint8)
        step = ((b == ord("[")) | (b == ord("{"))).astype(np.int32) - ((b == ord("]")) | (b == ord("}"))).astype(np.int32)
        depth = int(np.cumsum(step).max(initial=0))
    if depth > max_depth:
        raise InvalidInputError(f"{field}: nested more than {max_depth} levels deep", field)


def loads_json(text: str | bytes, field: str, *, max_depth: int = MAX_NESTING) -> Any:
    """Parse the JSON ``text`` after checking its nesting (:func:`json_depth`,
    linear, before the parser recurses): the one way the library reads JSON
    it did not write itself in this process (scene files, sketches,
    trajectories' ``scene_params``, checkpoints, stream messages, dataset
    and model metadata). Raises :class:`InvalidInputError` naming ``field``
    for text nested deeper than ``max_depth`` or that is not JSON (UTF-8)."""
    raw = text.encode("utf-8", "replace") if isinstance(text, str) else bytes(text)
    if json_depth(raw) > max_depth:
        raise InvalidInputError(f"{field}: nested more than {max_depth} levels deep", field)
    try:
        return json.loads(raw.decode("utf-8") if isinstance(text, (bytes, bytearray, memoryview)) else text)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:  # RecursionError: cannot happen within max_depth; kept as a guard
        raise InvalidInputError(f"{field}: not valid JSON ({str(e)[:120]})", field) from None


@dataclass(frozen=True)
class NpyHeader:
    """One member of an ``.npz`` archive as its ``.npy`` header declares it,
    read without its data: ``name`` (the key: the member's name less
    ``.npy``), ``shape``, ``dtype``, ``fortran_order``, ``stored_bytes`` (its
    decompressed size as the archive's directory declares it [bytes]) and
    ``member`` (its name in the archive)."""

    name: str
    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    stored_bytes: int
    member: str

    @property
    def size(self) -> int:
        """Values the header declares (the product of ``shape``)."""
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        """Bytes the array takes once read [bytes]: ``size · dtype.itemsize``."""
        return self.size * self.dtype.itemsize


def npz_headers(zf: zipfile.ZipFile, field: str | None = None, max_members: int = MAX_NPZ_MEMBERS) -> list[NpyHeader]:
    """The ``.npy`` header of every member of the open archive ``zf``, read
    before any member's data (each header is at most a few kilobytes): what
    sizes an ``.npz`` against the memory budget before it is read. A member
    whose header declares more bytes than the member holds is refused (a
    header cannot make a reader allocate what the file does not back).
    Raises :class:`InvalidInputError` naming ``field`` (None: the member's
    key) for more than ``max_members`` members, a member that is no ``.npy``
    array (bad magic, unknown version, malformed header) or one that
    declares more than it holds. Object dtypes are returned: the caller
    refuses them (they need pickle)."""
    infos = zf.infolist()
    if len(infos) > max_members:
        name = field or "path"
        raise InvalidInputError(f"{name}: more than {max_members} arrays in the archive", name)
    out = []
    for info in infos:
        key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        shown = key if len(key) <= 40 else key[:40] + "…"
        name = field or shown
        try:
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f"npy version {version}")
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, RuntimeError, NotImplementedError) as e:
            raise InvalidInputError(f"{name}: array {shown!r} is not a readable .npy array ({type(e).__name__})", name) from None
        h = NpyHeader(key, tuple(int(n) for n in shape), dtype, bool(fortran), int(info.file_size), info.filename)
        if h.nbytes > h.stored_bytes:
            raise InvalidInputError(f"{name}: array {shown!r} declares {list(h.shape)} {dtype.str} ({human(h.nbytes)}) but holds {h.stored_bytes} bytes", name)
        out.append(h)
    return out


def read_npz_member(zf: zipfile.ZipFile, header: NpyHeader) -> np.ndarray:
    """The array of a member :func:`npz_headers` read (no pickle). Raises
    what :func:`numpy.lib.format.read_array` raises for a corrupt member."""
    with zf.open(header.member) as f:
        return np.asarray(np.lib.format.read_array(f, allow_pickle=False))


def read_model_file(path: str | Path) -> bytes:
    """The bytes of the model file ``path`` (ONNX): :func:`read_regular_file` with at most
    :data:`MAX_MODEL_BYTES` (a FIFO, a device such as ``/dev/zero`` or a link to one refused without
    blocking, the size checked on the open file before it is read). Raises
    :class:`InvalidInputError` (field ``model``) for a missing or unreadable path, anything that is
    not a regular file, or a larger file."""
    return read_regular_file(path, MAX_MODEL_BYTES, "model", "model file")


def check_model_file(path: str | Path) -> None:
    """Check, without reading it, that the model file ``path`` is a regular file of at most
    :data:`MAX_MODEL_BYTES` (:func:`check_regular_file`), before onnxruntime opens it by name.
    Raises :class:`InvalidInputError` (field ``model``) as :func:`read_model_file` does."""
    check_regular_file(path, MAX_MODEL_BYTES, "model", "model file")


def read_text_file(path: str | Path, max_bytes: int, field: str, what: str = "file") -> str:
    """:func:`read_regular_file` decoded as UTF-8 (:class:`InvalidInputError` naming ``field`` if it is not)."""
    raw = read_regular_file(path, max_bytes, field, what)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InvalidInputError(f"{field}: {what} {path} is not a text file (not UTF-8 at byte {e.start})", field) from e


__all__ = [
    "FILE_KINDS",
    "MAX_MODEL_BYTES",
    "MAX_NESTING",
    "MAX_NPZ_MEMBERS",
    "NpyHeader",
    "check_model_file",
    "check_nesting",
    "check_regular_file",
    "json_depth",
    "loads_json",
    "npz_headers",
    "read_model_file",
    "read_npz_member",
    "read_regular_file",
    "read_text_file",
]
