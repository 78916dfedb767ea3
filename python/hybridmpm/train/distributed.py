"""Data-parallel training on several processes: torch's DistributedDataParallel
over gloo (CPU), for every trainer of :mod:`hybridmpm.train` (``hybridmpm
train``, ``train-control``, ``train-grid``; docs/neural.md, "Training on
several processes").

:func:`launch` runs a trainer's rank function ``fn(ranks, *args)``:

* ``nproc`` = 1 and no torchrun environment: in this process, as the one rank
  (:data:`SINGLE`); nothing distributed is set up, so a one-process run is
  the run it always was;
* ``nproc`` = N > 1: on N local processes (``torch.multiprocessing`` with the
  forkserver start method, whose server imports torch once, so a launch does
  not pay N imports), joined in a gloo group over a ``TCPStore`` that this
  process holds on loopback (port chosen by the system: no race for a free
  port); the ranks' ``InvalidInputError`` (any ``HybridMpmError``) is raised
  here as it was raised there, and rank 0's return value is returned;
* under ``torchrun`` (every one of :data:`TORCHRUN_VARIABLES` set): this
  process is one rank of torchrun's group (``env://`` rendezvous), on one
  machine or several; ``nproc`` must then stay 1 (torchrun's
  ``--nproc-per-node`` says how many). An environment with only some of the
  variables is refused, naming the first missing one.

Each rank gets ``cores // local ranks`` torch threads (at least 1) unless the
trainer sets its own (``--threads`` is per rank).

The semantics the trainers keep (what makes N ranks of batch b train the
weights of one process of batch N·b, to float rounding): every rank draws the
same global batch of N·b samples from the same random stream as the one
process would (noise included), and takes its own slice
(:meth:`Ranks.part`); its loss is its slice's share of the global batch's
loss, so DDP's gradient average is the global batch's gradient; clipping,
learning rate and the optimiser step follow the all-reduce, identically on
every rank. Rank 0 alone validates and writes checkpoints, logs and exports;
it loads a checkpoint and sends it to the others (:meth:`Ranks.broadcast`),
so a run resumes on machines that do not share its directory.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import socket
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import torch
import torch.distributed as dist
import torch.multiprocessing as torch_mp

from hybridmpm.errors import HybridMpmError, InvalidInputError

T = TypeVar("T")

#: The variables torchrun sets for each process; all of them, or none, must be present.
TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
#: The local rendezvous address.
LOOPBACK = "127.0.0.1"
#: What the forkserver imports before it forks the ranks (``torch._dynamo``: DDP's constructor imports it, seconds).
_PRELOAD = ["torch", "torch.distributed", "torch._dynamo", "hybridmpm.train.distributed"]


def cores() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def max_local_processes() -> int:
    """The most local ranks ``nproc`` may ask for: 4 per core, and at least 8."""
    return max(8, 4 * cores())


def check_nproc(nproc: Any, field: str = "nproc") -> int:
    """``nproc`` if it is an integer in [1, :func:`max_local_processes`], else :class:`InvalidInputError` naming ``field``."""
    top = max_local_processes()
    if isinstance(nproc, bool) or not isinstance(nproc, int) or not 1 <= nproc <= top:
        raise InvalidInputError(
            f"{field}: must be an integer in [1, {top}] (local processes, at most 4 per core of this machine; more machines: torchrun), got {nproc!r}",
            field,
        )
    return nproc


@dataclass(frozen=True)
class Ranks:
    """This process's place in the group: ``rank`` of ``size`` ranks, ``local_size`` of them on this machine."""

    rank: int = 0
    size: int = 1
    local_size: int = 1

    @property
    def main(self) -> bool:
        """Whether this is rank 0 (the one that validates, logs, checkpoints and exports)."""
        return self.rank == 0

    def part(self, per_rank: int) -> range:
        """This rank's slice of a global batch of ``size · per_rank`` samples."""
        return range(self.rank * per_rank, (self.rank + 1) * per_rank)

    def wrap(self, module: torch.nn.Module, unused: bool = False) -> torch.nn.Module:
        """``module`` in DistributedDataParallel (rank 0's parameters sent to
        every rank, gradients averaged over the ranks in ``backward``) when
        there are several ranks, else itself. ``unused``: some parameters
        take no part in the loss (DDP then looks for them every step and
        leaves their gradient unset, as a single process does)."""
        if self.size == 1:
            return module
        return torch.nn.parallel.DistributedDataParallel(module, find_unused_parameters=unused)

    def sum(self, *values: float) -> list[float]:
        """The sums over the ranks of ``values`` (float64; every rank must call it at the same point)."""
        if self.size == 1:
            return [float(v) for v in values]
        t = torch.tensor(values, dtype=torch.float64)
        dist.all_reduce(t)
        return [float(v) for v in t]

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` holds on any rank (every rank must call it at the same point)."""
        return self.sum(1.0 if flag else 0.0)[0] > 0

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` on every rank (pickled; every rank must call it at the same point)."""
        if self.size == 1:
            return obj
        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]  # type: ignore[no-any-return]

    def barrier(self) -> None:
        if self.size > 1:
            dist.barrier()


#: The rank of a one-process run.
SINGLE = Ranks()


class LossOf(torch.nn.Module):
    """``fn(net, *args)`` as a module's ``forward``: what DistributedDataParallel
    wraps when the loss calls the network's methods rather than its ``forward``
    (DDP prepares the gradient all-reduce in its own ``forward``)."""

    def __init__(self, net: torch.nn.Module, fn: Callable[..., torch.Tensor]) -> None:
        super().__init__()
        self.net = net
        self.fn = fn

    def forward(self, *args: Any) -> torch.Tensor:
        return self.fn(self.net, *args)


def _int_variable(name: str, low: int, high: int | None = None) -> int:
    value = os.environ[name]
    try:
        v = int(value)
    except ValueError:
        v = low - 1
    if v < low or (high is not None and v > high):
        span = f"[{low}, {high}]" if high is not None else f">= {low}"
        raise InvalidInputError(f"{name}: the torchrun variable must be an integer {span}, got {value!r}", name)
    return v


def torchrun_ranks() -> Ranks | None:
    """This process's :class:`Ranks` under torchrun (every one of
    :data:`TORCHRUN_VARIABLES` set), or None when none of them is set.
    Raises :class:`InvalidInputError` naming the first missing variable when
    only some are set, or a variable whose value is malformed."""
    present = [v for v in TORCHRUN_VARIABLES if os.environ.get(v)]
    if not present:
        return None
    missing = [v for v in TORCHRUN_VARIABLES if v not in present]
    if missing:
        raise InvalidInputError(
            f"{missing[0]}: the torchrun environment is incomplete ({', '.join(present)} set; {', '.join(missing)} not): "
            f"run under torchrun, or unset {', '.join(present)} to train with --nproc",
            missing[0],
        )
    size = _int_variable("WORLD_SIZE", 1)
    rank = _int_variable("RANK", 0, size - 1)
    _int_variable("LOCAL_RANK", 0, size - 1)
    _int_variable("MASTER_PORT", 1, 65535)
    local = _int_variable("LOCAL_WORLD_SIZE", 1, size) if os.environ.get("LOCAL_WORLD_SIZE") else size
    return Ranks(rank, size, local)


def is_main_process() -> bool:
    """Whether this process is rank 0 of a torchrun group, or not under torchrun (for what only one process should print)."""
    return os.environ.get("RANK", "0") in ("", "0")


def _set_threads(ranks: Ranks) -> None:
    torch.set_num_threads(max(1, cores() // ranks.local_size))


def launch(fn: Callable[..., T], nproc: int, *args: Any) -> T:
    """Run ``fn(ranks, *args)`` on ``nproc`` local ranks, or as this process's
    rank under torchrun (module doc); returns rank 0's result (under torchrun,
    this rank's). Raises :class:`InvalidInputError` naming ``nproc`` for a bad
    count, or a torchrun variable for a half-present torchrun environment;
    a rank's :class:`HybridMpmError` is raised as it is."""
    env = torchrun_ranks()
    if env is not None:
        if nproc != 1:
            raise InvalidInputError(
                f"nproc: under torchrun the ranks are torchrun's (WORLD_SIZE = {env.size}); leave --nproc at 1 and set --nproc-per-node", "nproc"
            )
        if env.size == 1:
            return fn(SINGLE, *args)
        dist.init_process_group("gloo", init_method="env://", rank=env.rank, world_size=env.size)
        try:
            _set_threads(env)
            return fn(env, *args)
        finally:
            dist.destroy_process_group()
    nproc = check_nproc(nproc)
    if nproc == 1:
        return fn(SINGLE, *args)
    return _spawn(fn, nproc, args)


