//! The particle projection: a particle that ends a substep deeper than
//! [`PROJECT_DEPTH_CELLS`] inside a collider loses its inward velocity and
//! goes back onto its surface; a solid's particle (one that carries a
//! deformation gradient `F`) goes back only from [`SOLID_PROJECT_DEPTH_CELLS`].

use nalgebra::SVector;

use super::condition::project_velocity;
use super::{Collider, Reach};

impl<const D: usize> Collider<D> {
    /// The particle projection of a collider with [`Collider::project`]
    /// (the solver calls it for each particle after g2p has moved it, with
    /// `depth` = [`PROJECT_DEPTH_CELLS`] cells, the threshold `reach` was
    /// made with: [`Collider::reach`]). A particle at `x` with signed
    /// distance `φ < −depth` (deeper inside than that) goes to the surface
    /// along the outward normal `n`, `x ← x − φ·n` (`φ` and `n` from
    /// [`Shape::step_below`]: exactly onto a box's face of least
    /// penetration or a sphere's surface, onto a sampled shape's to first
    /// order), and its velocity relative to the collider's (`v_obs`, `None`
    /// for a collider at rest) loses its inward normal part: `Sticky` takes
    /// the collider's velocity, `Slip` keeps the tangential part and an
    /// outward normal part, `Separate` does the same with Coulomb friction μ
    /// on the tangential speed as the grid condition does
    /// ([`apply_condition`]). With `keep_above` = `Some(d)` (a solid's
    /// particle, `d` = [`SOLID_PROJECT_DEPTH_CELLS`] cells in metres) a
    /// particle no deeper than `d` keeps its position and only its velocity
    /// changes: its `F` describes where its neighbours are, and a jump that
    /// `F` does not see becomes a strain the body keeps. Returns whether the
    /// particle's position or velocity changed.
    ///
    /// A particle where `reach` says the projection cannot act returns at
    /// once, untouched ([`Reach::may_act`], inlined here: most particles).
    ///
    /// [`Shape::step_below`]: super::Shape::step_below
    /// [`apply_condition`]: super::apply_condition
    #[inline(always)]
    pub fn project_particle(
        &self,
        reach: &Reach<'_, D>,
        x: &mut SVector<f32, D>,
        v: &mut SVector<f32, D>,
        v_obs: Option<&SVector<f32, D>>,
        keep_above: Option<f32>,
    ) -> bool {
        reach.may_act(x) && self.project_deeper(reach.depth, x, v, v_obs, keep_above)
    }

    /// [`Collider::project_particle`] past its inlined test.
    #[inline]
    fn project_deeper(
        &self,
        depth: f32,
        x: &mut SVector<f32, D>,
        v: &mut SVector<f32, D>,
        v_obs: Option<&SVector<f32, D>>,
        keep_above: Option<f32>,
    ) -> bool {
        let Some((phi, n)) = self.shape.step_below(x, depth) else {
            return false;
        };
        if keep_above.is_none_or(|d| phi < -d) {
            *x -= n * phi;
        }
        match v_obs {
            None => project_velocity(v, &n, self.condition, self.friction),
            Some(u) => {
                let mut rel = *v - u;
                project_velocity(&mut rel, &n, self.condition, self.friction);
                *v = u + rel;
            }
        }
        true
    }
}

/// How deep [grid cells] a particle may end a substep inside a collider
/// that projects particles ([`Collider::project_particle`]); a deeper one
/// goes back onto the surface. Particles within a fraction of a cell of the
/// surface are MPM's ordinary contact (the kernel spreads a particle over
/// nodes on both sides) and are left alone: measured (docs/obstacles.md),
/// a threshold of 0 rather than a quarter cell makes a mesh sphere's and a
/// mesh ramp's runs depart from their analytic twins' more (grid-mass
/// error 0.014 and 0.048 against 0.009 and 0.021 on a 32³ grid), and the
/// deepest particle stays below 0.3 cells either way.
pub const PROJECT_DEPTH_CELLS: f32 = 0.25;

/// How deep [grid cells] a solid's particle (elastic, snow, viscoplastic:
/// those whose `F` is their shape) may end a substep inside a collider that
/// projects particles before it goes back onto the surface; from
/// [`PROJECT_DEPTH_CELLS`] to this depth it only loses its inward velocity
/// and the body's own stress pushes it out. A particle put back moves
/// without its `F` seeing it: a strain the body keeps. Measured
/// (docs/materials.md, Limits; `benchmarks/solid_contact.py`): a 0.12 m
/// jello cube pressed by the surge against `paddle3d`'s paddle keeps, at
/// frame 1200 (RMS off a rigid motion, in fractions of its side), for
/// E 10 / 20 / 40 kPa: 6.4 / 3.2 / 1.5 % from half a cell, 5.3 / 3.0 /
/// 1.2 % from 0.625, 4.8 / 2.5 / 1.2 % from three quarters; 6.7 % (20 kPa)
/// from a quarter cell, 1.8 % when never put back. The deepest particle
/// reaches the depth (0.85 cells when never put back). Three quarters keeps
/// the 20 kPa cube within 3 % of its side at the least depth measured.
pub const SOLID_PROJECT_DEPTH_CELLS: f32 = 0.75;

// a solid's particle is put back from deeper than water's, never shallower
const _: () = assert!(SOLID_PROJECT_DEPTH_CELLS > PROJECT_DEPTH_CELLS);
