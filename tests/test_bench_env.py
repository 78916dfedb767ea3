"""The benchmark environment's CPU-steal meter against /proc/stat read independently."""

from __future__ import annotations

import sys

import pytest

from hybridmpm.bench.env import cpu_times, steal_fraction


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/stat is Linux's")
def test_cpu_times_are_the_aggregate_line_of_proc_stat() -> None:
    with open("/proc/stat") as f:
        head = f.readline().split()
    steal, total = cpu_times() or (None, None)
    assert head[0] == "cpu" and steal is not None and total is not None
    # the meter reads the same counters a moment later: never fewer, and steal is the 8th field
    assert int(head[8]) <= steal <= total
    assert total >= sum(int(v) for v in head[1:9])


def test_steal_fraction_is_the_share_of_the_interval() -> None:
    assert steal_fraction((10, 1000), (40, 1100)) == pytest.approx(0.3)
    assert steal_fraction((10, 1000), (10, 1000)) is None  # no time passed
    assert steal_fraction(None, (1, 2)) is None and steal_fraction((1, 2), None) is None
