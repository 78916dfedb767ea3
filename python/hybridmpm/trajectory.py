"""A particle trajectory on disk: positions over time plus per-particle data.

:class:`Trajectory` is what ``hybridmpm simulate`` writes (``trajectory.npz``)
and what ``hybridmpm evaluate`` and :mod:`hybridmpm.metrics` read. The file is
a plain ``.npz`` (no pickles) with these keys:

==================  ==============  ======================================================
key                 dtype / shape   meaning
==================  ==============  ======================================================
``positions``       float32 [T,N,D] particle positions [m], D ∈ {2, 3}, finite (required)
``particle_type``   int64 [N]       GNS type codes: water 5, sand 6, kinematic/boundary
                                    obstacle 3 (required)
``dt_frame``        float64 []      seconds of simulated time between *stored* frames,
                                    e.g. ``2.5e-3 · r_t`` (required, finite, > 0)
``n_grid``          int64 []        cells per dimension of the scene's grid (optional)
``masses``          float32 [N]     particle masses [kg] (optional, finite, >= 0)
``material``        int32 [N]       solver material codes, 0 water, 1 sand, 2 elastic, 3 snow, 4 viscoplastic (optional)
``obstacle_centers`` float64        each obstacle's centre [m] in every stored frame
                    [T,C,D]         (optional: written when the scene has obstacles;
                                    without it the obstacles stand where the scene
                                    put them)
``body_center``     float64         each rigid body's centre of mass [m] in every stored
                    [T,B,D]         frame (optional: written when the scene has bodies)
``body_rotation``   float64         each body's rotation (columns: its axes) per frame
                    [T,B,D,D]
``body_mass``       float64 [B]     each body's mass [kg; per unit depth in 2D, as ``masses``]
anything else       any             kept in :attr:`Trajectory.extras`, saved as-is
==================  ==============  ======================================================
"""

from __future__ import annotations

import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import NpyHeader, npz_headers, read_npz_member
from hybridmpm.limits import check_allocation

#: Keys with a meaning of their own; every other key of a file is an extra.
RESERVED_KEYS = ("positions", "particle_type", "dt_frame", "n_grid", "masses", "material", "obstacle_centers", "body_center", "body_rotation", "body_mass")
#: The rigid bodies' arrays: all three or none.
_BODY_KEYS = ("body_center", "body_rotation", "body_mass")
_REQUIRED_KEYS = ("positions", "particle_type", "dt_frame")
#: Largest velocity a trajectory's frames may imply [m/s]: ``|Δx| / dt_frame`` must stay a finite float32
#: (what the point clouds and the USD file store), so no export holds an infinite value.
MAX_FRAME_VELOCITY = float(np.finfo(np.float32).max)
#: Position values :func:`check_frame_velocities` differences at once (float64: 512 KiB; its few temporaries stay
#: small beside what a caller holds: at 8 MiB a 1000-frame control on water3d peaked 15 MB higher).
_VELOCITY_BLOCK_VALUES = 1 << 16


def check_frame_velocities(positions: np.ndarray, dt_frame: float, field: str = "dt_frame") -> None:
    """Refuse a ``dt_frame`` [s] so small for ``positions`` (finite, [T, N, D])
    that a particle's velocity between two frames, ``|Δx| / dt_frame`` per
    axis, exceeds :data:`MAX_FRAME_VELOCITY` — what the exports
    (point clouds, USD) would store as infinity. A block of frames at a time
    (at most :data:`_VELOCITY_BLOCK_VALUES` values copied at once, no
    ``[T, N, D]`` copy, and no Python step per frame: a million frames of one
    particle take milliseconds). Raises :class:`InvalidInputError` naming ``field``."""
    p = np.asarray(positions)
    frames = max(1, _VELOCITY_BLOCK_VALUES // max(1, math.prod(p.shape[1:])))
    step = 0.0
    for a in range(1, p.shape[0], frames):
        b = min(p.shape[0], a + frames)
        step = max(step, float(np.abs(p[a:b].astype(np.float64) - p[a - 1 : b - 1]).max(initial=0.0)))
    if step / float(dt_frame) > MAX_FRAME_VELOCITY:
        raise InvalidInputError(
            f"{field}: {float(dt_frame)!r} s between frames makes the particles' velocities overflow "
            f"(a particle moves {step:.3g} m in one frame: {step / float(dt_frame):.3g} m/s, beyond float32)",
            field,
        )


def all_finite(x: np.ndarray) -> bool:
    """Whether every value of the float array ``x`` is finite: its smallest and largest are (a NaN makes both NaN,
    an infinity one of them), without a boolean array as large as ``x``. True for an empty array."""
    return x.size == 0 or bool(np.isfinite(np.min(x)) and np.isfinite(np.max(x)))


def load_bytes(h: NpyHeader) -> int:
    """What reading the array of header ``h`` takes at its peak [bytes]: the
    array as read, its validated copy (float32 positions, int64 types, ...)
    and a one-byte finiteness mask per value."""
    return 2 * h.nbytes + h.size


def _scalar(name: str, value: Any) -> Any:
    arr = np.asarray(value)
    if arr.size != 1 or arr.ndim > 1:
        raise InvalidInputError(f"{name}: expected a scalar, got shape {list(arr.shape)}", name)
    if arr.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name}: expected a real number, got dtype {arr.dtype}", name)
    return arr.reshape(()).item()


