#!/usr/bin/env python3
"""Peer benchmark: Taichi (CPU backend) running the same MLS-MPM scenes as
hybridmpm. The implementation lives in :mod:`hybridmpm.bench.taichi_peer`
(``hybridmpm bench SCENE --peer taichi`` uses it too); this script keeps the
command of ``benchmarks/results/taichi_peer.md`` working."""

import sys

from hybridmpm.bench.taichi_peer import main

if __name__ == "__main__":
    sys.exit(main())
