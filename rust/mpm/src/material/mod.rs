//! Constitutive models: what each material contributes to a substep.
//!
//! A particle carries its Kirchhoff stress `τ` (derived from its state); p2g
//! turns it into grid forces, and g2p updates the material state from the new
//! velocity gradient `C` and recomputes `τ`:
//!
//! - [`water`]: weakly compressible water, state `J` (Hu et al. 2018, mpm88).
//! - [`sand`]: Drucker–Prager elastoplasticity in Hencky strain, state `F`
//!   and the volume correction (Klár et al. 2016; Tampubolon et al. 2017).

mod lanes;
pub mod sand;
mod vmath;
pub mod water;
