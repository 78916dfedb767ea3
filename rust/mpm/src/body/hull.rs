//! A convex body in 3D ([`Hull`]): the convex hull of a mesh's points (by
//! parry, rapier's geometry), centred on its centre of mass, with its face
//! planes (what the coupling's signed distance reads) and its mass
//! properties per unit density.
//!
//! The signed distance is the largest of the face planes' distances: exact
//! inside (the nearest face of a convex body is the nearest plane), a lower
//! bound outside near an edge or a corner (the plane of one of the faces
//! that meet there, not the distance to the edge): within the coupling's
//! reach of a cell, the nodes beside an edge are held by the face whose
//! plane they are farthest outside of.

use rapier3d::parry::math::Vector;
use rapier3d::parry::transformation::try_convex_hull;

use crate::error::{MpmError, Result};

/// Most points a hull is built from (a mesh's vertices, or inline).
pub const MAX_HULL_POINTS: usize = 100_000;

/// A convex polyhedron in the body's frame (centre of mass at 0).
#[derive(Clone, Debug, PartialEq)]
pub struct Hull {
    /// The hull's vertices [m], body frame.
    pub vertices: Vec<[f32; 3]>,
    /// The same vertices as given, in the frame of the points the hull was
    /// built from (a subset of them: the hull of these is this hull).
    pub source: Vec<[f32; 3]>,
    /// Its triangles (indices into `vertices`), counter-clockwise seen from
    /// outside.
    pub faces: Vec<[u32; 3]>,
    /// Distinct face planes: outward unit normal and offset `d` [m]
    /// (`n·x = d` on the plane, `n·x < d` inside).
    pub planes: Vec<([f32; 3], f32)>,
    /// Where the centre of mass lies in the frame of the points it was built
    /// from [m].
    pub offset: [f32; 3],
    /// Volume [m³].
    pub volume: f32,
    /// Inertia tensor per unit density about the centre of mass, body axes
    /// [m⁵].
    pub unit_inertia: [[f64; 3]; 3],
    /// Largest distance of a vertex from the centre of mass [m].
    pub radius: f32,
    /// Half its thinnest width across a face plane [m].
    pub thinnest_half: f32,
    /// The parameter its points came from (`path` or `vertices`): what an
    /// error about its size names.
    pub key: &'static str,
}

/// Volume, centre of mass and inertia tensor per unit density about the
/// centre of mass of a closed triangle mesh with outward faces, in `f64`
/// (sums over the tetrahedra from the origin to each face).
pub fn mass_properties(
    vertices: &[[f64; 3]],
    faces: &[[u32; 3]],
) -> (f64, [f64; 3], [[f64; 3]; 3]) {
    let mut vol = 0.0;
    let mut first = [0.0; 3];
    // Σ ∫ x xᵀ over the tetrahedra (the covariance about the origin)
    let mut cov = [[0.0; 3]; 3];
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let det = a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]);
        vol += det / 6.0;
        let s: [f64; 3] = std::array::from_fn(|k| a[k] + b[k] + c[k]);
        for k in 0..3 {
            first[k] += det / 24.0 * s[k];
        }
        for i in 0..3 {
            for j in 0..3 {
                cov[i][j] += det / 120.0 * (a[i] * a[j] + b[i] * b[j] + c[i] * c[j] + s[i] * s[j]);
            }
        }
    }
    let com = first.map(|x| x / vol);
    for i in 0..3 {
        for j in 0..3 {
            cov[i][j] -= vol * com[i] * com[j];
        }
    }
    let tr = cov[0][0] + cov[1][1] + cov[2][2];
    let inertia = std::array::from_fn(|i| {
        std::array::from_fn(|j| if i == j { tr - cov[i][j] } else { -cov[i][j] })
    });
    (vol, com, inertia)
}

