"""The validation curve of a training run: one row per evaluation, kept in
the checkpoint and written beside it.

A row is a flat dict of numbers (and None) a family's evaluation returns:
the step, the training loss since the last evaluation, its validation
scores, seconds and ranks, under the family's own column names. The rows of
the whole run (a resumed run's included, since they travel in the
checkpoint) are rewritten atomically as ``curve.json`` (a JSON list; NaN and
infinities are written as null, so the file is strict JSON) at every
evaluation. A family may also keep an append-only log of every call's rows
(``log.csv``: a header row, then one row per evaluation with the numbers
formatted as ``formats`` says; ``log.jsonl``: one JSON object per line), which
keeps a resumed run's repeated steps too; a CSV log begun with fewer columns
keeps them.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

from hybridmpm.data.gns.io import atomic_write

#: The curve's file beside the checkpoint.
CURVE_FILE = "curve.json"


def _strict(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


class ValidationCurve:
    """The rows of a run's evaluations (module doc), written into ``out``.

    ``log``: the name of the append-only log (``*.csv`` or ``*.jsonl``), or
    None; ``formats``: format specs of the CSV log's numbers by column (e.g.
    ``{"lr": ".3e"}``; other values are written as ``str``)."""

    def __init__(self, out: Path, log: str | None = None, formats: dict[str, str] | None = None) -> None:
        if log is not None and not log.endswith((".csv", ".jsonl")):
            raise ValueError(f"log: a .csv or .jsonl file name, got {log!r}")
        self.out = Path(out)
        self.log = log
        self.formats = dict(formats or {})
        self.rows: list[dict[str, Any]] = []

    def record(self, row: dict[str, Any]) -> None:
        """Append ``row`` and write the files (rank 0 only calls it)."""
        self.rows.append(dict(row))
        text = json.dumps([{k: _strict(v) for k, v in r.items()} for r in self.rows], indent=1)
        atomic_write(self.out / CURVE_FILE, lambda fh: fh.write(text.encode()))
        if self.log is not None:
            (self._append_csv if self.log.endswith(".csv") else self._append_jsonl)(row)

    def _append_jsonl(self, row: dict[str, Any]) -> None:
        with open(self.out / str(self.log), "a") as f:
            f.write(json.dumps({k: _strict(v) for k, v in row.items()}) + "\n")

    def _append_csv(self, row: dict[str, Any]) -> None:
        path = self.out / str(self.log)
        header: list[str] | None = None
        if path.exists():
            with open(path, newline="") as f:
                header = next(csv.reader(f), None)
        with open(path, "a", newline="") as f:
            writer = csv.writer(f)
            if not header:
                header = list(row)
                writer.writerow(header)
            writer.writerow([self._cell(c, row.get(c)) for c in header])

    def _cell(self, column: str, v: Any) -> str:
        if v is None:
            return ""
        spec = self.formats.get(column)
        return format(v, spec) if spec is not None and isinstance(v, (int, float)) else str(v)


__all__ = ["CURVE_FILE", "ValidationCurve"]
