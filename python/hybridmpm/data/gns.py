"""Datasets in the public GNS layout: read, write, statistics, metadata.

The layout is the one of the "Learning to Simulate" datasets (GNS,
Sanchez-Gonzalez et al. 2020, "Learning to Simulate Complex Physics with Graph
Networks", ICML) as converted to npz by geoelements/gns, the PyTorch GNS. A
dataset is a directory holding

* ``train.npz``, ``valid.npz``, ``test.npz``: each a zip of ``.npy`` members,
  one per trajectory, named ``<trajectory id>.npy`` (e.g.
  ``simulation_trajectory_0.npy``); each member is a 1-D object array
  ``(positions, particle_type)`` or ``(positions, particle_type,
  material_properties)`` with positions float32 ``[T, N, D]`` (``T =
  sequence_length + 1`` stored frames) and particle_type int64 ``[N]`` (GNS
  codes: :data:`GNS_KINEMATIC` 3 for boundary/obstacle particles, :data:`GNS_WATER` 5,
  :data:`GNS_SAND` 6). geoelements also reads a variant with a single member
  ``gns_data``, an object array of such tuples.
* ``metadata.json``: ``bounds`` ``[[lo, hi]] * D``, ``sequence_length``,
  ``default_connectivity_radius``, ``dim``, ``dt`` (seconds between stored
  frames) and ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std`` (``D``
  floats each, in GNS per-step units: velocity is the position difference of
  consecutive stored frames, acceleration the second difference; neither is
  divided by ``dt``).

Object arrays are pickles, and a pickle can run code when loaded. This module
never unpickles with :mod:`pickle`'s default class lookup: a restricted
unpickler rebuilds only numpy arrays, dtypes and scalars and refuses every other
global with :class:`~hybridmpm.errors.InvalidInputError`, so files from other
tools can be read without trusting them.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import numbers
import os
import pickle
import secrets
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import IO, Any, NamedTuple, Union

import numpy as np
from numpy.lib import format as npformat

from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER, SPLITS
from hybridmpm.errors import InvalidInputError

"""The split names of a GNS dataset directory, in canonical order."""

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

GNS_DATA_KEY = "gns_data"

_ZIP_DATE_TIME = (1980, 1, 1, 0, 0, 0)
_ZIP_COMPRESS_LEVEL = 1  # float32 positions: level 6 saves <1% more and is 1.5x slower
_STATS_CHUNK_FRAMES = 256

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


def _check_trajectory(tid: str, value: Any, *, source: str | None, lenient: bool) -> GnsTrajectory:
    """Validate one ``(positions, particle_type[, material_properties])`` item.

    ``lenient`` (reading files of other tools) also accepts integral-valued
    float particle types. Returns canonical arrays (float32 / int64, C order).
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


def _atomic_write(path: PathLike, write: Callable[[IO[bytes]], None]) -> None:
    """Write ``path`` through a temporary file in the same folder and ``os.replace``."""
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
                traj = _check_trajectory(tid, trajectories[tid], source=None, lenient=False)
                info = zipfile.ZipInfo(f"{tid}.npy", date_time=_ZIP_DATE_TIME)
                info.compress_type = method
                info.create_system = 3  # Unix, whatever the writing platform
                info.external_attr = 0o644 << 16
                zf.writestr(info, _member_bytes(traj), compresslevel=_ZIP_COMPRESS_LEVEL if compress else None)

    _atomic_write(path, write)


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
            out[key] = _check_trajectory(key, item, source=source, lenient=True)
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
        out[tid] = _check_trajectory(tid, item, source=f"{source} ({GNS_DATA_KEY}[{i}])", lenient=True)
    return out


# --------------------------------------------------------------------------- statistics


@dataclass
class _Moments:
    """Streaming per-axis count, mean and centred sum of squares (Chan et al. merge)."""

    count: int
    mean: np.ndarray
    m2: np.ndarray

    def add(self, x: np.ndarray) -> None:
        flat = x.reshape(-1, x.shape[-1])
        nb = flat.shape[0]
        if nb == 0:
            return
        mean_b = flat.mean(axis=0)
        m2_b = ((flat - mean_b) ** 2).sum(axis=0)
        n = self.count + nb
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (nb / n)
        self.m2 = self.m2 + m2_b + delta**2 * (self.count * nb / n)
        self.count = n


