"""The one benchmark harness: what every benchmark script records beside its
figures, how it takes repeats, and how it writes its results.

Every script under ``benchmarks/`` writes through this module
(``tests/test_architecture_bench.py`` holds it); it lives in the package so that
``hybridmpm bench`` can record the same provenance:

* :func:`provenance` — the machine (CPU model, cores, host), the commit
  (``-dirty`` when the code differs from it), the versions (hybridmpm,
  numpy, onnxruntime, Python), the load average before (when this module was
  imported, i.e. when the script started, or at :func:`mark_start`) and
  after, the share of CPU time the hypervisor stole in between, the command
  line and the date. Built on :mod:`hybridmpm.bench.env`.
* :func:`round_robin` — ``repeats`` runs of each configuration taken round
  the configurations (all once, then all again), so that a slow spell of a
  shared machine lands on several configurations' runs, not on all of one's.
* :func:`write_results` — ``OUT/NAME.json`` (the script's document with its
  provenance under ``"provenance"``) and ``OUT/NAME.md`` (the title, a header
  with the command and the machine, then the script's tables), and figures,
  each written atomically (a temporary file beside it, then ``os.replace``:
  an interrupted run leaves the previous result whole). ``append=True``
  appends a Markdown section instead (reports that several runs extend).
* :func:`write_file` — the same atomic write for what is not a result (a
  model card, package data, a plan handed to a subprocess).
* :func:`read_results` — a result's document, whether written here (a JSON
  object) or before (some scripts wrote a bare list of rows).

Figures are ratios against a peer measured in the same run: the header says
the load, so a reader can tell a quiet run from a busy one.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import shlex
import sys
import tempfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from hybridmpm.bench.env import cpu_times, environment, steal_fraction

T = TypeVar("T")
R = TypeVar("R")

#: The repository's root (the command line names scripts relative to it).
REPO_ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class Start:
    """The machine's state when a run started: load averages (1, 5, 15 min),
    :func:`hybridmpm.bench.env.cpu_times` and the wall-clock date."""

    load: tuple[float, float, float]
    ticks: tuple[int, int] | None
    date: _dt.datetime


def load_average() -> tuple[float, float, float]:
    """The machine's load averages over 1, 5 and 15 minutes (zeros where the
    platform has none)."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return (0.0, 0.0, 0.0)
    return (one, five, fifteen)


def mark_start() -> Start:
    """Record now as the start of the run (the load before, the CPU ticks, the
    date); :func:`provenance` reports against the latest mark. Importing this
    module marks it once, so a script need not call it unless its run starts
    later (after a long setup it does not time)."""
    global _START
    _START = Start(load_average(), cpu_times(), _dt.datetime.now(_dt.timezone.utc))
    return _START


_START: Start = Start(load_average(), cpu_times(), _dt.datetime.now(_dt.timezone.utc))


def command(argv: Sequence[str] | None = None) -> str:
    """The command line that reproduces the run, from the repository root:
    ``python benchmarks/SCRIPT.py ARGS`` for a script (its path relative to
    the root when inside it), ``NAME ARGS`` for an installed command such as
    ``hybridmpm`` (``argv``: the program then its arguments; default
    ``sys.argv``)."""
    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return "python"
    prog = Path(argv[0])
    if prog.suffix != ".py":
        return shlex.join([prog.name, *map(str, argv[1:])])
    try:
        shown = str(prog.resolve().relative_to(REPO_ROOT))
    except ValueError:
        shown = str(argv[0])
    return "python " + shlex.join([shown, *map(str, argv[1:])])


def script_argv(script: str, argv: Sequence[str] | None) -> list[str] | None:
    """The full command of a script whose ``main(argv)`` may be called with
    its arguments alone (from a test): ``[script, *argv]``, or None (then
    ``sys.argv``) when ``argv`` is None."""
    return None if argv is None else [script, *argv]


