"""Rewrite shipped (or any) GNS .onnx files of an earlier layout as the current
one (``hybridmpm.train.gns.export.upgrade_onnx``): files exported by torch's
exporter as the compiled inference graph of the same weights, files
of the ``compiled-1`` layout with the sum over receivers that is exact on any
number of onnxruntime threads, files of it or of ``compiled-2`` with each
LayerNorm's variance as one column (see ``hybridmpm.train.gns.onnx_graph``). Files of
the current layout are left alone.

    python benchmarks/upgrade_models.py python/hybridmpm/models/*.onnx python/hybridmpm/models/variants/*/*.onnx
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hybridmpm.train.gns.export import upgrade_onnx


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="+", type=Path)
    args = ap.parse_args()
    for f in args.files:
        print(f"{f}: {'rewritten' if upgrade_onnx(f) else 'already current'}")


if __name__ == "__main__":
    main()