def compute_statistics(
    trajectories: Mapping[str, TrajectoryLike] | Iterable[TrajectoryLike],
    *,
    exclude_types: Iterable[int] = (GNS_KINEMATIC,),
) -> dict[str, list[float]]:
    """Velocity and acceleration mean / std per axis, as GNS metadata wants them.

    Velocity is ``x[t+1] − x[t]`` and acceleration ``x[t+1] − 2 x[t] + x[t−1]``
    between stored frames, in GNS per-step units (position units per frame,
    NOT divided by ``dt``). The statistics run over every frame and every
    particle whose type is not in ``exclude_types`` (default: kinematic
    particles, type 3) of all trajectories. The std is the population one
    (``ddof=0``, as ``np.std``). Computed in float64 streaming (per-chunk mean
    and centred sum of squares, merged as in Chan, Golub & LeVeque 1979), so
    trajectories are never concatenated.

    Parameters
    ----------
    trajectories:
        A mapping id → trajectory (as :func:`read_split` returns) or an
        iterable of trajectories; each ``(positions [T, N, D],
        particle_type [N])`` as in :func:`write_split`. All share one D.
    exclude_types:
        GNS particle types left out.

    Returns
    -------
    dict
        ``{"vel_mean", "vel_std", "acc_mean", "acc_std"}``, each a list of D
        floats, ready for ``metadata.json``.

    Raises
    ------
    InvalidInputError
        A malformed trajectory (field ``"<id>.positions"``, ...), dimensions
        that differ between trajectories, or too little data: no counted
        particle, or fewer than 3 frames in all (``field="trajectories"``).
    """
    pairs: Iterable[tuple[str, Any]]
    if isinstance(trajectories, Mapping):
        pairs = trajectories.items()
    else:
        pairs = ((f"#{i}", t) for i, t in enumerate(trajectories))
    excluded = np.asarray(sorted({int(t) for t in exclude_types}), dtype=np.int64)
    dim: int | None = None
    vel: _Moments | None = None
    acc: _Moments | None = None
    for tid, value in pairs:
        traj = _check_trajectory(str(tid), value, source=None, lenient=True)
        t_count, _, d = traj.positions.shape
        if dim is None:
            dim = d
            vel = _Moments(0, np.zeros(d), np.zeros(d))
            acc = _Moments(0, np.zeros(d), np.zeros(d))
        elif d != dim:
            raise InvalidInputError(f"trajectory {tid!r}: positions have D = {d}, earlier trajectories D = {dim}", f"{tid}.positions")
        assert vel is not None and acc is not None
        keep = ~np.isin(traj.particle_type, excluded)
        if not keep.any() or t_count < 2:
            continue
        for start in range(0, t_count - 1, _STATS_CHUNK_FRAMES):
            window = traj.positions[start : start + _STATS_CHUNK_FRAMES + 2][:, keep].astype(np.float64)
            d1 = np.diff(window, axis=0)
            vel.add(d1[:_STATS_CHUNK_FRAMES])
            acc.add(np.diff(d1, axis=0)[:_STATS_CHUNK_FRAMES])
    if vel is None or acc is None or acc.count == 0:
        raise InvalidInputError(
            f"statistics need at least one trajectory with 3 or more frames and one particle whose type is not excluded (excluded types: {excluded.tolist()})",
            "trajectories",
        )
    return {
        "vel_mean": [float(v) for v in vel.mean],
        "vel_std": [float(v) for v in np.sqrt(vel.m2 / vel.count)],
        "acc_mean": [float(v) for v in acc.mean],
        "acc_std": [float(v) for v in np.sqrt(acc.m2 / acc.count)],
    }


# --------------------------------------------------------------------------- metadata


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

    _atomic_write(path, write)


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
        meta = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidInputError(f"{source}: not valid JSON ({exc})", "path") from exc
    validate_metadata(meta, source=source)
    assert isinstance(meta, dict)
    return meta


# --------------------------------------------------------------------------- dataset


class SplitNotFoundError(InvalidInputError, KeyError):
    """A split file is absent from a dataset directory (also a ``KeyError``)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class GnsDataset(Mapping[str, dict[str, GnsTrajectory]]):
    """A dataset directory in the GNS layout, as a mapping split name → split.

    ``GnsDataset(directory)`` reads and validates ``metadata.json`` at once;
    splits are read lazily, on each :meth:`split` call (the result is not
    cached: keep it). ``len`` and iteration cover the splits present, in the
    order train, valid, test.

    Raises
    ------
    FileNotFoundError
        ``directory`` or its ``metadata.json`` does not exist.
    InvalidInputError
        ``metadata.json`` is malformed (see :func:`read_metadata`).
    """

    def __init__(self, directory: PathLike) -> None:
        self.directory = os.fspath(directory)
        if not os.path.isdir(self.directory):
            raise FileNotFoundError(f"{self.directory}: no such dataset directory")
        self.metadata: dict[str, Any] = read_metadata(os.path.join(self.directory, METADATA_FILE))

    @property
    def dim(self) -> int:
        """Spatial dimension D from the metadata."""
        return int(self.metadata["dim"])

    @property
    def splits(self) -> tuple[str, ...]:
        """Names of the split files present (among train, valid, test)."""
        return tuple(s for s in SPLITS if os.path.isfile(self.path(s)))

    def path(self, name: str) -> str:
        """Path of split ``name``'s npz file (whether or not it exists)."""
        return os.path.join(self.directory, f"{name}.npz")

    def split(self, name: str) -> dict[str, GnsTrajectory]:
        """Read split ``name`` ("train", "valid" or "test") with :func:`read_split`.

        Also checks every trajectory against the metadata's ``dim``.

        Raises
        ------
        SplitNotFoundError
            (an :class:`InvalidInputError` and a ``KeyError``, ``field="name"``)
            ``name`` is not a split name or its file is absent; the message
            lists the splits present.
        InvalidInputError
            As :func:`read_split`, or positions whose D differs from ``dim``.
        """
        if name not in SPLITS or not os.path.isfile(self.path(name)):
            present = ", ".join(self.splits) or "none"
            what = "is not a split name (train, valid, test)" if name not in SPLITS else "has no file"
            raise SplitNotFoundError(f"{self.directory}: split {name!r} {what}; splits present: {present}", "name")
        source = self.path(name)
        data = read_split(source)
        for tid, traj in data.items():
            if traj.positions.shape[2] != self.dim:
                raise InvalidInputError(
                    f"{source}: trajectory {tid!r}: positions have D = {traj.positions.shape[2]}, metadata dim = {self.dim}",
                    f"{tid}.positions",
                )
        return data

    def __getitem__(self, name: str) -> dict[str, GnsTrajectory]:
        return self.split(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self.splits)

    def __len__(self) -> int:
        return len(self.splits)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self.splits

    def __repr__(self) -> str:
        return f"GnsDataset({self.directory!r}, dim={self.dim}, splits={list(self.splits)})"


