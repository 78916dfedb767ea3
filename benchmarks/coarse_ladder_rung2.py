"""Rung 2 of the coarse-grid ladder: the ceiling of a local closure that is handed the fine particles' history
(docs/correction.md, "Rung 2").

Each coarse particle of the half grid stands for the fine particles nearest to it at frame 0 (its children: 4 in
2D, 8 in 3D). Full-resolution MPM *projected* onto the coarse particles (:class:`Projection`) is their children's
mass-weighted mean position, velocity, APIC ``C`` and left stretch ``V`` of the elastic ``F = V R`` (a mean of
rotated ``F`` would shrink it; sand's stress depends on ``V`` alone).

On the fitting seeds the coarse solver is restarted from the projected reference every :data:`WINDOW` frames and
runs freely in between; on every :data:`ROW_STRIDE`-th frame a row is taken for a random :data:`ROW_SHARE` of the
coarse particles: the particle's features and two targets (cells per frame):

* ``tendency``: the error of its tendency, the projected reference's velocity change over the frame minus the
  coarse solver's (the drift a window builds up is not a target);
* ``nudge``: the velocity change that makes its velocity after the frame the projected reference's (the drift
  included, as in nudging a coarse run toward a coarse-grained reference).

Tiny closures are fitted on each target, on two feature sets:

* ``markov``: the local features of the coarse state (:func:`local_features`: velocity, ``C``, the left stretch
  ``V`` of ``F``, material, offset in the cell, the 3^D neighbouring cells' masses and relative velocity,
  walls; 58 in 2D);
* ``privileged``: the same plus the true sub-cell state read from the reference at that frame
  (:meth:`Projection.privileged`: the covariance of the particle's children's positions, in coarse spacings², and
  of their velocities, in (cells per frame)²; 6 in 2D);

each by ridge regression (scikit-learn ``RidgeCV``, inputs standardised; 2·(F + 1) weights) and by an MLP with one
hidden layer of :data:`MLP_HIDDEN` units (about 1k weights), read only inside the fitting rows' ranges
(:class:`Clipped`). The held-out seeds are rolled out from frame 0 with
each closure applied every frame as an acceleration (the privileged features read from the reference every frame),
through :func:`hybridmpm.sim.rollout`, and scored as every rung is: the share ``f`` of the plain half grid's excess
error over MPM at ``r_p`` removed, and the time per frame against MPM at ``r_p``'s (one run each; the closures'
features are numpy, so their time says what a numpy closure costs, not what one in Rust would). The ``floor`` row
is the projected reference itself (a coarse particle set that follows full resolution exactly).

Stop rule: if even the best privileged closure removes less than a quarter of the excess on sand2d, no local
closure can, and the ladder stops here.

Resumable: each fitting seed's rows, the fitted closures and each held-out seed's scores are kept under
``runs/coarse_ladder/rung2/SCENE/``; a rerun picks up where it stopped. Progress goes to stdout.

    python benchmarks/coarse_ladder_rung2.py sand2d
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np
from coarse_ladder import FIT_SEEDS, FRAMES, HELD_OUT, OUT, RUNS, WARMUP, half_grid, share
from experiments.learned_correction.features import particle_features
from experiments.learned_correction.forcing import cell_average
from scipy import sparse
from scipy.spatial import cKDTree

from hybridmpm.bench.harness import load_average, table, write_file, write_json, write_results
from hybridmpm.metrics import grid_mass_error
from hybridmpm.scenes import PAPER_R_P, make_scene
from hybridmpm.scenes.resolution import on_grid
from hybridmpm.sim import MpmSimulator, rollout

#: Frames between restarts from the projected reference on the fitting seeds.
WINDOW = 20
#: Rows are taken on every 2nd frame of the windows, for a quarter of the particles (drawn per frame).
ROW_STRIDE, ROW_SHARE = 2, 0.25
ALPHAS = (1e-2, 1.0, 1e2, 1e4)
#: Hidden units of the MLP closure: 16·(F + 1) + 17·D weights, ~1.1k in 2D with the privileged features.
MLP_HIDDEN = 16
TARGETS = ("tendency", "nudge")
FEATURES = ("markov", "privileged")
MODELS = ("ridge", "mlp")
#: The stop rule's threshold on the best privileged closure's f.
STOP_F = 0.25


class Projection:
    """A fine particle set seen through coarse particles: each coarse particle the mass-weighted mean of its children
    (the fine particles nearest to it at frame 0).

    ``fine_x0`` float [N, D] and ``fine_m`` [N] the fine particles' first positions [m] and masses; ``coarse_x0``
    float [M, D] the coarse particles' first positions; ``spacing`` [m] the coarse particles' spacing (the unit of the
    position covariance); ``vunit`` the factor from m/s to the velocity unit (cells per frame: ``dt_frame · n_grid``).
    ``group_mass`` [M]: each coarse particle's children's mass (0 for one without children)."""

    def __init__(self, fine_x0: np.ndarray, fine_m: np.ndarray, coarse_x0: np.ndarray, spacing: float, vunit: float) -> None:
        self.parent = cKDTree(np.asarray(coarse_x0, np.float64)).query(np.asarray(fine_x0, np.float64))[1]
        m, n = len(coarse_x0), len(self.parent)
        w = np.asarray(fine_m, np.float64)
        self.group_mass = np.bincount(self.parent, weights=w, minlength=m)
        self.P = sparse.csr_matrix((w / np.maximum(self.group_mass, 1e-300)[self.parent], (self.parent, np.arange(n))), shape=(m, n))
        self.spacing, self.vunit = float(spacing), float(vunit)

    def mean(self, values: np.ndarray) -> np.ndarray:
        """Mass-weighted mean of ``values`` [N, ...] over each coarse particle's children, float64 [M, ...] (0 where none)."""
        a = np.asarray(values, np.float64)
        return np.asarray(self.P @ a.reshape(len(a), -1)).reshape((self.P.shape[0], *a.shape[1:]))

    def privileged(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The sub-cell state of the fine positions ``x`` [m] and velocities ``v`` [m/s], float [N, D]: per coarse
        particle the mass-weighted covariance of its children's positions [spacing²] and of their velocities
        [(cells per frame)²], upper triangles (xx, xy, yy in 2D), float64 [M, D(D+1)]."""
        cols = []
        for a in (np.asarray(x, np.float64) / self.spacing, np.asarray(v, np.float64) * self.vunit):
            mu = self.mean(a)
            d = a.shape[1]
            for i in range(d):
                for j in range(i, d):
                    cols.append(self.mean(a[:, i] * a[:, j]) - mu[:, i] * mu[:, j])
        return np.stack(cols, axis=1)


def left_stretch(f: np.ndarray) -> np.ndarray:
    """The left stretch ``V = U Σ Uᵀ`` of each ``F = V R`` (its singular value decomposition ``U Σ Wᵀ``), float64 [N, D, D]."""
    u, sig, _ = np.linalg.svd(np.asarray(f, np.float64))
    return np.einsum("nij,nj,nkj->nik", u, sig, u)


def local_features(solver: Any, dt_frame: float) -> np.ndarray:
    """The Markov features of the coarse state, float32 [M, F]: ``particle_features`` with its ``F − I`` columns
    replaced by ``V − I`` (the left stretch, :func:`left_stretch`). The elastic ``F``'s rotation is no state of the
    material (the stress depends on ``V`` alone), and over a free rollout it wanders to half turns no window of the
    fitting rows reaches."""
    x = particle_features(solver, dt_frame)
    n, d = np.shape(solver.positions)
    x[:, d + d * d : d + 2 * d * d] = (left_stretch(solver.deformation_gradient) - np.eye(d)).reshape(n, d * d)
    return x


def coarse_sim(scene: str, seed: int) -> MpmSimulator:
    """The plain half grid of ``scene`` (2 particles per cell per axis), one thread."""
    return MpmSimulator(on_grid(make_scene(scene, seed=seed), half_grid(scene)), threads=1)


def fine_states(scene: str, seed: int, frames: int) -> dict[str, np.ndarray]:
    """Full-resolution MPM's particle state at every frame: ``x``, ``v`` float32 [T+1, N, D], ``C`` and the left
    stretch ``V`` of the elastic ``F`` float32 [T+1, N, D, D]; masses ``m`` float64 [N]."""
    sim = MpmSimulator(make_scene(scene, seed=seed), threads=1)
    s = sim.solver
    out: dict[str, list] = {"x": [], "v": [], "C": [], "F": []}

    def grab(_: Any = None) -> None:
        out["x"].append(np.array(s.positions, np.float32))
        out["v"].append(np.array(s.velocities, np.float32))
        out["C"].append(np.array(s.affine, np.float32))
        out["F"].append(left_stretch(s.deformation_gradient).astype(np.float32))

    grab()
    ro = rollout(sim, frames, on_frame=grab)
    if ro.failure:
        raise SystemExit(f"{scene} seed {seed} full resolution: {ro.failure_detail}")
    res = {k: np.stack(v) for k, v in out.items()}
    res["m"] = np.asarray(s.masses, np.float64)
    return res


def projection_for(sim: MpmSimulator, fine: dict[str, np.ndarray]) -> Projection:
    s = sim.solver
    return Projection(fine["x"][0], fine["m"], np.asarray(s.positions), 0.5 / s.n_grid, sim.dt_frame * s.n_grid)


def set_state(sim: MpmSimulator, proj: Projection, fine: dict[str, np.ndarray], t: int) -> None:
    """Restart the coarse solver from the projected reference at frame ``t`` (positions, velocities, ``C``, ``F``)."""
    s = sim.solver
    lo, hi = s.domain_bounds  # a group's mean can lie a hair outside the band the solver keeps particles in
    s.positions = np.clip(proj.mean(fine["x"][t]), lo + 1e-6, hi - 1e-6).astype(np.float32)
    s.velocities = proj.mean(fine["v"][t]).astype(np.float32)
    s.affine = proj.mean(fine["C"][t]).astype(np.float32)
    s.deformation_gradient = proj.mean(fine["F"][t]).astype(np.float32)


def fit_rows(scene: str, seed: int, frames: int) -> dict[str, np.ndarray]:
    """One fitting seed's rows: ``markov`` [R, F], ``privileged`` [R, D(D+1)] and the targets ``tendency``, ``nudge``
    [R, D] (cells per frame), float32. The frames are advanced by the simulator (no forcing); the state is reset from
    the projected reference at the start of every window."""
    rng = np.random.default_rng(seed)
    fine = fine_states(scene, seed, frames)
    sim = coarse_sim(scene, seed)
    s, dt = sim.solver, sim.dt_frame
    proj = projection_for(sim, fine)
    rows: dict[str, list] = {k: [] for k in ("markov", "privileged", *TARGETS)}
    for t in range(frames):
        if t % WINDOW == 0:
            set_state(sim, proj, fine, t)
        take = t % ROW_STRIDE == 0
        if take:
            feats = local_features(s, dt)
            priv = proj.privileged(fine["x"][t], fine["v"][t])
        v0 = np.asarray(s.velocities, np.float64).copy()
        sim.advance()
        if take:
            pick = rng.random(s.num_particles) < ROW_SHARE
            vc = np.asarray(s.velocities, np.float64)
            vr0, vr1 = proj.mean(fine["v"][t]), proj.mean(fine["v"][t + 1])
            rows["markov"].append(feats[pick])
            rows["privileged"].append(priv[pick])
            rows["tendency"].append(((vr1 - vr0) - (vc - v0))[pick] * proj.vunit)
            rows["nudge"].append((vr1 - vc)[pick] * proj.vunit)
    return {k: np.concatenate(v).astype(np.float32) for k, v in rows.items()}


def make_model(kind: str):  # noqa: ANN201 (a scikit-learn estimator)
    from sklearn.compose import TransformedTargetRegressor
    from sklearn.linear_model import RidgeCV
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if kind == "ridge":
        return make_pipeline(StandardScaler(), RidgeCV(alphas=ALPHAS))
    mlp = MLPRegressor(hidden_layer_sizes=(MLP_HIDDEN,), alpha=1e-4, batch_size=512, max_iter=40, early_stopping=True, n_iter_no_change=5, random_state=0)
    return TransformedTargetRegressor(make_pipeline(StandardScaler(), mlp), transformer=StandardScaler())


class Clipped:
    """A fitted closure read only inside what it was fitted on: its inputs clipped, per feature, to their range on
    the fitting rows, and its answer, per component, to the targets' range. A closure read far outside the states
    it saw does not kick the coarse state with an answer no fitting row asked for."""

    def __init__(self, model: Any, x: np.ndarray, y: np.ndarray) -> None:
        self.model, self.xlo, self.xhi, self.lo, self.hi = model, x.min(axis=0), x.max(axis=0), y.min(axis=0), y.max(axis=0)

    def predict(self, x: np.ndarray) -> np.ndarray:
        return np.clip(self.model.predict(np.clip(x, self.xlo, self.xhi)), self.lo, self.hi)

    def score(self, x: np.ndarray, y: np.ndarray) -> float:
        return float(self.model.score(x, y))


def inputs(rows: dict[str, np.ndarray], features: str) -> np.ndarray:
    return rows["markov"] if features == "markov" else np.concatenate([rows["markov"], rows["privileged"]], axis=1)


class ClosureForcing:
    """``sim.forcing``: before every frame, the closure's velocity change [cells per frame] over the frame as an
    acceleration [m/s²], from the coarse state's features (and the reference's sub-cell state at that frame when
    ``fine`` is given); with ``cell``, its mass-weighted mean over each coarse cell's particles (a field, without the
    per-particle scatter of the closure's error that disorders the coarse particles)."""

    def __init__(self, sim: MpmSimulator, model: Any, proj: Projection, fine: dict[str, np.ndarray] | None, cell: bool = False) -> None:
        self.sim, self.model, self.proj, self.fine, self.cell = sim, model, proj, fine, cell
        self.dt = float(sim.dt_frame)

    def __call__(self, frame: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        x = local_features(self.sim.solver, self.dt)
        if self.fine is not None:
            x = np.concatenate([x, self.proj.privileged(self.fine["x"][frame], self.fine["v"][frame])], axis=1)
        dv = np.asarray(self.model.predict(x), np.float64) / self.proj.vunit  # m/s over the frame
        if self.cell:
            s = self.sim.solver
            dv = cell_average(np.asarray(s.positions, np.float64), np.asarray(s.masses, np.float64), dv, s.n_grid)
        return (dv / self.dt).astype(np.float32)


#: The two error grids (rung 0's): the scene's (the bench's metric) and the half grid (every field deposited with the
#: kernel matched to the coarse particles' spacing: what is left when the splat of fewer particles is taken out).
METRICS = ("grid", "half")


def score(x: np.ndarray, ref: np.ndarray, n0: int, weights: np.ndarray | None = None) -> dict[str, float]:
    """Mean grid-mass error of ``x`` against ``ref`` on the scene's grid ``n0`` (``grid``) and on the half grid (``half``)."""
    return {m: float(grid_mass_error(x, ref, n, pred_weights=weights).mean()) for m, n in zip(METRICS, (n0, n0 // 2))}


def timed_rollout(sim: MpmSimulator, frames: int) -> tuple[np.ndarray, float, str | None]:
    """Fluid positions [frames + 1, M, D] (a rollout broken off keeps its last frame to the end), ms per frame after
    the warm-up, and the failure (None)."""
    ro = rollout(sim, frames)
    x = ro.fluid_positions
    if ro.failure:
        x = np.concatenate([x, np.repeat(x[-1:], frames + 1 - len(x), axis=0)])
    ms = float(ro.frame_seconds(after=WARMUP).mean() * 1e3) if ro.frames_done > WARMUP else float("nan")
    return x, ms, ro.failure


def held_out_seed(scene: str, seed: int, frames: int, models: dict[str, Any]) -> dict:
    """Errors, ms per frame and failures of MPM at r_p, the plain half grid, every closure, the floor and the fine
    subset (one child of each coarse particle: full resolution's own dynamics carried by as many particles as the
    half grid's) on one seed."""
    base = make_scene(scene, seed=seed)
    n0 = base.params.resolved_n_grid()
    fine = fine_states(scene, seed, frames)
    ref = fine["x"]  # full-resolution MPM, one thread: the reference
    sim = coarse_sim(scene, seed)
    proj = projection_for(sim, fine)
    err, ms, failed = {}, {}, {}
    x, ms["rp"], failed["rp"] = timed_rollout(MpmSimulator(base, r_p=PAPER_R_P, seed=seed, threads=1), frames)
    err["rp"] = score(x, ref, n0)
    x, ms["plain"], failed["plain"] = timed_rollout(sim, frames)
    err["plain"] = score(x, ref, n0)
    for name, model in models.items():
        for key, cell in ((name, False), (f"{name}_cell", True)):
            sim = coarse_sim(scene, seed)
            sim.forcing = ClosureForcing(sim, model, proj, fine if key.startswith("privileged") else None, cell)
            x, ms[key], failed[key] = timed_rollout(sim, frames)
            err[key] = score(x, ref, n0)
    floor = np.stack([proj.mean(fine["x"][t]) for t in range(frames + 1)])
    has = proj.group_mass > 0
    err["floor"] = score(floor[:, has], ref, n0, proj.group_mass[has])
    one = np.unique(proj.parent, return_index=True)[1]  # the first child of each coarse particle that has children
    err["fine_subset"] = score(ref[:, one], ref, n0, fine["m"][one])
    return {"seed": seed, "error": err, "ms": ms, "failed": {k: v for k, v in failed.items() if v}, "load": list(load_average())}


def load_or(path: Path, make: Any, what: str) -> Any:
    """``make()``, pickled at ``path`` (a rerun loads it)."""
    if path.is_file():
        return pickle.loads(path.read_bytes())
    t0 = time.time()
    value = make()
    write_file(path, pickle.dumps(value))
    print(f"{what}: {time.time() - t0:.0f} s", flush=True)
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", default="sand2d")
    ap.add_argument("--frames", type=int, default=FRAMES)
    ap.add_argument("--fit-seeds", type=int, nargs="+", default=list(FIT_SEEDS))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(HELD_OUT))
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--runs", type=Path, default=RUNS / "rung2", help="the resumable state (rows, closures, per-seed scores)")
    a = ap.parse_args()
    state = a.runs / f"{a.scene}_{a.frames}"
    rows = [load_or(state / f"rows_{sd}.pkl", lambda sd=sd: fit_rows(a.scene, sd, a.frames), f"rows of seed {sd}") for sd in a.fit_seeds]
    data = {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}
    n_rows = len(data["nudge"])

    def fit_all() -> dict[str, Any]:
        out = {}
        for target in TARGETS:
            for feats in FEATURES:
                for kind in MODELS:
                    t0 = time.time()
                    x = inputs(data, feats)
                    out[f"{feats}_{kind}_{target}"] = Clipped(make_model(kind).fit(x, data[target]), x, data[target])
                    print(f"fitted {feats}_{kind}_{target} on {n_rows} rows: {time.time() - t0:.0f} s", flush=True)
        return out

    models = load_or(state / "closures.pkl", fit_all, "closures")
    r2 = {k: float(m.score(inputs(data, k.split("_")[0]), data[k.split("_")[-1]])) for k, m in models.items()}
    per_seed = []
    for sd in a.seeds:
        path = state / f"held_out_{sd}.json"
        if not path.is_file():
            t0 = time.time()
            write_json(path, held_out_seed(a.scene, sd, a.frames, models))
            print(f"held-out seed {sd}: {time.time() - t0:.0f} s", flush=True)
        per_seed.append(json.loads(path.read_text()))
        print(json.dumps(per_seed[-1]["error"]), flush=True)
    closures = [k for name in models for k in (name, f"{name}_cell")]
    keys = [*closures, "floor", "fine_subset"]
    mean = {m: {k: float(np.mean([r["error"][k][m] for r in per_seed])) for k in ["rp", "plain", *keys]} for m in METRICS}
    summary: dict[str, dict] = {}
    for k in keys:
        t_ratio = [r["ms"][k] / r["ms"]["rp"] for r in per_seed] if k in per_seed[0]["ms"] else [float("nan")]
        summary[k] = {
            "time_ratio": [float(np.min(t_ratio)), float(np.median(t_ratio)), float(np.max(t_ratio))],
            "failed_seeds": [r["seed"] for r in per_seed if k in r.get("failed", {})],
        }
        for m in METRICS:
            f_seeds = [share(r["error"]["plain"][m], r["error"]["rp"][m], r["error"][k][m]) for r in per_seed]
            summary[k][m] = {
                "error": mean[m][k],
                "f": share(mean[m]["plain"], mean[m]["rp"], mean[m][k]),
                "f_seeds": [float(np.min(f_seeds)), float(np.median(f_seeds)), float(np.max(f_seeds))],
            }
    plain_t = [r["ms"]["plain"] / r["ms"]["rp"] for r in per_seed]
    best = max((k for k in closures if k.startswith("privileged")), key=lambda k: summary[k]["grid"]["f"])
    fb, ff = summary[best]["grid"]["f"], summary["floor"]["grid"]["f"]
    stop = fb < STOP_F
    verdict = (
        f"stop: the best privileged closure ({best}) removes f = {fb:+.2f} < {STOP_F} of the excess (the floor: {ff:+.2f}); no local closure can"
        if stop
        else f"go on: the best privileged closure ({best}) removes f = {fb:+.2f} >= {STOP_F}; rung 3 must reach it without privilege"
    )
    doc = {
        "scene": a.scene,
        "frames": a.frames,
        "fit_seeds": a.fit_seeds,
        "held_out": a.seeds,
        "window": WINDOW,
        "row_stride": ROW_STRIDE,
        "row_share": ROW_SHARE,
        "rows_fitted": n_rows,
        "r2_fit_rows": r2,
        "weights": {k: weights(m) for k, m in models.items()},
        "rows": per_seed,
        "mean": mean,
        "summary": summary,
        "plain_time_ratio": [float(np.min(plain_t)), float(np.median(plain_t)), float(np.max(plain_t))],
        "best_privileged": best,
        "stop": stop,
        "verdict": verdict,
    }
    write_results(a.out, f"rung2_{a.scene}", doc=doc, markdown=markdown(doc))
    print((a.out / f"rung2_{a.scene}.md").read_text())


def weights(model: Any) -> int:
    """The closure's trainable weights (coefficients and intercepts)."""
    model = model.model
    est = model.regressor_[-1] if hasattr(model, "regressor_") else model[-1]
    if hasattr(est, "coefs_"):
        return int(sum(c.size for c in est.coefs_) + sum(b.size for b in est.intercepts_))
    return int(est.coef_.size + np.size(est.intercept_))


def markdown(doc: dict) -> str:
    s, m = doc["summary"], doc["mean"]
    g, h = m["grid"], m["half"]

    def rng(v: list[float]) -> str:
        return f"{v[1]:+.2f} ({v[0]:+.2f} to {v[2]:+.2f})"

    def t(v: list[float]) -> str:
        return "" if np.isnan(v[1]) else f"{v[1]:.2f} ({v[0]:.2f} to {v[2]:.2f})"

    rows = [
        ["MPM at r_p", "", f"{g['rp']:.3f}", "1", "", f"{h['rp']:.3f}", "1", "", "1", ""],
        ["plain half grid", "", f"{g['plain']:.3f}", "0", "", f"{h['plain']:.3f}", "0", "", t(doc["plain_time_ratio"]), ""],
    ]
    for k, v in s.items():
        w = doc["weights"].get(k.removesuffix("_cell"), "")
        failed = ", ".join(map(str, v["failed_seeds"])) or ""
        vg, vh = v["grid"], v["half"]
        label = {"floor": "floor (the projected reference)", "fine_subset": "fine subset (one child per coarse particle)"}.get(k, k.replace("_", ", "))
        label = label.replace(", cell", ", cell mean")
        rows.append([label, str(w), f"{vg['error']:.3f}", f"{vg['f']:+.2f}", rng(vg["f_seeds"]), f"{vh['error']:.3f}", f"{vh['f']:+.2f}", rng(vh["f_seeds"]),
                     t(v["time_ratio"]), failed])  # fmt: skip
    lines = [
        f"# Rung 2 on {doc['scene']}: a local closure with privileged history",
        "",
        f"Fitting seeds {doc['fit_seeds'][0]}-{doc['fit_seeds'][-1]} ({doc['rows_fitted']} rows: windows of {doc['window']} frames restarted from "
        f"the projected reference, every {doc['row_stride']}nd frame, {doc['row_share']:.0%} of the particles), held-out seeds "
        f"{doc['held_out'][0]}-{doc['held_out'][-1]}, {doc['frames']} frames. Error: mean grid-mass error against full-resolution MPM "
        "on the scene's grid (`grid`, the bench's) and deposited on the half grid (`half`), mean over the held-out seeds; "
        "f = (plain - row) / (plain - MPM at r_p) of the means; per seed: median (min to max); "
        "time: ms per frame / MPM at r_p's, per seed median (min to max), one run each (the closures' features in numpy).",
        "",
        *table(
            [
                "row (features, closure, target)",
                "weights",
                "error (grid)",
                "f (grid)",
                "f per seed (grid)",
                "error (half)",
                "f (half)",
                "f per seed (half)",
                "time / r_p's",
                "rollouts broken off (seeds)",
            ],
            rows,
        ),  # fmt: skip
        "",
        "R² on the fitting rows: " + ", ".join(f"{k} {v:.3f}" for k, v in doc["r2_fit_rows"].items()) + ".",
        "",
        f"**Verdict**: {doc['verdict']}.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
