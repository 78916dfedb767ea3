//! Grid mass: p2g of particle mass only, onto a given grid, normalised to sum 1.
//!
//! Building block of the accuracy metric (docs/design.md, "Grid-mass error"; paper
//! Sec. 3.1.1, `RMSE_m̃`): trajectories with different particle counts are
//! compared through their normalised grid-mass fields on one reference grid.

use crate::error::{MpmError, Result, check_budget, human_bytes};
use crate::kernel::quadratic_weights;

/// Bytes [`grid_mass`] allocates for `n` nodes per dimension in `D`
/// dimensions: an f64 accumulation grid and the f32 result, 12 bytes per
/// node (`None`: beyond `u128`). 2D `n = 4096` needs 192 MiB, 3D `n = 1024`
/// 12 GiB.
pub fn grid_mass_bytes(n: usize, d: usize) -> Option<u128> {
    (n as u128).checked_pow(d as u32)?.checked_mul(12)
}

/// [`grid_mass`] with no memory budget.
pub fn grid_mass<const D: usize>(
    positions: &[[f32; D]],
    masses: Option<&[f32]>,
    n: usize,
) -> Result<Vec<f32>> {
    grid_mass_with_budget(positions, masses, n, None)
}

/// Splat particle masses onto the node lattice `i·dx`, `i ∈ [0, n)^D`,
/// `dx = 1/n`, with quadratic B-spline weights, and normalise to sum 1.
///
/// * `positions`: `[N][D]` in the unit domain [m].
/// * `masses`: per-particle masses, or `None` for equal masses (1/N each).
/// * `n`: nodes per dimension (e.g. 128 in 2D, 64 in 3D).
///
/// Returns `n^D` values in row-major order (first coordinate slowest).
/// Stencil nodes outside `[0, n)` are clamped to the nearest edge node, so no
/// mass is lost. Errors: non-finite positions or masses, negative masses, a
/// zero total mass, `n` outside [3, 4096], and (field `n_grid`, before
/// anything is allocated) a grid of more than `memory_budget` bytes
/// ([`grid_mass_bytes`]; `None`: no budget).
pub fn grid_mass_with_budget<const D: usize>(
    positions: &[[f32; D]],
    masses: Option<&[f32]>,
    n: usize,
    memory_budget: Option<u64>,
) -> Result<Vec<f32>> {
    if !(3..=4096).contains(&n) {
        return Err(MpmError::invalid(
            "n_grid",
            format!("must be in [3, 4096], got {n}"),
        ));
    }
    check_budget(
        "n_grid",
        &format!("a {D}D grid-mass grid of {n}^{D} nodes"),
        grid_mass_bytes(n, D),
        memory_budget,
    )?;
    if let Some(m) = masses {
        if m.len() != positions.len() {
            return Err(MpmError::invalid(
                "masses",
                format!("length {} != particle count {}", m.len(), positions.len()),
            ));
        }
        if let Some(i) = m.iter().position(|x| !(x.is_finite() && *x >= 0.0)) {
            return Err(MpmError::invalid(
                "masses",
                format!("particle {i}: mass must be finite and >= 0, got {}", m[i]),
            ));
        }
    }
    if let Some(i) = positions
        .iter()
        .position(|p| !p.iter().all(|x| x.is_finite()))
    {
        return Err(MpmError::invalid(
            "positions",
            format!("particle {i} has a non-finite coordinate"),
        ));
    }
    let total = n.pow(D as u32);
    let oom = || {
        MpmError::invalid(
            "n_grid",
            format!(
                "cannot allocate a grid of {n}^{D} nodes ({}): out of memory",
                human_bytes(total as f64 * 12.0)
            ),
        )
    };
    let mut grid: Vec<f64> = Vec::new();
    grid.try_reserve_exact(total).map_err(|_| oom())?;
    grid.resize(total, 0.0);
    let inv_dx = n as f32;
    let k = 3usize.pow(D as u32);
    for (i, p) in positions.iter().enumerate() {
        let m = masses.map_or(1.0, |m| m[i] as f64);
        let mut base = [0i64; D];
        let mut w = [[0.0f64; 3]; D];
        for d in 0..D {
            let xg = p[d] * inv_dx;
            let b = (xg - 0.5).floor();
            let f = (xg - b) as f64;
            base[d] = b as i64;
            w[d] = quadratic_weights(f);
        }
        for s in 0..k {
            let mut rem = s;
            let mut weight = m;
            let mut lin = 0usize;
            for d in (0..D).rev() {
                let o = rem % 3;
                rem /= 3;
                weight *= w[d][o];
                let idx = (base[d] + o as i64).clamp(0, n as i64 - 1) as usize;
                lin += idx * n.pow((D - 1 - d) as u32);
            }
            grid[lin] += weight;
        }
    }
    let sum: f64 = grid.iter().sum();
    if !(sum > 0.0) {
        return Err(MpmError::invalid("masses", "total mass must be > 0"));
    }
    let mut out: Vec<f32> = Vec::new();
    out.try_reserve_exact(total).map_err(|_| oom())?;
    out.extend(grid.into_iter().map(|x| (x / sum) as f32));
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sums_to_one_and_centres_mass() {
        let pts: Vec<[f32; 2]> = (0..100).map(|i| [0.3 + 0.001 * i as f32, 0.6]).collect();
        let g = grid_mass(&pts, None, 64).unwrap();
        let s: f32 = g.iter().sum();
        assert!((s - 1.0).abs() < 1e-5);
        // first moment equals the particles' centre of mass (B-splines reproduce linear functions)
        let mut cx = 0.0f64;
        let mut cy = 0.0f64;
        for i in 0..64 {
            for j in 0..64 {
                cx += g[i * 64 + j] as f64 * i as f64 / 64.0;
                cy += g[i * 64 + j] as f64 * j as f64 / 64.0;
            }
        }
        let mx: f64 = pts.iter().map(|p| p[0] as f64).sum::<f64>() / 100.0;
        assert!(
            (cx - mx).abs() < 1e-5 && (cy - 0.6).abs() < 1e-5,
            "{cx} {cy}"
        );
    }

    #[test]
    fn rejects_bad_input() {
        assert!(grid_mass::<2>(&[[f32::NAN, 0.5]], None, 16).is_err());
        assert!(grid_mass::<2>(&[[0.5, 0.5]], Some(&[-1.0]), 16).is_err());
        assert!(grid_mass::<2>(&[[0.5, 0.5]], None, 2).is_err());
    }

    #[test]
    fn refuses_a_grid_beyond_the_budget_before_allocating() {
        // 3D n = 4096 would need 768 GiB: refused, naming n_grid and the size
        let e = grid_mass_with_budget::<3>(&[[0.5; 3]], None, 4096, Some(1 << 30)).unwrap_err();
        assert_eq!(e.field(), Some("n_grid"));
        let msg = e.to_string();
        assert!(
            msg.starts_with("n_grid: ") && msg.contains("768.0 GiB"),
            "{msg}"
        );
        assert!(msg.contains("824633720832 bytes"), "{msg}");
        // the same grid fits a larger budget and gives the same bits as no budget
        let pts = [[0.3f32, 0.6], [0.5, 0.51]];
        let b = grid_mass_bytes(64, 2).unwrap() as u64;
        assert_eq!(
            grid_mass_with_budget(&pts, None, 64, Some(b)).unwrap(),
            grid_mass(&pts, None, 64).unwrap()
        );
        assert!(grid_mass_with_budget(&pts, None, 64, Some(b - 1)).is_err());
    }
}
