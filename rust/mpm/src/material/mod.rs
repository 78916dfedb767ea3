//! Constitutive models: what each material contributes to a substep.
//!
//! A particle carries its Kirchhoff stress `τ` (derived from its state); p2g
//! turns it into grid forces, and g2p updates the material state from the new
//! velocity gradient `C` and recomputes `τ`:
//!
//! - [`water`]: weakly compressible water, state `J` (Hu et al. 2018, mpm88).
//! - [`sand`]: Drucker–Prager elastoplasticity in Hencky strain, state `F`
//!   and the volume correction (Klár et al. 2016; Tampubolon et al. 2017).
//! - [`solid`]: the elastic solid (fixed-corotated, Stomakhin et al. 2012, or
//!   neo-Hookean), snow (Stomakhin et al. 2013) and the viscoplastic solid
//!   (von Mises on the Hencky strain with viscous relaxation), state `F`
//!   (and `J_P` for snow); and the per-set constants of every material
//!   ([`solid::Models`]).

mod lanes;
pub mod sand;
pub(crate) mod solid;
mod vmath;
pub mod water;
