"""The training loop every family runs: progress, evaluations, resumable
checkpoints (torch; the ``train`` extra).

A family builds its model, optimiser and random stream (:class:`Parts`) and
hands :class:`TrainingLoop` two functions: ``train_step(step) -> loss`` (draw
a batch from the numpy stream, forward, backward, optimiser step: the
family's own), and ``evaluate(step, train_loss) -> row`` (rank 0's
validation, a row of the :class:`~hybridmpm.train.scaffold.curve.ValidationCurve`).
The loop then

* sets every parameter group's learning rate to ``parts.lr(step)`` before
  each step (a schedule that is a function of the step has no state to save);
* shows a tqdm bar on rank 0 (the running loss every 50 steps, the last
  evaluation's ``postfix``);
* every ``every`` steps and at the last one: sums the ranks' mean loss and
  CPU seconds (every rank calls it), and on rank 0 evaluates, records the
  row, keeps the best ``score`` (``on_best``), and saves the checkpoint
  atomically (``before_save`` runs first: what must exist when a run
  resumes from that checkpoint);
* stops early, at a step all ranks agree on, when ``stop()`` holds on any
  rank, and then saves where it stopped.

The checkpoint (``torch.save`` of a dict, written through a temporary file
and ``os.replace``) holds ``model``, ``optimizer`` and ``scheduler`` (when
there is one) state dicts, every ``parts.extra`` module's (e.g. ``ema``),
``step``, ``rng`` (the numpy bit generator's state), ``torch_rng`` (torch's
CPU generator), ``best`` and ``best_step``, ``curve`` (the rows),
``elapsed`` (wall seconds of every call), ``core_seconds`` (CPU seconds of
every rank), ``ranks``, and the family's own entries. :meth:`TrainingLoop.restore`
puts all of it back, so a run resumed from the checkpoint of step k goes on
to the weights an uninterrupted run reaches (``tests/test_train_scaffold.py``).

:func:`start_run` guards a run directory (``train_config.json``: a run is
resumed only by the settings that made it, :meth:`RunConfig.resume_error`);
:func:`load_checkpoint` reads a checkpoint on rank 0 and sends it to the
others, who may not share its directory.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybridmpm.data.gns.io import atomic_write
from hybridmpm.train.distributed import Ranks
from hybridmpm.train.scaffold.config import RunConfig
from hybridmpm.train.scaffold.curve import ValidationCurve

#: The checkpoint's default file name.
CHECKPOINT = "checkpoint.pt"
#: The settings of the run in a directory (:meth:`RunConfig.to_dict` and ``ranks``).
CONFIG_FILE = "train_config.json"
#: Steps between the running loss shown on the progress bar.
SHOW_EVERY = 50


def save_torch(obj: Any, path: Path) -> None:
    """``torch.save(obj)`` to ``path`` atomically (a reader sees the old file or the whole new one)."""
    atomic_write(path, lambda fh: torch.save(obj, fh))


def start_run(config: RunConfig, ranks: Ranks, out: Path, checkpoint: str = CHECKPOINT) -> None:
    """Make ``out`` (rank 0) and refuse settings that cannot resume the run in
    it (:meth:`RunConfig.resume_error`; raised on every rank), else record
    them in ``train_config.json``. A directory whose settings are only in its
    checkpoint is checked against those (``train_config`` of an older
    grid-model run; ``batch`` and ``ranks`` of an older controller's)."""
    error = None
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
        saved_path, ckpt = out / CONFIG_FILE, out / checkpoint
        saved = json.loads(saved_path.read_text()) if saved_path.exists() else None
        if saved is None and ckpt.exists():
            old = torch.load(ckpt, map_location="cpu", weights_only=False)
            if "train_config" in old:
                saved = {**old["train_config"], "ranks": old.get("ranks", 1)}
            elif "batch" in old:  # an older controller's run: its global batch
                saved = {**config.to_dict(), "batch": old["batch"], "ranks": old.get("ranks", 1)}
        error = config.resume_error(saved, ranks.size, out) if saved is not None else None
        if error is None:
            text = json.dumps({**config.to_dict(), "ranks": ranks.size}, indent=2)
            atomic_write(saved_path, lambda fh: fh.write(text.encode()))
    error = ranks.broadcast(error)
    if error is not None:
        raise error


def load_checkpoint(path: Path, ranks: Ranks) -> dict[str, Any] | None:
    """The checkpoint at ``path`` (None if there is none), read by rank 0 and sent to every rank."""
    state = torch.load(path, map_location="cpu", weights_only=False) if ranks.main and path.exists() else None
    return ranks.broadcast(state)


@dataclass
class Parts:
    """What a checkpoint saves and restores: the ``model`` and its
    ``optimizer``, the numpy ``rng`` the family draws its batches (and noise)
    from, ``lr`` (the learning rate as a function of the step, or None: the
    optimiser's own), a ``scheduler`` the family steps (anything with
    ``state_dict``/``load_state_dict``, or None) and ``extra`` modules saved
    by name (an exponential moving average of the weights)."""

    model: torch.nn.Module
    optimizer: torch.optim.Optimizer
    rng: np.random.Generator
    lr: Callable[[int], float] | None = None
    scheduler: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


class TrainingLoop:
    """A run of ``steps`` optimiser steps in ``out`` (module doc).

    ``every``: steps between evaluations and checkpoints; ``desc``: the
    progress bar's label (shown on rank 0 when ``progress``); ``checkpoint``:
    the checkpoint's file name; ``curve``: where the rows go (default: a
    :class:`ValidationCurve` writing ``curve.json``); ``score``: the row's
    column whose smallest value is the best (None: no best is kept);
    ``postfix(row)``: what the bar shows after an evaluation; ``state()``:
    the family's own checkpoint entries (its architecture, its settings).

    ``step``, ``best``, ``best_step``, ``elapsed``, ``core_seconds`` and
    ``losses`` (this call's training losses on this rank) are read by the family."""

    def __init__(
        self,
        out: Path,
        ranks: Ranks,
        parts: Parts,
        *,
        steps: int,
        every: int,
        desc: str,
        progress: bool = True,
        checkpoint: str = CHECKPOINT,
        curve: ValidationCurve | None = None,
        score: str | None = None,
        postfix: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
        state: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        self.out, self.ranks, self.parts = Path(out), ranks, parts
        self.steps, self.every, self.desc, self.progress = steps, every, desc, progress
        self.path = self.out / checkpoint
        self.curve = curve if curve is not None else ValidationCurve(self.out)
        self.score, self.postfix, self.state = score, postfix, state
        self.step = 0
        self.best, self.best_step = math.inf, -1
        self.elapsed = self.core_seconds = 0.0
        self.losses: list[float] = []
        self._interval: list[float] = []
        self._t0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self._shown: dict[str, Any] = {}

    # ------------------------------------------------------------------ checkpoints
    def restore(self, ck: dict[str, Any]) -> None:
        """Put a checkpoint's state back: weights, optimiser, scheduler, extra
        modules, step, random streams, best, curve, seconds. A checkpoint
        without ``torch_rng`` leaves torch's generator as it is."""
        p = self.parts
        p.model.load_state_dict(ck["model"])
        p.optimizer.load_state_dict(ck["optimizer"])
        if p.scheduler is not None and ck.get("scheduler") is not None:
            p.scheduler.load_state_dict(ck["scheduler"])
        for name, module in p.extra.items():
            module.load_state_dict(ck[name])
        p.rng.bit_generator.state = ck["rng"]
        if "torch_rng" in ck:
            torch.set_rng_state(ck["torch_rng"])
        self.step = int(ck["step"])
        self.best, self.best_step = float(ck.get("best", math.inf)), int(ck.get("best_step", -1))
        self.elapsed = float(ck.get("elapsed", 0.0))
        self.core_seconds = float(ck.get("core_seconds", self.elapsed))  # a checkpoint from before the count: its wall time
        self.curve.rows = list(ck.get("curve", []))

    def checkpoint(self) -> dict[str, Any]:
        """What :meth:`save` writes (module doc)."""
        p = self.parts
        ck: dict[str, Any] = {"model": p.model.state_dict(), "optimizer": p.optimizer.state_dict()}
        if p.scheduler is not None:
            ck["scheduler"] = p.scheduler.state_dict()
        ck.update({name: module.state_dict() for name, module in p.extra.items()})
        ck.update(
            step=self.step, rng=p.rng.bit_generator.state, torch_rng=torch.get_rng_state(), best=self.best, best_step=self.best_step,
            curve=self.curve.rows, elapsed=self.elapsed, core_seconds=self.core_seconds, ranks=self.ranks.size,
        )  # fmt: skip
        if self.state is not None:
            ck.update(self.state())
        return ck

    def save(self) -> None:
        """Write the checkpoint atomically (rank 0)."""
        save_torch(self.checkpoint(), self.path)

    def wall(self) -> float:
        """Wall seconds of the run so far, earlier calls included."""
        return time.perf_counter() - self._t0

    # ------------------------------------------------------------------ the loop
    def run(
        self,
        train_step: Callable[[int], float],
        evaluate: Callable[[int, float | None], dict[str, Any]],
        *,
        on_best: Callable[[int], None] | None = None,
        before_save: Callable[[int, dict[str, Any]], None] | None = None,
        stop: Callable[[], bool] | None = None,
        evaluate_first: bool = False,
    ) -> None:
        """Train from :attr:`step` to ``steps`` (module doc). ``evaluate_first``:
        a new run (step 0) records the untrained model's row first (no checkpoint)."""
        from tqdm import tqdm

        ranks = self.ranks
        bar = tqdm(total=self.steps, initial=min(self.step, self.steps), desc=self.desc, unit="step", disable=not (self.progress and ranks.main))
        self._t0 = time.perf_counter() - self.elapsed
        self._cpu0 = time.process_time()
        saved_at = self.step
        try:
            if evaluate_first and self.step == 0 and ranks.main:
                self.curve.record(evaluate(0, math.nan))
            while self.step < self.steps:
                if stop is not None and ranks.any(stop()):  # every rank stops at the same step
                    break
                if self.parts.lr is not None:
                    lr = self.parts.lr(self.step)
                    for group in self.parts.optimizer.param_groups:
                        group["lr"] = lr
                loss = float(train_step(self.step))
                self.step += 1
                self.losses.append(loss)
                self._interval.append(loss)
                bar.update(1)
                if self.step % SHOW_EVERY == 0:
                    self._show(bar, loss=f"{np.mean(self.losses[-SHOW_EVERY:]):.4g}")
                if self.step % self.every == 0 or self.step == self.steps:
                    self._evaluate(bar, evaluate, on_best, before_save)
                    saved_at = self.step
            if saved_at != self.step:  # stopped early
                self._evaluate(bar, evaluate, on_best, before_save)
        finally:
            bar.close()

    def _evaluate(self, bar: Any, evaluate: Callable[..., dict[str, Any]], on_best: Any, before_save: Any) -> None:
        """Every rank: the ranks' mean loss and summed CPU seconds; rank 0: the row, the best, the checkpoint."""
        had = bool(self._interval)
        loss_sum, cpu = self.ranks.sum(float(np.mean(self._interval)) if had else 0.0, time.process_time() - self._cpu0)
        self.core_seconds += cpu
        self._cpu0 = time.process_time()
        self._interval = []
        self.elapsed = self.wall()
        if not self.ranks.main:
            return
        row = evaluate(self.step, loss_sum / self.ranks.size if had else None)
        self.elapsed = self.wall()
        self.curve.record(row)
        if self.score is not None and row[self.score] < self.best:
            self.best, self.best_step = float(row[self.score]), self.step
            if on_best is not None:
                on_best(self.step)
        if before_save is not None:
            before_save(self.step, row)
        self.save()
        if self.postfix is not None:
            self._show(bar, **self.postfix(row))

    def _show(self, bar: Any, **items: Any) -> None:
        self._shown.update(items)
        bar.set_postfix(self._shown)


__all__ = ["CHECKPOINT", "CONFIG_FILE", "Parts", "TrainingLoop", "load_checkpoint", "save_torch", "start_run"]