def _spawn(fn: Callable[..., T], nproc: int, args: tuple[Any, ...]) -> T:
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    if method == "forkserver":  # takes effect when this process first starts the server
        multiprocessing.set_forkserver_preload([*_PRELOAD, fn.__module__])
    store = dist.TCPStore(LOOPBACK, 0, nproc, is_master=True, wait_for_workers=False)
    with tempfile.TemporaryDirectory(prefix="hybridmpm-ranks-") as box, _main_not_rerun(fn):
        try:
            torch_mp.start_processes(_rank_main, args=(fn, args, nproc, store.port, box), nprocs=nproc, start_method=method)
        except (torch_mp.ProcessRaisedException, torch_mp.ProcessExitedException) as e:
            for r in range(nproc):
                kind, value = _read(Path(box) / f"rank_{r}.pkl")
                if kind == "error":
                    raise value from None
            raise HybridMpmError(f"nproc: rank {e.error_index} of {nproc} failed: {e}") from None
        kind, value = _read(Path(box) / "rank_0.pkl")
        if kind != "result":
            raise HybridMpmError("nproc: rank 0 ended without a result")
        return value  # type: ignore[no-any-return]


@contextlib.contextmanager
def _main_not_rerun(fn: Callable[..., Any]) -> Iterator[None]:
    """Hide ``__main__``'s file from multiprocessing while the ranks start when
    it is no file (a script read from stdin, ``<stdin>``) and ``fn`` does not
    live there: the ranks would try to run it again, and fail."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    hide = path is not None and fn.__module__ != "__main__" and not os.path.isfile(path) and getattr(main, "__spec__", None) is None
    if hide:
        del main.__file__  # type: ignore[union-attr]
    try:
        yield
    finally:
        if hide:
            main.__file__ = path  # type: ignore[union-attr]


def _read(path: Path) -> tuple[str | None, Any]:
    try:
        with open(path, "rb") as f:
            return pickle.load(f)  # type: ignore[no-any-return]
    except (OSError, EOFError, pickle.UnpicklingError):
        return None, None


def _write(path: Path, kind: str, value: Any) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump((kind, value), f)
    os.replace(tmp, path)


def _rank_main(rank: int, fn: Callable[..., Any], args: tuple[Any, ...], size: int, port: int, box: str) -> None:
    """A local rank (started by :func:`_spawn`): join the group over the
    parent's store, run ``fn``, leave rank 0's result (or any rank's
    :class:`HybridMpmError`) in ``box`` for the parent."""
    if "GLOO_SOCKET_IFNAME" not in os.environ and "lo" in {name for _, name in _interfaces()}:
        os.environ["GLOO_SOCKET_IFNAME"] = "lo"  # every rank is on this machine: loopback, whatever the host name resolves to
    store = dist.TCPStore(LOOPBACK, port, size, is_master=False)
    dist.init_process_group("gloo", store=store, rank=rank, world_size=size)
    ranks = Ranks(rank, size, size)
    try:
        _set_threads(ranks)
        result = fn(ranks, *args)
        if ranks.main:
            _write(Path(box) / f"rank_{rank}.pkl", "result", result)
    except HybridMpmError as e:
        _write(Path(box) / f"rank_{rank}.pkl", "error", e)
        raise
    finally:
        dist.destroy_process_group()


def _interfaces() -> list[tuple[int, str]]:
    try:
        return socket.if_nameindex()
    except (OSError, AttributeError):
        return []


__all__ = [
    "LOOPBACK",
    "SINGLE",
    "TORCHRUN_VARIABLES",
    "LossOf",
    "Ranks",
    "check_nproc",
    "cores",
    "is_main_process",
    "launch",
    "max_local_processes",
    "torchrun_ranks",
]
