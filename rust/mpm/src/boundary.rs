//! How a boundary (a wall of the domain, a collider) acts on the grid
//! velocity of the nodes inside it: [`BoundaryCondition`], named in the
//! parameter dict (the rule itself: [`crate::collider::apply_condition`]).
//! Both [`crate::params`] and [`crate::collider`] use it; it uses neither.

use crate::error::{MpmError, Result};

/// How a boundary acts on the grid velocity of nodes inside it (named
/// `"sticky"`, `"slip"`, `"separate"` in the parameter dict).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum BoundaryCondition {
    /// Velocity set to the boundary's (zero): no slip.
    Sticky,
    /// Normal component removed both ways (no penetration, no separation).
    Slip,
    /// Only the inward normal component removed; Coulomb friction on the
    /// tangential part while in contact.
    Separate,
}

impl BoundaryCondition {
    pub fn parse(field: &str, s: &str) -> Result<Self> {
        match s {
            "sticky" => Ok(Self::Sticky),
            "slip" => Ok(Self::Slip),
            "separate" => Ok(Self::Separate),
            other => Err(MpmError::invalid(
                field,
                format!("must be one of 'sticky', 'slip', 'separate', got '{other}'"),
            )),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Sticky => "sticky",
            Self::Slip => "slip",
            Self::Separate => "separate",
        }
    }
}
