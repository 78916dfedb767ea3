"""The scaffold every training family stands on (torch; the ``train`` extra):

* :mod:`~hybridmpm.train.scaffold.config` — :class:`RunConfig`, the settings'
  base: fields with their own checks (an error names the field) and the rule
  by which a run directory is resumed;
* :mod:`~hybridmpm.train.scaffold.loop` — :class:`TrainingLoop`: the loop with
  its progress bar, evaluations and atomic, resumable checkpoints (model,
  optimiser, scheduler, step, random streams), :func:`start_run`,
  :func:`load_checkpoint`;
* :mod:`~hybridmpm.train.scaffold.curve` — :class:`ValidationCurve`: a row per
  evaluation, kept in the checkpoint, written as ``curve.json`` (and a family's
  CSV or JSON-lines log) beside it;
* :mod:`~hybridmpm.train.scaffold.metadata` — :func:`export_metadata`: the run's
  facts in an exported model's metadata.

The GNS (:mod:`hybridmpm.train.gns.train`), the grid model
(:mod:`hybridmpm.train.grid.train`) and the controller
(:mod:`hybridmpm.train.control.train`) train through it; data-parallel ranks
come from :mod:`hybridmpm.train.distributed`.
"""

from hybridmpm.train.scaffold.config import RunConfig, flag, integer, number, one_of, optional, processes, setting
from hybridmpm.train.scaffold.curve import CURVE_FILE, ValidationCurve
from hybridmpm.train.scaffold.loop import CHECKPOINT, CONFIG_FILE, Parts, TrainingLoop, load_checkpoint, save_torch, start_run
from hybridmpm.train.scaffold.metadata import data_sha256, export_metadata

__all__ = [
    "CHECKPOINT",
    "CONFIG_FILE",
    "CURVE_FILE",
    "Parts",
    "RunConfig",
    "TrainingLoop",
    "ValidationCurve",
    "data_sha256",
    "export_metadata",
    "flag",
    "integer",
    "load_checkpoint",
    "number",
    "one_of",
    "optional",
    "processes",
    "save_torch",
    "setting",
    "start_run",
]
