//! The solver's rigid bodies: adding, removing and reading them between
//! frames, and their part in a frame ([`crate::body`], docs/bodies.md).

use super::Solver;
use crate::body::{Bodies, Body, BodyState, MAX_BODIES};
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
    /// field under `bodies[i]` ([`Body::validate`]), or `bodies` beyond
    /// [`MAX_BODIES`]; on error nothing changes.
    pub fn add_body(&mut self, body: Body<D>) -> Result<usize> {
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
        self.bodies.push(body);
        Ok(i)
    }

    /// Removes body `index` (between frames; the later ones move down one).
    /// Errors (field `index`) for no such body.
    pub fn remove_body(&mut self, index: usize) -> Result<()> {
        self.check_body(index)?;
        self.bodies.remove(index);
        Ok(())
    }

    /// Sets body `index`'s exact state (a checkpoint's). Errors name
    /// `index`, or `bodies[i].state` for a non-finite state.
    pub fn set_body_state(&mut self, index: usize, state: BodyState) -> Result<()> {
        self.check_body(index)?;
        let finite = state
            .x
            .iter()
            .chain(&state.q)
            .chain(&state.v)
            .chain(&state.w)
            .all(|x| x.is_finite());
        if !finite {
            return Err(MpmError::invalid(
                format!("bodies[{index}].state"),
                "must be finite",
            ));
        }
        self.bodies.set_state(index, state);
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
        let dx = self.params.dx();
        let lo = self.params.walls.cells as f32 * dx;
        self.bodies
            .begin(&self.params.gravity, lo, 1.0 - lo, 8.0 * dx);
    }
}