def provenance(argv: Sequence[str] | None = None, *, start: Start | None = None) -> dict[str, Any]:
    """Where and how a result was made, recorded with it.

    Keys: ``machine`` (architecture and CPU model), ``cores``, ``host``,
    ``commit`` (12 hex digits, ``-dirty`` if tracked code under ``python/`` or
    ``rust/`` differs from it), ``hybridmpm``, ``numpy``, ``onnxruntime``,
    ``python`` (versions), ``load_before`` and ``load_after`` (load averages
    over 1, 5, 15 minutes at ``start`` — default the latest
    :func:`mark_start`, at the latest this module's import — and now),
    ``steal`` (the share of CPU time the hypervisor gave to others in
    between, or None where unknown), ``started`` and ``date`` (UTC, ISO 8601),
    ``command`` (:func:`command` of ``argv``)."""
    s = _START if start is None else start
    now = _dt.datetime.now(_dt.timezone.utc)
    env = environment()
    return {
        "machine": env["machine"],
        "cores": env["cores"],
        "host": platform.node(),
        "commit": env["commit"],
        "hybridmpm": env["hybridmpm"],
        "numpy": env["numpy"],
        "onnxruntime": env["onnxruntime"],
        "python": env["python"],
        "load_before": [round(x, 2) for x in s.load],
        "load_after": [round(x, 2) for x in load_average()],
        "steal": steal_fraction(s.ticks, cpu_times()),
        "started": s.date.isoformat(timespec="seconds"),
        "date": now.isoformat(timespec="seconds"),
        "command": command(argv),
    }


def header(prov: Mapping[str, Any]) -> list[str]:
    """The Markdown lines that say how a result was made (the command, the
    machine and versions, the date, the load and the stolen CPU time)."""
    steal = prov.get("steal")
    stolen = "unknown" if steal is None else f"{100 * steal:.0f} %"
    before, after = prov.get("load_before") or [float("nan")], prov.get("load_after") or [float("nan")]
    return [
        f"Command: `{prov['command']}`  ",
        f"Machine: {prov['machine']}, {prov['cores']} cores ({prov['host']}); hybridmpm {prov['hybridmpm']} (commit {prov['commit']}), "
        f"numpy {prov['numpy']}, onnxruntime {prov['onnxruntime']}, Python {prov['python']}  ",
        f"Run: {prov['started']} to {prov['date']}; load average {before[0]:.2f} before, {after[0]:.2f} after; CPU time stolen by the hypervisor: {stolen}",
    ]


def round_robin(configs: Sequence[T], repeats: int, run: Callable[[T], R]) -> list[list[R]]:
    """``run(config)`` ``repeats`` times for each of ``configs``, taken round
    the configurations (every configuration once, then every one again), so
    that a slow spell of the machine lands on several configurations' runs,
    not on all of one's. Returns ``results[i][k]``: configuration ``i``'s
    ``k``-th run. Raises ValueError if ``repeats < 1``."""
    if repeats < 1:
        raise ValueError(f"repeats: must be >= 1, got {repeats}")
    results: list[list[R]] = [[] for _ in configs]
    for _ in range(repeats):
        for i, cfg in enumerate(configs):
            results[i].append(run(cfg))
    return results


def table(head: Sequence[str], rows: Iterable[Sequence[Any]], align: str | None = None) -> list[str]:
    """A Markdown table's lines: the header, the rule (``align``: one of
    ``l``, ``r``, ``c`` per column, default all left) and one line per row
    (cells as ``str``)."""
    rules = {"l": "---", "r": "---:", "c": ":---:"}
    align = align or "l" * len(head)
    if len(align) != len(head):
        raise ValueError(f"align: {len(align)} letters for {len(head)} columns")
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(rules[a] for a in align) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return lines


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"a benchmark result holds a {type(obj).__name__}, which JSON cannot hold")


def dumps(obj: Any, *, indent: int | None = 1, sort_keys: bool = False) -> str:
    """``obj`` as JSON text (numpy arrays and scalars as lists and numbers,
    paths as strings; NaN as ``NaN``, as Python's reader takes it), ending in
    a newline."""
    return json.dumps(obj, indent=indent, sort_keys=sort_keys, default=_json_default) + "\n"


