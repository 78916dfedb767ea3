//! A body where it is during a substep ([`BodyPose`]): what the grid
//! update's collider pass reads (signed distance, outward normal, point
//! velocity) and the exact sums of the impulses it writes ([`ImpulseSum`]).

use nalgebra::{SMatrix, SVector};

use super::BodyShape;

/// A body's pose and velocity for one substep, in `f32` for the grid update.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyPose<const D: usize> {
    pub shape: BodyShape<D>,
    /// Centre of mass [m].
    pub center: SVector<f32, D>,
    /// Rotation (columns: the body's axes in world coordinates).
    pub rotation: SMatrix<f32, D, D>,
    /// Velocity of the centre of mass [m/s].
    pub velocity: SVector<f32, D>,
    /// Angular velocity [rad/s] (2D: about z, the last component).
    pub angular_velocity: [f32; 3],
    /// Coulomb friction coefficient against the fluid.
    pub friction: f32,
}

impl<const D: usize> BodyPose<D> {
    /// Signed distance of `x` to the surface [m] (negative inside) and the
    /// outward unit normal there (of the nearest face; a ball's radial
    /// direction, `+x` at its centre; a capsule's from its segment, `+x` on
    /// it; a hull's from the face plane it lies farthest outside of, exact
    /// inside: [`super::Hull::sdf_normal`]).
    #[inline]
    pub fn sdf_normal(&self, x: &SVector<f32, D>) -> (f32, SVector<f32, D>) {
        let r = x - self.center;
        match &self.shape {
            BodyShape::Capsule {
                radius,
                half_height,
            } => {
                let mut q = self.rotation.tr_mul(&r);
                q[1] -= q[1].clamp(-half_height, *half_height);
                let len = q.norm();
                let local = if len > 0.0 {
                    q / len
                } else {
                    SVector::from_fn(|d, _| if d == 0 { 1.0 } else { 0.0 })
                };
                (len - radius, self.rotation * local)
            }
            BodyShape::Hull(hull) => {
                let q = self.rotation.tr_mul(&r);
                let (dist, n) =
                    hull.sdf_normal(std::array::from_fn(|d| if d < D { q[d] } else { 0.0 }));
                let local = SVector::<f32, D>::from_fn(|d, _| n[d]);
                (dist, self.rotation * local)
            }
            BodyShape::Ball { radius } => {
                let len = r.norm();
                let n = if len > 0.0 {
                    r / len
                } else {
                    SVector::from_fn(|d, _| if d == 0 { 1.0 } else { 0.0 })
                };
                (len - *radius, n)
            }
            BodyShape::Box { half_extents } => {
                let q = self.rotation.tr_mul(&r);
                let mut out = SVector::<f32, D>::zeros();
                let (mut inside, mut axis) = (f32::NEG_INFINITY, 0);
                for d in 0..D {
                    let e = q[d].abs() - half_extents[d];
                    out[d] = e.max(0.0).copysign(q[d]);
                    if e > inside {
                        (inside, axis) = (e, d);
                    }
                }
                let len = out.norm();
                let local = if len > 0.0 {
                    out / len
                } else {
                    SVector::from_fn(|d, _| {
                        if d == axis {
                            1.0f32.copysign(q[d])
                        } else {
                            0.0
                        }
                    })
                };
                let dist = if len > 0.0 { len } else { inside };
                (dist, self.rotation * local)
            }
        }
    }

    /// The body's velocity at point `x`: `v + ω × (x − c)` [m/s].
    #[inline]
    pub fn point_velocity(&self, x: &SVector<f32, D>) -> SVector<f32, D> {
        point_velocity(&self.center, &self.velocity, &self.angular_velocity, x)
    }

    /// Whether the shape, grown by `margin` [m], may reach the ball of
    /// radius `radius` about `centre`.
    #[inline]
    pub fn near(&self, centre: &SVector<f32, D>, radius: f32, margin: f32) -> bool {
        (centre - self.center).norm() < self.shape.bounding_radius() + radius + margin
    }
}