impl Hull {
    /// The convex hull of `points` [m] (a non-convex set is taken as its
    /// hull), moved so that its centre of mass is at 0; they came from
    /// parameter `key` (`path` or `vertices`). Errors name `field.key`: fewer than 4 points, a non-finite coordinate, more than
    /// [`MAX_HULL_POINTS`], or points that span no volume (all on one plane).
    pub fn new(points: &[[f32; 3]], field: &str, key: &'static str) -> Result<Hull> {
        let bad = |msg: String| MpmError::invalid(format!("{field}.{key}"), msg);
        if points.len() < 4 {
            return Err(bad(format!(
                "a convex body needs at least 4 points not on one plane, got {}",
                points.len()
            )));
        }
        if points.len() > MAX_HULL_POINTS {
            return Err(bad(format!(
                "{} points, more than the {MAX_HULL_POINTS} a hull takes",
                points.len()
            )));
        }
        if let Some(i) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
            return Err(bad(format!("point {i} is not finite: {:?}", points[i])));
        }
        let pts: Vec<Vector> = points.iter().map(|p| Vector::from_array(*p)).collect();
        let (verts, mut faces) = try_convex_hull(&pts)
            .map_err(|e| bad(format!("no convex hull of its points: {e:?}")))?;
        let v64: Vec<[f64; 3]> = verts
            .iter()
            .map(|p| p.to_array().map(|x| x as f64))
            .collect();
        let (lo, hi) = bounds(&v64);
        let diag = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
        let (mut vol, _, _) = mass_properties(&v64, &faces);
        if vol < 0.0 {
            for f in &mut faces {
                f.swap(1, 2);
            }
            vol = -vol;
        }
        if faces.len() < 4 || !(vol > 1e-9 * diag.powi(3)) {
            return Err(bad(
                "its points lie on one plane (or on a line): a convex body needs volume"
                    .to_string(),
            ));
        }
        let (_, com, _) = mass_properties(&v64, &faces);
        let offset = com.map(|x| x as f32);
        let vertices: Vec<[f32; 3]> = verts
            .iter()
            .map(|p| std::array::from_fn(|k| p[k] - offset[k]))
            .collect();
        let local: Vec<[f64; 3]> = vertices.iter().map(|p| p.map(|x| x as f64)).collect();
        let (volume, _, unit_inertia) = mass_properties(&local, &faces);
        let planes = planes(&local, &faces, 1e-6 * diag);
        let radius = local
            .iter()
            .map(|p| p.iter().map(|x| x * x).sum::<f64>().sqrt())
            .fold(0.0, f64::max) as f32;
        let thinnest_half = planes
            .iter()
            .map(|(n, _)| {
                let along = local
                    .iter()
                    .map(|p| (0..3).map(|k| n[k] as f64 * p[k]).sum::<f64>());
                let (a, b) = along.fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)));
                0.5 * (b - a)
            })
            .fold(f64::MAX, f64::min) as f32;
        Ok(Hull {
            vertices,
            source: verts.iter().map(|p| p.to_array()).collect(),
            faces,
            planes,
            offset,
            volume: volume as f32,
            unit_inertia,
            radius,
            thinnest_half,
            key,
        })
    }

    /// Signed distance [m] of `q` (body frame) to the surface: the largest
    /// of the face planes' (exact inside, a lower bound outside), and the
    /// outward normal of that plane (body frame).
    #[inline]
    pub fn sdf_normal(&self, q: [f32; 3]) -> (f32, [f32; 3]) {
        let mut best = (f32::NEG_INFINITY, [1.0, 0.0, 0.0]);
        for (n, d) in &self.planes {
            let s = n[0] * q[0] + n[1] * q[1] + n[2] * q[2] - d;
            if s > best.0 {
                best = (s, *n);
            }
        }
        best
    }

    /// The lowest and highest coordinate of the hull's vertices along world
    /// axis `d` when the body is rotated by `r` (columns: its axes), about
    /// its centre of mass [m].
    pub fn span(&self, r: impl Fn(usize, usize) -> f32, d: usize) -> (f32, f32) {
        self.vertices
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), p| {
                let x = r(d, 0) * p[0] + r(d, 1) * p[1] + r(d, 2) * p[2];
                (a.min(x), b.max(x))
            })
    }
}

fn bounds(v: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    v.iter()
        .fold(([f64::MAX; 3], [f64::MIN; 3]), |(lo, hi), p| {
            (
                std::array::from_fn(|k| lo[k].min(p[k])),
                std::array::from_fn(|k| hi[k].max(p[k])),
            )
        })
}

/// The distinct planes of the faces (coplanar triangles give one plane:
/// offsets within `tol` [m]).
fn planes(v: &[[f64; 3]], faces: &[[u32; 3]], tol: f64) -> Vec<([f32; 3], f32)> {
    let mut out: Vec<([f64; 3], f64)> = Vec::new();
    for f in faces {
        let [a, b, c] = f.map(|i| v[i as usize]);
        let (u, w): ([f64; 3], [f64; 3]) = (
            std::array::from_fn(|k| b[k] - a[k]),
            std::array::from_fn(|k| c[k] - a[k]),
        );
        let n = [
            u[1] * w[2] - u[2] * w[1],
            u[2] * w[0] - u[0] * w[2],
            u[0] * w[1] - u[1] * w[0],
        ];
        let len = n.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(len > 0.0) {
            continue;
        }
        let n = n.map(|x| x / len);
        let d = (0..3).map(|k| n[k] * a[k]).sum::<f64>();
        let same = out.iter().any(|(m, e)| {
            (0..3).map(|k| m[k] * n[k]).sum::<f64>() > 1.0 - 1e-9 && (e - d).abs() < tol
        });
        if !same {
            out.push((n, d));
        }
    }
    out.into_iter()
        .map(|(n, d)| (n.map(|x| x as f32), d as f32))
        .collect()
}
