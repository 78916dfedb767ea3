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

from hybridmpm.conventions import GNS_SAND, GNS_WATER, SPLITS
from hybridmpm.data.gns.dataset import GnsDataset, SplitNotFoundError, check_dataset, file_sha256
from hybridmpm.data.gns.io import GnsTrajectory, read_split, write_split
from hybridmpm.data.gns.metadata import METADATA_FILE, REQUIRED_METADATA, read_metadata, validate_metadata, write_metadata
from hybridmpm.data.gns.statistics import compute_statistics

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