@dataclass
class Trajectory:
    """Positions over time of one rollout, with the per-particle data needed to
    evaluate it.

    Attributes
    ----------
    positions:
        float32 [T, N, D] [m], D ∈ {2, 3}, finite. Other floating dtypes are
        converted to float32.
    particle_type:
        int64 [N], GNS codes (water 5, sand 6, kinematic obstacle
        :data:`GNS_KINEMATIC` = 3).
    dt_frame:
        Simulated time between stored frames [s], finite and > 0 (``2.5e-3``
        for every MPM frame, ``2.5e-3 · r_t`` for a neural rollout), and
        large enough that no particle's velocity between two frames,
        ``|Δx| / dt_frame``, exceeds :data:`MAX_FRAME_VELOCITY` (the largest
        float32: the exports store velocities as float32).
    n_grid:
        Cells per dimension of the scene's grid (3 … 4096), or ``None``
        (then consumers use 128 in 2D and 64 in 3D).
    masses:
        float32 [N] [kg], finite and >= 0, or ``None``.
    material:
        int32 [N] solver material codes, or ``None``.
    extras:
        Further named arrays (e.g. ``one_step_positions``), saved and loaded
        as-is; names may not be one of :data:`RESERVED_KEYS`.
    obstacle_centers:
        float64 [T, C, D] [m], finite: each of the scene's ``C`` obstacles'
        centre in every stored frame (:attr:`~hybridmpm.sim.MpmSimulator.obstacle_centers`;
        the surfaces and the USD file place the obstacles there), or
        ``None``: the obstacles stand where the scene put them.
    body_center, body_rotation, body_mass:
        float64 [T, B, D] [m], [T, B, D, D] and [B] [kg; per unit depth in
        2D], finite, the masses > 0: the scene's ``B`` rigid bodies in every
        stored frame; all three or none (a scene without bodies).

    Construction validates and normalises every field and raises
    :class:`~hybridmpm.errors.InvalidInputError` naming the bad field.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    dt_frame: float
    n_grid: int | None = None
    masses: np.ndarray | None = None
    material: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    obstacle_centers: np.ndarray | None = None
    body_center: np.ndarray | None = None
    body_rotation: np.ndarray | None = None
    body_mass: np.ndarray | None = None

    def __post_init__(self) -> None:
        pos = np.asarray(self.positions)
        if pos.dtype.kind != "f":
            raise InvalidInputError(f"positions: expected a floating-point array, got dtype {pos.dtype}", "positions")
        if pos.ndim != 3 or pos.shape[2] not in (2, 3):
            raise InvalidInputError(f"positions: expected shape [T, N, D] with D in {{2, 3}}, got {list(pos.shape)}", "positions")
        if pos.shape[0] < 1 or pos.shape[1] < 1:
            raise InvalidInputError(f"positions: need at least one frame and one particle, got shape {list(pos.shape)}", "positions")
        pos = np.ascontiguousarray(pos, dtype=np.float32)
        if not all_finite(pos):
            t, i = np.argwhere(~np.isfinite(pos).all(axis=2))[0]
            raise InvalidInputError(f"positions: frame {t}, particle {i} has a non-finite coordinate", "positions")
        self.positions = pos
        n = pos.shape[1]

        ptype = np.asarray(self.particle_type)
        if ptype.dtype.kind not in "iu":
            raise InvalidInputError(f"particle_type: expected an integer array, got dtype {ptype.dtype}", "particle_type")
        if ptype.shape != (n,):
            raise InvalidInputError(f"particle_type: expected shape [{n}] (one per particle), got {list(ptype.shape)}", "particle_type")
        self.particle_type = ptype.astype(np.int64)

        dt = _scalar("dt_frame", self.dt_frame)
        if not (math.isfinite(dt) and dt > 0):
            raise InvalidInputError(f"dt_frame: must be a finite number > 0 [s], got {dt!r}", "dt_frame")
        self.dt_frame = float(dt)
        check_frame_velocities(pos, self.dt_frame)

        if self.n_grid is not None:
            g = _scalar("n_grid", self.n_grid)
            if not (float(g).is_integer() and 3 <= g <= 4096):
                raise InvalidInputError(f"n_grid: must be an integer in [3, 4096], got {g!r}", "n_grid")
            self.n_grid = int(g)

        if self.masses is not None:
            m = np.asarray(self.masses)
            if m.dtype.kind not in "fiu" or m.shape != (n,):
                raise InvalidInputError(f"masses: expected a real array of shape [{n}], got {m.dtype} {list(m.shape)}", "masses")
            m = m.astype(np.float32)
            if not (np.isfinite(m) & (m >= 0)).all():
                raise InvalidInputError("masses: must be finite and >= 0 [kg]", "masses")
            self.masses = m

        if self.material is not None:
            mat = np.asarray(self.material)
            if mat.dtype.kind not in "iu" or mat.shape != (n,):
                raise InvalidInputError(f"material: expected an integer array of shape [{n}], got {mat.dtype} {list(mat.shape)}", "material")
            self.material = mat.astype(np.int32)

        if self.obstacle_centers is not None:
            oc = np.asarray(self.obstacle_centers)
            if oc.dtype.kind not in "fiu" or oc.ndim != 3 or oc.shape[0] != pos.shape[0] or oc.shape[2] != pos.shape[2]:
                raise InvalidInputError(
                    f"obstacle_centers: expected a real array [{pos.shape[0]}, C, {pos.shape[2]}] (a centre per frame and obstacle), got {oc.dtype} {list(oc.shape)}",
                    "obstacle_centers",
                )
            oc = np.ascontiguousarray(oc, np.float64)
            if not np.isfinite(oc).all():
                raise InvalidInputError("obstacle_centers: contains NaN or inf", "obstacle_centers")
            self.obstacle_centers = oc

        self._check_bodies(pos.shape[0], pos.shape[2])
        extras: dict[str, np.ndarray] = {}
        for key, value in dict(self.extras).items():
            if not isinstance(key, str) or not key or key in RESERVED_KEYS:
                raise InvalidInputError(f"extras: key {key!r} must be a non-empty string other than {', '.join(RESERVED_KEYS)}", "extras")
            arr = np.asarray(value)
            if arr.dtype.kind == "O":
                raise InvalidInputError(f"extras.{key}: object arrays cannot be saved without pickle", f"extras.{key}")
            extras[key] = arr
        self.extras = extras

    def _check_bodies(self, t: int, d: int) -> None:
        given = [k for k in _BODY_KEYS if getattr(self, k) is not None]
        if not given:
            return
        if len(given) != 3:
            k = next(k for k in _BODY_KEYS if k not in given)
            raise InvalidInputError(f"{k}: missing ({', '.join(given)} given: the body arrays go together)", k)
        b = np.asarray(self.body_mass).shape[0] if np.ndim(np.asarray(self.body_mass)) == 1 else -1
        for k, shape in (("body_center", (t, b, d)), ("body_rotation", (t, b, d, d)), ("body_mass", (b,))):
            a = np.asarray(getattr(self, k))
            if a.dtype.kind not in "fiu" or a.shape != shape or b < 0:
                raise InvalidInputError(f"{k}: expected a real array {list(shape)} (T frames, B bodies, D = {d}), got {a.dtype} {list(a.shape)}", k)
            a = np.ascontiguousarray(a, np.float64)
            if not np.isfinite(a).all() or (k == "body_mass" and not (a > 0).all()):
                raise InvalidInputError(f"{k}: must be finite{' and > 0 kg' if k == 'body_mass' else ''}", k)
            setattr(self, k, a)

    # ------------------------------------------------------------------ info
    @property
    def num_frames(self) -> int:
        """T."""
        return int(self.positions.shape[0])

    @property
    def num_particles(self) -> int:
        """N (all particles, kinematic ones included)."""
        return int(self.positions.shape[1])

    @property
    def dim(self) -> int:
        """D ∈ {2, 3}."""
        return int(self.positions.shape[2])

    @property
    def times(self) -> np.ndarray:
        """float64 [T]: the simulated time of every stored frame [s], ``t·dt_frame``."""
        return np.arange(self.num_frames, dtype=np.float64) * self.dt_frame

    def fluid_mask(self) -> np.ndarray:
        """bool [N]: True for particles that are not kinematic (GNS type 3)."""
        return np.asarray(self.particle_type != GNS_KINEMATIC)

    # ------------------------------------------------------------------ io
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every field as the named arrays stored in the file."""
        out: dict[str, np.ndarray] = {
            "positions": self.positions,
            "particle_type": self.particle_type,
            "dt_frame": np.float64(self.dt_frame),  # type: ignore[dict-item]
        }
        if self.n_grid is not None:
            out["n_grid"] = np.int64(self.n_grid)  # type: ignore[assignment]
        if self.masses is not None:
            out["masses"] = self.masses
        if self.material is not None:
            out["material"] = self.material
        if self.obstacle_centers is not None:
            out["obstacle_centers"] = self.obstacle_centers
        for k in _BODY_KEYS:
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        out.update(self.extras)
        return out

    def save(self, path: str | os.PathLike[str], *, compressed: bool = True) -> Path:
        """Write a ``.npz`` at ``path`` (exactly that name) atomically: a
        temporary file beside it, then ``os.replace``, so an existing file is
        either kept whole or replaced whole. Returns the path."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        writer = np.savez_compressed if compressed else np.savez
        try:
            with open(tmp, "wb") as f:
                writer(f, allow_pickle=False, **self.to_arrays())
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Trajectory:
        """Read and validate a trajectory ``.npz`` (no pickles).

        Every array is sized from its ``.npy`` header before any is read
        (:func:`~hybridmpm.files.npz_headers`): the array, its validated
        copy and a byte per value (:func:`load_bytes`), each and all
        together, against the memory budget (:func:`hybridmpm.limits.check_allocation`).

        Raises :class:`~hybridmpm.errors.InvalidInputError`: with field
        ``"path"`` if the file is missing or not a readable ``.npz``; with the
        key's name if a required key (``positions``, ``particle_type``,
        ``dt_frame``) is missing, an array's header is malformed, declares
        more than its member holds, needs pickle or more than the memory
        budget, or any array is malformed (``obstacle_centers``: not
        [T, C, D], or not finite). A file without ``obstacle_centers``
        loads with None (static obstacles).
        """
        path = Path(path)
        zf = _open_npz(path)
        arrays: dict[str, np.ndarray] = {}
        with zf:
            headers = npz_headers(zf)  # every array's shape and dtype, before any is read
            for h in headers:
                if h.dtype.hasobject:
                    raise InvalidInputError(f"{h.name}: cannot be read from {path} without pickle (dtype {h.dtype})", h.name)
                check_allocation(h.name, load_bytes(h), f"reading {h.name} {list(h.shape)} {h.dtype} from {path.name}")
            if headers:
                biggest = max(headers, key=load_bytes)
                check_allocation(biggest.name, sum(load_bytes(h) for h in headers), f"reading the trajectory {path.name} (its largest array: {biggest.name})")
            keys = [h.name for h in headers]
            for h in headers:
                try:
                    arrays[h.name] = read_npz_member(zf, h)
                except (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error) as e:
                    raise InvalidInputError(f"path: {path}: entry {h.name!r} is corrupt ({e})", "path") from e
        for key in _REQUIRED_KEYS:
            if key not in arrays:
                raise InvalidInputError(f"{key}: missing from {path} (it has: {', '.join(keys) or 'nothing'})", key)
        return cls(
            positions=arrays.pop("positions"),
            particle_type=arrays.pop("particle_type"),
            dt_frame=arrays.pop("dt_frame"),  # type: ignore[arg-type]
            n_grid=arrays.pop("n_grid", None),  # type: ignore[arg-type]
            masses=arrays.pop("masses", None),
            material=arrays.pop("material", None),
            obstacle_centers=arrays.pop("obstacle_centers", None),
            body_center=arrays.pop("body_center", None),
            body_rotation=arrays.pop("body_rotation", None),
            body_mass=arrays.pop("body_mass", None),
            extras=arrays,
        )


def _open_npz(path: Path) -> zipfile.ZipFile:
    """The trajectory file ``path`` opened as a zip archive; :class:`InvalidInputError` (``path``)
    for a missing file, a single ``.npy`` array or anything that is no readable ``.npz``."""
    if not path.is_file():
        raise InvalidInputError(f"path: no such file: {path}", "path")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except OSError as e:
        raise InvalidInputError(f"path: cannot read {path} ({e})", "path") from e
    if magic == b"\x93NUMPY":
        raise InvalidInputError(f"path: {path} is a single .npy array, not an .npz archive", "path")
    if magic[:2] != b"PK":
        raise InvalidInputError(f"path: {path} is not an .npz archive (no zip signature)", "path")
    try:
        return zipfile.ZipFile(path)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InvalidInputError(f"path: {path} is not a readable .npz file ({e})", "path") from e


def trajectory_headers(path: str | os.PathLike[str]) -> dict[str, NpyHeader]:
    """Every array of the trajectory file ``path`` as its ``.npy`` header declares it (shape, dtype),
    by key, read without any array's data (:func:`~hybridmpm.files.npz_headers`): what sizes work on
    a trajectory (``hybridmpm evaluate``) before it is loaded. Raises :class:`InvalidInputError` as
    :meth:`Trajectory.load` does for the path (``path``) and for a malformed header (the key)."""
    with _open_npz(Path(path)) as zf:
        return {h.name: h for h in npz_headers(zf)}


__all__ = ["MAX_FRAME_VELOCITY", "RESERVED_KEYS", "Trajectory", "check_frame_velocities", "load_bytes", "trajectory_headers"]
