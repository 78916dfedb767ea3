"""Data shipped with hybridmpm and dataset input/output.

* ``martin_moyce_1952.csv``: the dam-break experiment (see
  :mod:`hybridmpm.validation`).
* :mod:`hybridmpm.data.gns`: datasets in the public GNS layout (GNS,
  Sanchez-Gonzalez et al. 2020; the geoelements/gns npz layout).
"""

from hybridmpm.data.gns import (
    GNS_SAND,
    GNS_WATER,
    METADATA_FILE,
    REQUIRED_METADATA,
    SPLITS,
    GnsDataset,
    GnsTrajectory,
    SplitNotFoundError,
    compute_statistics,
    read_metadata,
    read_split,
    validate_metadata,
    write_metadata,
    write_split,
)

__all__ = [
    "METADATA_FILE",
    "REQUIRED_METADATA",
    "GNS_SAND",
    "SPLITS",
    "GNS_WATER",
    "GnsDataset",
    "GnsTrajectory",
    "SplitNotFoundError",
    "compute_statistics",
    "read_metadata",
    "read_split",
    "validate_metadata",
    "write_metadata",
    "write_split",
]
