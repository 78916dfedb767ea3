//! The solver's rigid bodies: adding, removing and reading them between
//! frames, and their part in a frame ([`crate::body`], docs/bodies.md).

use std::sync::Arc;

use nalgebra::SVector;

use super::Solver;
use crate::body::world::{ObstacleShape, ObstacleSpec, Voxelized};
use crate::body::{Bodies, Body, BodyPose, BodyState, MAX_BODIES};
use crate::collider::Shape;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// The rigid bodies: as given, their states, the fluid's force on each
    /// over the last frame.
    pub fn bodies(&self) -> &Bodies<D> {
        &self.bodies
    }

    /// Adds a body (between frames); returns its index. Errors name the
    /// field under `bodies[i]` ([`Body::validate`]; `center` for a body
    /// that overlaps another body where it is now, by parry's intersection
    /// test, or an obstacle, at a grid node inside both), or `bodies` beyond
    /// [`MAX_BODIES`]; on error nothing changes.
    pub fn add_body(&mut self, body: Body<D>) -> Result<usize> {
        self.push_checked(body, true)
    }

    /// Adds a body as a parameter set gives it (a scene's, or a
    /// checkpoint's before its states are set): as [`Solver::add_body`],
    /// but not checked for overlaps (a checkpoint's bodies were checked when
    /// they were added, against where the others were then; a scene file's
    /// are checked when it is read).
    pub fn add_given_body(&mut self, body: Body<D>) -> Result<usize> {
        self.push_checked(body, false)
    }

    /// The checks of [`Solver::add_body`] (the count, [`Body::validate`]
    /// and, with `overlaps`, [`Self::check_overlap`]), then the body; on
    /// error nothing changes.
    fn push_checked(&mut self, body: Body<D>, overlaps: bool) -> Result<usize> {
        let i = self.bodies.len();
        if i >= MAX_BODIES {
            return Err(MpmError::invalid(
                "bodies",
                format!("at most {MAX_BODIES} bodies, the solver has {i}"),
            ));
        }
        body.validate(
            &format!("bodies[{i}]"),
            self.params.dx(),
            self.params.walls.cells,
        )?;
        if overlaps {
            self.check_overlap(&body, i)?;
        }
        self.bodies.push(body);
        self.drift_frames = 0; // a projection step spanning frames ends: the next frame steps the body
        Ok(i)
    }

    /// Refuses (field `bodies[i].center`) body `body`, to be body `i`, where
    /// it overlaps a body (at that body's state now) or an obstacle.
    fn check_overlap(&self, body: &Body<D>, i: usize) -> Result<()> {
        let field = format!("bodies[{i}].center");
        let state = BodyState::of(body);
        for (j, (other, st)) in self
            .bodies
            .bodies()
            .iter()
            .zip(self.bodies.states())
            .enumerate()
        {
            if body.overlaps(&state, other, st) {
                return Err(MpmError::invalid(
                    field,
                    format!("the body overlaps body {j}"),
                ));
            }
        }
        if self.colliders.is_empty() {
            return Ok(());
        }
        // the grid nodes inside the body: one inside an obstacle too is an overlap
        let pose = BodyPose {
            shape: body.shape.clone(),
            center: body.center,
            rotation: body.rotation,
            velocity: SVector::zeros(),
            angular_velocity: [0.0; 3],
            friction: 0.0,
        };
        let dx = self.params.dx();
        let r = body.shape.bounding_radius();
        let lo: [usize; D] =
            std::array::from_fn(|d| ((body.center[d] - r) / dx).floor().max(0.0) as usize);
        let n: [usize; D] =
            std::array::from_fn(|d| ((body.center[d] + r) / dx).ceil() as usize + 1 - lo[d]);
        for mut k in 0..n.iter().product::<usize>() {
            let mut x = SVector::<f32, D>::zeros();
            for d in 0..D {
                x[d] = (lo[d] + k % n[d]) as f32 * dx;
                k /= n[d];
            }
            if pose.sdf_normal(&x).0 >= 0.0 {
                continue;
            }
            if let Some(c) = self.colliders.iter().position(|c| c.shape.sdf(&x) < 0.0) {
                return Err(MpmError::invalid(
                    field,
                    format!("the body overlaps obstacle {c} (grid node {x:?} is inside both)"),
                ));
            }
        }
        Ok(())
    }

    /// Removes body `index` (between frames; the later ones move down one).
    /// Errors (field `index`) for no such body.
    pub fn remove_body(&mut self, index: usize) -> Result<()> {
        self.check_body(index)?;
        self.bodies.remove(index);
        self.drift_frames = 0; // as for an added body
        Ok(())
    }

    /// Checks a checkpoint's state for body `index` without setting it
    /// ([`Body::check_state`]: finite, a unit rotation, inside the walls
    /// within a cell, no faster than a frame can simulate). Errors name
    /// `index`, or `body_state[index]`.
    pub fn check_body_state(&self, index: usize, state: &BodyState) -> Result<()> {
        self.check_body(index)?;
        self.bodies.bodies()[index].check_state(
            &format!("body_state[{index}]"),
            state,
            self.params.dx(),
            self.params.walls.cells,
        )
    }

    /// Sets body `index`'s exact state (a checkpoint's), checked as
    /// [`Solver::check_body_state`] does; on error nothing changes.
    pub fn set_body_state(&mut self, index: usize, state: BodyState) -> Result<()> {
        self.check_body_state(index, &state)?;
        self.bodies.set_state(index, state);
        Ok(())
    }

    /// Sets the fluid's mean force [N] and torque [N·m] on body `index`
    /// over the last frame, as a checkpoint holds them (lanes as
    /// [`Bodies::last_force`]'s): a restored solver reads what the one that
    /// wrote it read. Errors naming `index` (no such body) or
    /// `bodies[index].force` (not finite); nothing changes then.
    pub fn set_body_force(&mut self, index: usize, force: [f64; 6]) -> Result<()> {
        self.check_body(index)?;
        if !force.iter().all(|x| x.is_finite()) {
            return Err(MpmError::invalid(
                format!("bodies[{index}].force"),
                "must be finite",
            ));
        }
        self.bodies.set_last_force(index, force);
        Ok(())
    }

    fn check_body(&self, index: usize) -> Result<()> {
        if index >= self.bodies.len() {
            return Err(MpmError::invalid(
                "index",
                format!("no body {index}: the solver has {}", self.bodies.len()),
            ));
        }
        Ok(())
    }

    /// Start of a frame attempt: the bodies' rigid world, with walls at the
    /// inner faces of the wall bands.
    pub(super) fn begin_bodies(&mut self) {
        if self.bodies.is_empty() {
            return;
        }
        let obstacles = self
            .colliders
            .iter()
            .zip(&self.moves)
            .map(|(c, m)| obstacle_spec(&c.shape, m.is_some(), self.bodies.obstacles()))
            .collect();
        self.bodies.set_obstacles(obstacles);
        let dx = self.params.dx();
        let lo = self.params.walls.cells as f32 * dx;
        self.bodies
            .begin(&self.params.gravity, lo, 1.0 - lo, 8.0 * dx);
    }
}