/// A rigid body's velocity at point `x`: `v + ω × (x − c)` [m/s], for centre of mass `c`, velocity
/// `v` and angular velocity `w` [rad/s] (2D: about z, the last component).
#[inline]
pub fn point_velocity<const D: usize>(
    c: &SVector<f32, D>,
    v: &SVector<f32, D>,
    w: &[f32; 3],
    x: &SVector<f32, D>,
) -> SVector<f32, D> {
    let r = x - c;
    let mut u = *v;
    if D == 2 {
        u[0] -= w[2] * r[1];
        u[1] += w[2] * r[0];
    } else {
        u[0] += w[1] * r[2] - w[2] * r[1];
        u[1] += w[2] * r[0] - w[0] * r[2];
        u[2] += w[0] * r[1] - w[1] * r[0];
    }
    u
}

/// Fixed-point scale of [`ImpulseSum`]: 2⁻⁴⁸ units (≈ 3.6e-15).
const SCALE: f64 = (1u64 << 48) as f64;

/// Lanes of an [`ImpulseSum`]: the explicit impulse (0..3) and torque
/// impulse (3..6), then the 21 entries of the symmetric 6×6 matrix
/// `Σ m jᵀj` over the constrained nodes, `j = [n, r × n]` (upper triangle,
/// row by row).
pub const SUM_LANES: usize = 27;

/// The impulse and its torque about the centre of mass, and the coupled
/// mass matrix, summed over grid nodes in fixed point: integer sums, so the
/// total is the same bits in any order of the nodes, for any number of
/// threads. Impulses in N·s (per unit depth in 2D), torques in N·m·s (2D:
/// about z, lane 5).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImpulseSum(pub [i128; SUM_LANES]);

impl Default for ImpulseSum {
    fn default() -> Self {
        ImpulseSum([0; SUM_LANES])
    }
}

#[inline]
fn q(x: f64) -> i128 {
    (x * SCALE).round() as i128
}

#[inline]
fn lift<const D: usize>(v: &SVector<f32, D>) -> [f64; 3] {
    std::array::from_fn(|d| if d < D { v[d] as f64 } else { 0.0 })
}

#[inline]
fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

impl ImpulseSum {
    /// Adds the impulse `j` applied at `r` from the centre of mass.
    #[inline]
    pub fn add<const D: usize>(&mut self, j: &SVector<f32, D>, r: &SVector<f32, D>) {
        let (jj, rr) = (lift(j), lift(r));
        let t = cross(&rr, &jj);
        for k in 0..3 {
            self.0[k] += q(jj[k]);
            self.0[3 + k] += q(t[k]);
        }
    }

    /// Adds a node of mass `m` held at the body's normal velocity along `n`
    /// at `r` from the centre of mass: `m jᵀj` with `j = [n, r × n]`.
    #[inline]
    pub fn add_coupled<const D: usize>(
        &mut self,
        m: f32,
        n: &SVector<f32, D>,
        r: &SVector<f32, D>,
    ) {
        let (nn, rr) = (lift(n), lift(r));
        let rn = cross(&rr, &nn);
        let j = [nn[0], nn[1], nn[2], rn[0], rn[1], rn[2]];
        let m = m as f64;
        let mut k = 6;
        for a in 0..6 {
            for b in a..6 {
                self.0[k] += q(m * j[a] * j[b]);
                k += 1;
            }
        }
    }

    /// Adds another sum.
    pub fn merge(&mut self, o: &ImpulseSum) {
        for k in 0..SUM_LANES {
            self.0[k] += o.0[k];
        }
    }

    /// `(impulse, torque impulse)` as numbers.
    pub fn value(&self) -> ([f64; 3], [f64; 3]) {
        let f = |k: usize| self.0[k] as f64 / SCALE;
        ([f(0), f(1), f(2)], [f(3), f(4), f(5)])
    }

    /// The coupled mass matrix `Σ m jᵀj` (6×6, symmetric).
    pub fn coupled(&self) -> [[f64; 6]; 6] {
        let mut out = [[0.0; 6]; 6];
        let mut k = 6;
        for a in 0..6 {
            for b in a..6 {
                let x = self.0[k] as f64 / SCALE;
                out[a][b] = x;
                out[b][a] = x;
                k += 1;
            }
        }
        out
    }
}

/// A grid node held at a body's normal velocity in this substep's grid
/// update: after the bodies' velocities change, its normal velocity follows
/// (`Bodies::substep`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coupled {
    /// The node's place in the grid update's output (`out_v`).
    pub node: u32,
    /// The body.
    pub body: u32,
    /// Outward normal and offset from the centre of mass (lanes past D zero).
    pub n: [f32; 3],
    pub r: [f32; 3],
}
