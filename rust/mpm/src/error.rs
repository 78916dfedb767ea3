//! Error type of the MPM crate.

use thiserror::Error;

/// Errors of the MPM solver. Input errors name the offending field.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum MpmError {
    /// A parameter or input array is malformed or out of range.
    #[error("{field}: {msg}")]
    InvalidInput { field: String, msg: String },
    /// The state became non-finite during a substep; the solver state was
    /// rolled back to the beginning of the frame.
    #[error(
        "non-finite state at substep {substep} of the frame (of {substeps}, after {retries} retries with the substep halved); state restored to the start of the frame"
    )]
    NonFinite {
        substep: usize,
        substeps: usize,
        retries: usize,
    },
    /// A particle travelled more than one grid cell in a substep (speed
    /// `max_speed` m/s) even with the substep halved `retries` times; the
    /// solver state was rolled back to the beginning of the frame.
    #[error(
        "CFL violation at substep {substep} of the frame (of {substeps}, after {retries} retries with the substep halved): max speed {max_speed} m/s moves particles more than one cell per substep; state restored to the start of the frame"
    )]
    CflViolation {
        substep: usize,
        substeps: usize,
        max_speed: f32,
        retries: usize,
    },
    /// A checkpoint blob could not be decoded.
    #[error("checkpoint: {0}")]
    Checkpoint(String),
}

impl MpmError {
    pub fn invalid(field: impl Into<String>, msg: impl Into<String>) -> Self {
        MpmError::InvalidInput {
            field: field.into(),
            msg: msg.into(),
        }
    }
}

pub type Result<T> = std::result::Result<T, MpmError>;