/// An obstacle for the bodies' rigid world: a box, a ball or a mesh
/// obstacle's voxels where it is now, kinematic when it moves in the frame.
/// A mesh obstacle's voxels are taken from `previous` (the last world's
/// obstacles) while its samples are the same, else made from them.
fn obstacle_spec<const D: usize>(
    shape: &Shape<D>,
    moving: bool,
    previous: &[ObstacleSpec],
) -> ObstacleSpec {
    let pad = |v: &SVector<f32, D>| std::array::from_fn(|d| if d < D { v[d] } else { 0.0 });
    let mut o = ObstacleSpec {
        shape: ObstacleShape::Absent,
        x: [0.0; 3],
        q: if D == 2 {
            [1.0, 0.0, 0.0, 0.0]
        } else {
            [0.0, 0.0, 0.0, 1.0]
        },
        moving,
    };
    match shape {
        Shape::Box {
            center,
            half_extents,
            rotation,
        } => {
            o.shape = ObstacleShape::Box(pad(half_extents));
            o.x = pad(center);
            let body = Body {
                shape: crate::body::BodyShape::Ball { radius: 1.0 },
                center: *center,
                rotation: *rotation,
                density: 1.0,
                velocity: SVector::zeros(),
                angular_velocity: [0.0; 3],
                friction: 0.0,
            };
            o.q = BodyState::of(&body).q;
        }
        Shape::Sphere { center, radius } => {
            o.shape = ObstacleShape::Ball(*radius);
            o.x = pad(center);
        }
        Shape::Sampled {
            origin,
            cell,
            dims,
            values,
            ..
        } => {
            o.x = pad(origin);
            let kept = previous.iter().find_map(|p| match &p.shape {
                ObstacleShape::Voxels(v) if Arc::ptr_eq(&v.source, values) => Some(Arc::clone(v)),
                _ => None,
            });
            if let Some(v) =
                kept.or_else(|| Voxelized::of_samples(values, dims, *cell).map(Arc::new))
            {
                o.shape = ObstacleShape::Voxels(v);
            }
        }
    }
    o
}