def write_file(path: str | os.PathLike[str], data: str | bytes) -> Path:
    """Write ``data`` to ``path`` atomically (a temporary file in the same
    folder, then ``os.replace``); creates the folder. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 1, sort_keys: bool = False) -> Path:
    """``obj`` as JSON (:func:`dumps`) at ``path``, atomically: for what is
    not a result (package data, a plan, a resumable state); results go
    through :func:`write_results`, which adds their provenance."""
    return write_file(path, dumps(obj, indent=indent, sort_keys=sort_keys))


def save_figure(fig: Any, path: str | os.PathLike[str], **savefig: Any) -> Path:
    """Save a matplotlib figure at ``path`` atomically (its format from the
    suffix) and close it. Returns the path."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or None, **savefig)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    finally:
        plt.close(fig)
    return path


def _with_header(markdown: str, prov: Mapping[str, Any]) -> str:
    """The header after the text's first heading line (``#``/``##``), or at
    its top when it starts with none."""
    lead = len(markdown) - len(markdown.lstrip("\n"))
    body = markdown[lead:]
    first, _, rest = body.partition("\n")
    head = "\n".join(header(prov))
    if first.startswith("#"):
        return "\n" * lead + f"{first}\n\n{head}\n\n{rest.lstrip(chr(10))}"
    return "\n" * lead + f"{head}\n\n{body}"


def write_results(
    out: str | os.PathLike[str],
    name: str,
    *,
    doc: Mapping[str, Any] | None = None,
    markdown: str | Sequence[str] | None = None,
    figures: Mapping[str, Any] | None = None,
    argv: Sequence[str] | None = None,
    append: bool = False,
    sort_keys: bool = False,
    indent: int | None = 1,
    dpi: int | None = None,
) -> dict[str, Path]:
    """Write a benchmark's results under the folder ``out`` (created).

    * ``doc`` → ``out/name.json``: ``{"provenance": provenance(argv), **doc}``
      (``doc`` must not hold its own ``"provenance"``).
    * ``markdown`` (text, or sections joined by blank lines) →
      ``out/name.md``: its first line if a heading, then the
      :func:`header` (the command, the machine, the load), then the rest.
      ``append=True`` appends it (with its header) to the file instead of
      replacing it: reports that several runs or scripts extend.
    * ``figures`` (file name relative to ``out``, or a path, → a matplotlib
      figure) → saved with :func:`save_figure` (``dpi`` if given), and their
      names listed under the JSON's ``"figures"``.

    Every file is written atomically. Returns the paths written by kind
    (``json``, ``md``, and each figure's name). Raises ValueError when
    nothing is given or ``doc`` holds ``"provenance"``."""
    if doc is None and markdown is None and not figures:
        raise ValueError("write_results: nothing to write (doc, markdown and figures all empty)")
    out = Path(out)
    prov = provenance(argv)
    written: dict[str, Path] = {}
    for fname, fig in (figures or {}).items():
        path = Path(fname) if Path(fname).is_absolute() else out / fname
        written[fname] = save_figure(fig, path, **({} if dpi is None else {"dpi": dpi}))
    if doc is not None:
        if "provenance" in doc:
            raise ValueError("write_results: doc already holds 'provenance' (the harness adds it)")
        full = {"provenance": prov, **doc}
        if figures:
            full["figures"] = sorted(figures)
        written["json"] = write_json(out / f"{name}.json", full, indent=indent, sort_keys=sort_keys)
    if markdown is not None:
        text = markdown if isinstance(markdown, str) else "\n\n".join(s.strip("\n") for s in markdown)
        text = _with_header(text, prov).rstrip("\n") + "\n"
        path = out / f"{name}.md"
        if append and path.is_file():
            text = path.read_text() + ("\n" if not text.startswith("\n") else "") + text
        written["md"] = write_file(path, text)
    return written


def read_results(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A result's document: the JSON object :func:`write_results` wrote, or
    ``{"rows": [...]}`` for a file an older script wrote as a bare list.
    Raises ValueError for anything else."""
    obj = json.loads(Path(path).read_text())
    if isinstance(obj, list):
        return {"rows": obj}
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: a benchmark result is a JSON object or list, not {type(obj).__name__}")
    return obj


__all__ = [
    "REPO_ROOT",
    "Start",
    "command",
    "cpu_times",
    "dumps",
    "header",
    "load_average",
    "mark_start",
    "provenance",
    "read_results",
    "round_robin",
    "save_figure",
    "script_argv",
    "steal_fraction",
    "table",
    "write_file",
    "write_json",
    "write_results",
]
