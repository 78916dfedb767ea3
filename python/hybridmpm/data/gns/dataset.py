"""A GNS dataset directory (:class:`GnsDataset`: its splits and metadata) and its check (``hybridmpm inspect``)."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from hybridmpm.conventions import SPLITS
from hybridmpm.data.gns.io import GnsTrajectory, PathLike, read_split
from hybridmpm.data.gns.metadata import METADATA_FILE, read_metadata
from hybridmpm.errors import InvalidInputError


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
