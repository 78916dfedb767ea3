"""Digests of sessions stepped through the service, to show that a refactor
of the session layer moves no float.

For each scene and solver, one session of a fresh ``hybridmpm serve`` (the
local backend, or the ray backend on a two-node local cluster) is driven the
same way: 6 frames stepped, a 10-frame ``constant`` control of an arrow (not
for the network alone, which takes none), 4
frames stepped, its checkpoint taken and put back, 3 frames stepped, a reset (through its stream),
2 frames stepped, and its recent trajectory fetched. The digest is the
SHA-256 of every float the service answered (the steps' positions, the
control's trajectory, the arrays of the recent trajectory's file) and of the checkpoint's state
arrays (less its meta and its ``stats``, which hold wall-clock times).

Run it at two commits and compare the files' ``digests`` (``--compare``;
their ``provenance`` differs from run to run): equal digests mean the same
floats.

    python benchmarks/session_digests.py --backend local --out /tmp/digests-local.json
    python benchmarks/session_digests.py --backend ray --out /tmp/digests-ray.json
    python benchmarks/session_digests.py --backend local --out /tmp/new.json --compare benchmarks/results/session_digests/local.json
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import secrets
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from websockets.sync.client import connect

from hybridmpm.bench.harness import read_results, write_results
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.testing import LiveServer, RayCluster, step_binary

SCENES = ("water2d", "sand2d", "dam_break2d", "water3d")
SOLVERS = ("mpm", "neural", "hybrid")
SEED = 5
ARROW = {"kind": "arrow", "points": [[0.3, 0.3], [0.6, 0.4]]}
OCTET = {"Accept": "application/octet-stream"}
WAIT_S = 300.0


def feed(h: Any, tree: Any) -> None:
    """Hash a state tree: arrays by dtype, shape and bytes, mappings in key order, other values by ``repr``."""
    if isinstance(tree, dict):
        for k in sorted(tree, key=str):
            h.update(repr(k).encode())
            feed(h, tree[k])
    elif isinstance(tree, (list, tuple)):
        for x in tree:
            feed(h, x)
    elif isinstance(tree, np.ndarray) and tree.dtype != object:
        h.update(f"{tree.dtype.str}{tree.shape}".encode())
        h.update(np.ascontiguousarray(tree).tobytes())
    elif isinstance(tree, np.ndarray):
        feed(h, tree.tolist())
    else:
        h.update(repr(tree).encode())


def reset(ws_url: str, sid: str) -> None:
    """Reset the session through its stream (the page's ``reset`` message); returns once the ``reset`` event arrives."""
    with connect(f"{ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws:
        while not isinstance(ws.recv(timeout=WAIT_S), bytes):  # the stream is fed (Ray: its first poll is done, so no event is missed)
            pass
        ws.send('{"type": "reset"}')
        while True:
            m = ws.recv(timeout=WAIT_S)
            if isinstance(m, str) and json.loads(m).get("type") == "reset":
                return


def drive(c: httpx.Client, ws_url: str, scene: str, solver: str) -> str:
    """The digest of one session of ``scene`` and ``solver`` driven as the module doc says."""
    h = hashlib.sha256()
    r = c.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": SEED})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    try:
        h.update(step_binary(c, sid, 6).tobytes())
        if solver != "neural":  # the network alone takes no control
            r = c.post(f"/v1/sessions/{sid}/controls", json={"sketch": ARROW, "method": "constant", "frames": 10})
            assert r.status_code == 200, r.text
            t = c.get(r.json()["trajectory"], headers=OCTET)
            assert t.status_code == 200, t.text
            h.update(t.content)
        h.update(step_binary(c, sid, 4).tobytes())
        blob = c.get(f"/v1/sessions/{sid}/checkpoint")
        assert blob.status_code == 200, blob.text
        state, _ = ckpt.loads(blob.content, 1 << 30)
        state.pop("stats", None)  # wall-clock timings
        feed(h, state)
        r = c.put(f"/v1/sessions/{sid}/checkpoint", content=blob.content)
        assert r.status_code == 200, r.text
        h.update(step_binary(c, sid, 3).tobytes())
        reset(ws_url, sid)
        h.update(step_binary(c, sid, 2).tobytes())
        t = c.get(f"/v1/sessions/{sid}/trajectory", params={"frames": 20})
        assert t.status_code == 200, t.text
        with np.load(io.BytesIO(t.content)) as z:  # the arrays, not the zip (its entries carry the time of writing)
            for k in sorted(z.files):
                h.update(k.encode())
                h.update(np.ascontiguousarray(z[k]).tobytes())
    finally:
        c.delete(f"/v1/sessions/{sid}")
    return h.hexdigest()


def run(url: str, ws_url: str) -> dict[str, str]:
    out: dict[str, str] = {}
    with httpx.Client(base_url=url, timeout=WAIT_S) as c:
        for scene in SCENES:
            for solver in SOLVERS:
                out[f"{scene}/{solver}"] = drive(c, ws_url, scene, solver)
                print(f"{scene:12s} {solver:7s} {out[f'{scene}/{solver}'][:16]}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("local", "ray"), default="local")
    ap.add_argument("--out", type=Path, required=True, help="JSON file of the digests (FILE.json)")
    ap.add_argument("--compare", type=Path, default=None, help="a recorded digests file: exit status 1 unless every digest is equal")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="hmdig", dir="/tmp"))
    try:
        if args.backend == "local":
            with LiveServer(max_sessions=4, args=["--store", str(root / "store")]) as s:
                digests = run(s.url, s.ws_url)
        else:
            with RayCluster(root / "ray", secrets.token_hex(16), nodes=2, num_cpus=1, timeout=WAIT_S) as cl:
                env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cl.token}
                args_ = ["--backend", "ray", "--ray-address", cl.address, "--store", str(root / "store")]
                s = LiveServer(max_sessions=4, args=args_, env=env)
                try:
                    s.start(timeout=WAIT_S)
                    digests = run(s.url, s.ws_url)
                finally:
                    s.stop()
    finally:
        shutil.rmtree(root, ignore_errors=True)
    write_results(args.out.parent, args.out.stem, doc={"backend": args.backend, "seed": SEED, "digests": digests})
    if args.compare is not None:
        doc = read_results(args.compare)
        old = doc["digests"] if "digests" in doc else doc["after"]["digests"]  # a recorded before/after pair: its "after"
        differ = sorted(k for k in {*old, *digests} if old.get(k) != digests.get(k))
        print(f"{len(digests) - len(differ)} of {len({*old, *digests})} digests equal to {args.compare}" + (f"; differ: {', '.join(differ)}" if differ else ""))
        sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