def file_sha256(path: PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_dataset(ds: GnsDataset) -> dict[str, Any]:
    """Check a GNS dataset against its own metadata; returns a summary with
    ``problems`` (a list of sentences, empty when all holds).

    Checked: every split present (a missing one is a problem for our datasets,
    whose metadata record ``trajectories`` per split, and a note otherwise);
    each split file's SHA-256 against ``metadata["sha256"]`` when recorded;
    every trajectory has ``sequence_length + 1`` frames (GNS layout), the
    metadata's dimension and finite positions; positions outside
    ``bounds`` are counted (particles may rest up to a cell outside them; more
    than 10 % of the domain's extent is a problem).
    """
    meta = ds.metadata
    problems: list[str] = []
    notes: list[str] = []
    sha = meta.get("sha256")
    recorded: dict[str, Any] = sha if isinstance(sha, dict) else {}
    counts = meta.get("trajectories")
    expected_splits: dict[str, Any] | None = counts if isinstance(counts, dict) else None
    bounds = np.asarray(meta["bounds"], np.float64)
    extent = bounds[:, 1] - bounds[:, 0]
    seq = int(meta["sequence_length"])
    info: dict[str, Any] = {"directory": ds.directory, "dim": ds.dim, "splits": {}, "metadata": meta}
    for name in SPLITS:
        if name not in ds.splits:
            (problems if expected_splits is not None and name in expected_splits else notes).append(f"split {name!r} is missing ({ds.path(name)})")
            continue
        if name in recorded:
            actual = file_sha256(ds.path(name))
            if actual != recorded[name]:
                problems.append(f"{name}.npz: sha256 {actual[:16]}… differs from the recorded {str(recorded[name])[:16]}… (modified or truncated)")
        trajs = ds.split(name)
        shapes = [t.positions.shape for t in trajs.values()]
        types = sorted({int(v) for t in trajs.values() for v in np.unique(t.particle_type)})
        outside, worst = 0, 0.0
        for key, t in trajs.items():
            x = np.asarray(t.positions)
            if x.shape[0] != seq + 1:
                problems.append(f"{name}/{key}: {x.shape[0]} frames, the metadata's sequence_length {seq} means {seq + 1}")
            if x.shape[-1] != ds.dim:
                problems.append(f"{name}/{key}: dimension {x.shape[-1]}, the metadata says {ds.dim}")
                continue
            if not np.isfinite(x).all():
                problems.append(f"{name}/{key}: non-finite positions")
                continue
            below = (bounds[:, 0] - x).max(axis=(0, 1))
            above = (x - bounds[:, 1]).max(axis=(0, 1))
            excess = float(np.max(np.maximum(below, above) / extent))
            if excess > 0:
                outside += 1
                worst = max(worst, excess)
        if worst > 0.1:
            problems.append(f"{name}: positions lie up to {100 * worst:.0f}% of the domain outside bounds")
        if expected_splits is not None and name in expected_splits and int(expected_splits[name]) != len(trajs):
            problems.append(f"{name}: {len(trajs)} trajectories, the metadata records {expected_splits[name]}")
        info["splits"][name] = {
            "trajectories": len(trajs),
            "frames": sorted({s[0] for s in shapes}),
            "particles": {"min": min(s[1] for s in shapes), "max": max(s[1] for s in shapes)} if shapes else None,
            "particle_types": types,
            "trajectories_outside_bounds": outside,
            "sha256_checked": name in recorded,
        }
    info["problems"] = problems
    info["notes"] = notes
    return info


__all__ = [
    "METADATA_FILE",
    "REQUIRED_METADATA",
    "GNS_SAND",
    "SPLITS",
    "GNS_WATER",
    "GnsDataset",
    "GnsTrajectory",
    "SplitNotFoundError",
    "check_dataset",
    "compute_statistics",
    "file_sha256",
    "read_metadata",
    "read_split",
    "validate_metadata",
    "write_metadata",
    "write_split",
]
