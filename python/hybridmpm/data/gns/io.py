"""Trajectories in the GNS layout: reading (a restricted unpickler: numpy arrays, dtypes and scalars only) and
writing the split files (``train.npz``, ...), atomically."""

from __future__ import annotations

import io
import math
import os
import pickle
import secrets
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import IO, Any, NamedTuple, Union

import numpy as np
from numpy.lib import format as npformat

from hybridmpm.errors import InvalidInputError

GNS_DATA_KEY = "gns_data"

_ZIP_DATE_TIME = (1980, 1, 1, 0, 0, 0)
_ZIP_COMPRESS_LEVEL = 1  # float32 positions: level 6 saves <1% more and is 1.5x slower

PathLike = Union[str, "os.PathLike[str]"]


class GnsTrajectory(NamedTuple):
    """One trajectory of a GNS split.

    Attributes
    ----------
    positions:
        float32 ``[T, N, D]``, D ∈ {2, 3}: particle positions at the ``T``
        stored frames (simulation units, the unit domain here).
    particle_type:
        int64 ``[N]``: GNS particle type per particle (:data:`GNS_KINEMATIC`,
        :data:`GNS_WATER`, :data:`GNS_SAND`, ...).
    material_properties:
        The optional third element of the stored tuple (geoelements' material
        feature, any numeric array) or ``None``. Kept as read.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    material_properties: np.ndarray | None = None


TrajectoryLike = Union[GnsTrajectory, Sequence[Any]]


# --------------------------------------------------------------------------- validation


def _where(source: str | None, tid: str) -> str:
    prefix = f"{source}: " if source else ""
    return f"{prefix}trajectory {tid!r}"


def check_trajectory(tid: str, value: Any, *, source: str | None, lenient: bool) -> GnsTrajectory:
    """Validate one ``(positions, particle_type[, material_properties])`` item
    (positions [T, N, D], particle_type [N]) of trajectory ``tid``.

    ``lenient`` (reading files of other tools) also accepts integral-valued
    float particle types. Returns canonical arrays (positions float32
    [T, N, D], particle_type int64 [N], C order); raises
    :class:`~hybridmpm.errors.InvalidInputError` naming ``tid`` (with
    ``source``, the file, in the message) for anything else.
    """
    where = _where(source, tid)
    if isinstance(value, np.ndarray) and value.dtype == object and value.ndim == 1:
        elems = list(value)
    elif isinstance(value, (tuple, list)):
        elems = list(value)
    else:
        kind = f"{type(value).__name__}" + (f" of dtype {value.dtype}, shape {value.shape}" if isinstance(value, np.ndarray) else "")
        raise InvalidInputError(f"{where}: expected a (positions, particle_type[, material_properties]) tuple, got {kind}", tid)
    if len(elems) == 3 and elems[2] is None:
        elems = elems[:2]
    if len(elems) not in (2, 3):
        raise InvalidInputError(f"{where}: expected 2 or 3 elements (positions, particle_type[, material_properties]), got {len(elems)}", tid)

    field = f"{tid}.positions"
    try:
        raw = np.asarray(elems[0])
    except Exception as exc:  # ragged lists and the like
        raise InvalidInputError(f"{where}: positions is not an array ({exc})", field) from exc
    if raw.dtype.kind not in "fiu":
        raise InvalidInputError(f"{where}: positions must be real numbers castable to float32, got dtype {raw.dtype}", field)
    if raw.ndim != 3 or raw.shape[2] not in (2, 3):
        raise InvalidInputError(f"{where}: positions must have shape [T, N, D] with D in {{2, 3}}, got {raw.shape}", field)
    if raw.shape[0] < 1 or raw.shape[1] < 1:
        raise InvalidInputError(f"{where}: positions needs at least one frame and one particle, got {raw.shape}", field)
    with np.errstate(over="ignore", invalid="ignore"):
        positions = np.ascontiguousarray(raw, dtype=np.float32)
    finite = np.isfinite(positions)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise InvalidInputError(
            f"{where}: positions must be finite in float32; {int((~finite).sum())} value(s) are not, "
            f"first at [frame {bad[0]}, particle {bad[1]}, axis {bad[2]}]",
            field,
        )
    n = positions.shape[1]

    field = f"{tid}.particle_type"
    try:
        ptype = np.asarray(elems[1])
    except Exception as exc:
        raise InvalidInputError(f"{where}: particle_type is not an array ({exc})", field) from exc
    if ptype.shape != (n,):
        raise InvalidInputError(f"{where}: particle_type must have shape [N] = ({n},) to match positions, got {ptype.shape}", field)
    if ptype.dtype.kind in "iu":
        if ptype.dtype == np.uint64 and n and int(ptype.max()) > np.iinfo(np.int64).max:
            raise InvalidInputError(f"{where}: particle_type values must fit in int64", field)
        particle_type = np.ascontiguousarray(ptype, dtype=np.int64)
    elif lenient and ptype.dtype.kind == "f" and bool(np.all(np.isfinite(ptype))) and bool(np.all(ptype == np.round(ptype))):
        particle_type = np.ascontiguousarray(ptype, dtype=np.int64)
    else:
        raise InvalidInputError(f"{where}: particle_type must be integers, got dtype {ptype.dtype}", field)

    material: np.ndarray | None = None
    if len(elems) == 3:
        field = f"{tid}.material_properties"
        try:
            material = np.asarray(elems[2])
        except Exception as exc:
            raise InvalidInputError(f"{where}: material_properties is not an array ({exc})", field) from exc
        if material.dtype.kind not in "biuf":
            raise InvalidInputError(f"{where}: material_properties must be numeric, got dtype {material.dtype}", field)
    return GnsTrajectory(positions, particle_type, material)


def _check_id(tid: Any, *, source: str | None = None) -> str:
    prefix = f"{source}: " if source else ""
    if not isinstance(tid, str) or not tid:
        raise InvalidInputError(f"{prefix}trajectory ids must be non-empty strings, got {tid!r}", "trajectory_id")
    if any(c in tid for c in "/\\\0") or tid in (".", ".."):
        raise InvalidInputError(f"{prefix}trajectory id {tid!r} must not contain '/', '\\' or NUL", "trajectory_id")
    if tid == GNS_DATA_KEY:
        raise InvalidInputError(
            f"{prefix}trajectory id {GNS_DATA_KEY!r} is reserved: GNS readers take a member of that name for the whole split",
            "trajectory_id",
        )
    return tid


# --------------------------------------------------------------------------- atomic files


def atomic_write(path: PathLike, write: Callable[[IO[bytes]], object]) -> None:
    """Write ``path`` through a temporary file in the same folder (``write(fh)``
    fills it; it is fsynced) and ``os.replace``: readers see the old file or
    the whole new one. Whatever ``write`` raises propagates, the temporary
    file removed."""
    target = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(target))
    tmp = os.path.join(folder, f".{os.path.basename(target)}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


# --------------------------------------------------------------------------- writing


def _member_bytes(traj: GnsTrajectory) -> memoryview:
    item = np.empty(2 if traj.material_properties is None else 3, dtype=object)
    item[0] = traj.positions
    item[1] = traj.particle_type
    if traj.material_properties is not None:
        item[2] = traj.material_properties
    buf = io.BytesIO()
    npformat.write_array(buf, item, allow_pickle=True)
    return buf.getbuffer()


def write_split(path: PathLike, trajectories: Mapping[str, TrajectoryLike], *, compress: bool = False) -> None:
    """Write one split file (``train.npz``, ...) in the GNS npz layout.

    Parameters
    ----------
    path:
        The file to write, exactly as given (no ``.npz`` is appended). It is
        replaced atomically: written to a temporary file in the same folder,
        then ``os.replace``-d, so readers never see a partial file.
    trajectories:
        Trajectory id → ``(positions, particle_type)`` or ``(positions,
        particle_type, material_properties)`` (a :class:`GnsTrajectory` works).
        positions: real ``[T, N, D]``, D ∈ {2, 3}, T ≥ 1, N ≥ 1, finite once
        cast to float32; particle_type: integers ``[N]`` (stored int64);
        material_properties: optional numeric array, stored as given. Ids are
        non-empty strings without ``/``, ``\\`` or NUL, and not ``gns_data``.
        Trajectories are read from the mapping one at a time (a lazy mapping
        keeps memory at one trajectory).
    compress:
        DEFLATE the members (level 1). Off by default: float32 positions
        compress by only ~13% and deflating costs ~30 MB/s of one core,
        minutes on a 2 GB training split.

    The file is byte-deterministic for a given numpy / zlib install: members
    ``<id>.npy`` in sorted id order (so zero-pad numeric ids where the index
    order matters to a GNS tool), each a 1-D object array written by
    ``numpy.lib.format.write_array``, stored (or DEFLATE level 1), time stamps 1980-01-01.
    It reads back with ``np.load(path, allow_pickle=True)`` (what
    geoelements/gns does) and with :func:`read_split`.

    Raises
    ------
    InvalidInputError
        An id or array is malformed; ``field`` is ``"<id>.positions"``,
        ``"<id>.particle_type"``, ``"<id>.material_properties"`` or
        ``"trajectory_id"``. Nothing is written then (the partial temporary
        file is removed).
    """
    if not isinstance(trajectories, Mapping):
        raise InvalidInputError(
            f"trajectories must be a mapping of trajectory id to (positions, particle_type), got {type(trajectories).__name__}",
            "trajectories",
        )
    for tid in trajectories:
        _check_id(tid)
    ordered = sorted(trajectories)
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED

    def write(fh: IO[bytes]) -> None:
        with zipfile.ZipFile(fh, mode="w", compression=method, compresslevel=_ZIP_COMPRESS_LEVEL if compress else None) as zf:
            for tid in ordered:
                traj = check_trajectory(tid, trajectories[tid], source=None, lenient=False)
                info = zipfile.ZipInfo(f"{tid}.npy", date_time=_ZIP_DATE_TIME)
                info.compress_type = method
                info.create_system = 3  # Unix, whatever the writing platform
                info.external_attr = 0o644 << 16
                zf.writestr(info, _member_bytes(traj), compresslevel=_ZIP_COMPRESS_LEVEL if compress else None)

    atomic_write(path, write)


# --------------------------------------------------------------------------- restricted unpickling


def _latin1_encode(obj: Any, encoding: str = "utf-8", errors: str = "strict") -> bytes:
    # Python 3 pickles (protocol < 3) spell bytes as _codecs.encode(str, "latin1").
    if not isinstance(obj, str) or encoding.lower().replace("_", "-") not in ("latin1", "latin-1", "iso-8859-1"):
        raise pickle.UnpicklingError("_codecs.encode is only allowed for latin-1 byte strings")
    return obj.encode("latin-1", errors)


def _allowed_globals() -> dict[tuple[str, str], Any]:
    # Take the objects from what numpy itself pickles, so no private module is imported.
    reconstruct = np.empty(0).__reduce__()[0]
    scalar = np.float64(0).__reduce__()[0]
    frombuffer = np.empty(1).__reduce_ex__(5)[0]
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("_codecs", "encode"): _latin1_encode,
    }
    for core in ("numpy._core", "numpy.core"):  # numpy >= 2 and numpy 1.x spellings
        allowed[(f"{core}.multiarray", "_reconstruct")] = reconstruct
        allowed[(f"{core}.multiarray", "scalar")] = scalar
        allowed[(f"{core}.numeric", "_frombuffer")] = frombuffer
    return allowed


_ALLOWED_GLOBALS = _allowed_globals()


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that rebuilds numpy arrays, dtypes and scalars and nothing else."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise _ForbiddenGlobal(module, name) from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("persistent ids are not allowed")


class _ForbiddenGlobal(pickle.UnpicklingError):
    def __init__(self, module: str, name: str) -> None:
        super().__init__(f"{module}.{name}")
        self.qualname = f"{module}.{name}"


# --------------------------------------------------------------------------- reading


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, source: str, key: str) -> Any:
    """Parse one ``.npy`` member; object payloads go through the restricted unpickler."""
    where = f"{source}: member {info.filename!r}"
    try:
        with zf.open(info) as fp:
            version = npformat.read_magic(fp)
            if version == (1, 0):
                shape, fortran_order, dtype = npformat.read_array_header_1_0(fp)
            elif version == (2, 0):
                shape, fortran_order, dtype = npformat.read_array_header_2_0(fp)
            else:
                raise InvalidInputError(f"{where}: unsupported .npy format version {version}", key)
            if dtype.hasobject:
                if dtype != np.dtype(object):
                    raise InvalidInputError(f"{where}: structured dtypes holding objects are not supported ({dtype})", key)
                try:
                    array = _RestrictedUnpickler(fp, encoding="latin1").load()
                except _ForbiddenGlobal as exc:
                    raise InvalidInputError(
                        f"{where}: refusing to unpickle {exc.qualname}: only numpy arrays, dtypes and scalars are "
                        "allowed in a GNS dataset (the file may be malicious)",
                        key,
                    ) from None
                if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
                    raise InvalidInputError(f"{where}: object payload does not match its header shape {shape}", key)
            else:
                count = math.prod(shape)
                nbytes = count * dtype.itemsize
                if nbytes > info.file_size:  # refuse before reading a header that promises more than the member holds
                    raise InvalidInputError(f"{where}: truncated: header promises {nbytes} bytes, member holds {info.file_size}", key)
                data = fp.read(nbytes)
                if len(data) != nbytes:
                    raise InvalidInputError(f"{where}: truncated: header promises {nbytes} bytes, found {len(data)}", key)
                array = np.frombuffer(data, dtype=dtype, count=count).reshape(shape, order="F" if fortran_order else "C")
            if fp.read(1):  # reading to the end also checks the member's CRC
                raise InvalidInputError(f"{where}: trailing data after the array", key)
    except InvalidInputError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, zlib.error, EOFError, UnpicklingError, ValueError, ...
        raise InvalidInputError(f"{where}: corrupt or truncated ({type(exc).__name__}: {exc})", key) from exc
    return array


def read_split(path: PathLike) -> dict[str, GnsTrajectory]:
    """Read one split file of the GNS npz layout (ours or another tool's).

    Accepts the files :func:`write_split` writes and those of other tools:
    ``np.savez`` / ``np.savez_compressed`` of per-trajectory object arrays, and
    the geoelements variant with a single ``gns_data`` member (an object array
    of ``(positions, particle_type[, material_properties])`` tuples, whose
    trajectories get the ids ``simulation_trajectory_<i>``, zero-padded to
    keep their order; as in geoelements/gns, other members are then ignored).
    Pickled payloads go through a restricted unpickler that rebuilds numpy
    arrays only; nothing in the file is executed.

    Returns
    -------
    dict[str, GnsTrajectory]
        Trajectory id → trajectory, in file order. positions float32
        ``[T, N, D]`` (other float or int dtypes are cast; must be finite),
        particle_type int64 ``[N]`` (integral floats are accepted),
        material_properties as stored or ``None``.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    InvalidInputError
        Not a zip, truncated or corrupt (``field="path"`` or the member's
        id), a forbidden pickle (``field`` = the member's id), or a malformed
        trajectory (``field="<id>.positions"``, ``"<id>.particle_type"``, ...).
        The message names the file, the trajectory and the field.
    """
    source = os.fspath(path)
    try:
        zf = zipfile.ZipFile(source)
    except (FileNotFoundError, IsADirectoryError):
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
        raise InvalidInputError(f"{source}: not a readable npz (zip) file ({exc})", "path") from exc
    with zf:
        members: dict[str, zipfile.ZipInfo] = {}
        for info in zf.infolist():
            if info.is_dir():
                continue
            if not info.filename.endswith(".npy"):
                raise InvalidInputError(f"{source}: member {info.filename!r} is not a .npy array", "path")
            key = info.filename[: -len(".npy")]
            if key in members:
                raise InvalidInputError(f"{source}: member {info.filename!r} appears twice", key)
            members[key] = info

        if GNS_DATA_KEY in members:
            return _read_gns_data(_read_member(zf, members[GNS_DATA_KEY], source, GNS_DATA_KEY), source)
        out: dict[str, GnsTrajectory] = {}
        for key, info in members.items():
            item = _read_member(zf, info, source, key)
            out[key] = check_trajectory(key, item, source=source, lenient=True)
        return out


def _read_gns_data(data: Any, source: str) -> dict[str, GnsTrajectory]:
    where = f"{source}: member {GNS_DATA_KEY!r}"
    if not isinstance(data, np.ndarray) or data.dtype != object or data.ndim not in (1, 2):
        raise InvalidInputError(f"{where}: expected an object array of (positions, particle_type) tuples", GNS_DATA_KEY)
    items: list[Any] = list(data) if data.ndim == 1 else [list(row) for row in data]
    width = len(str(max(len(items) - 1, 0)))
    out: dict[str, GnsTrajectory] = {}
    for i, item in enumerate(items):
        tid = f"simulation_trajectory_{i:0{width}d}"
        out[tid] = check_trajectory(tid, item, source=f"{source} ({GNS_DATA_KEY}[{i}])", lenient=True)
    return out


# --------------------------------------------------------------------------- statistics
