//! Error type of the MPM crate.

use thiserror::Error;

/// Errors of the MPM solver. Input errors name the offending field.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum MpmError {
    /// A parameter or input array is malformed or out of range.
    #[error("{field}: {msg}")]
    InvalidInput { field: String, msg: String },
    /// An input would make the solver (or `grid_mass`) allocate more than the
    /// memory budget it was given; nothing was allocated.
    #[error(
        "{field}: {what} would need {} ({bytes} bytes), over the memory budget of {}",
        human_bytes(*bytes as f64),
        human_bytes(*budget as f64)
    )]
    OverBudget {
        field: String,
        what: String,
        bytes: u128,
        budget: u64,
    },
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
    /// A sand particle's elastic deformation gradient inverted (`det F ≤ 0`)
    /// during a substep, even with the substep halved `retries` times; the
    /// solver state was rolled back to the beginning of the frame.
    #[error(
        "a sand particle's deformation gradient inverted (det F <= 0) at substep {substep} of the frame (of {substeps}, after {retries} retries with the substep halved); state restored to the start of the frame"
    )]
    Inverted {
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
    /// The CFL condition asks for more than `max_substeps` substeps in the
    /// frame (`needed`, possibly astronomically many): the fastest speed
    /// (`max_speed`, set by `speed_of`: the particles, a moving obstacle or
    /// a body's fastest point) plus the largest wave speed (`wave_speed`,
    /// of the parameter set `wave_of`) is too fast for the grid. The state
    /// is unchanged.
    #[error(
        "{speed_of} moving at up to {} m/s and {wave_of} (wave speed {} m/s) need {} substeps of at most {} s (cfl·dx / (c + |v|max)) for a frame of {dt_frame} s, more than max_substeps = {max_substeps}; state unchanged",
        num(*max_speed),
        num(*wave_speed as f64),
        count(*needed),
        num(*dt_max)
    )]
    TooManySubsteps {
        needed: f64,
        max_substeps: usize,
        max_speed: f64,
        wave_speed: f32,
        dt_max: f64,
        dt_frame: f32,
        /// What moves fastest: `particles`, `a moving obstacle`, `body 2's
        /// fastest point`.
        speed_of: String,
        /// The parameter set whose wave speed is the largest:
        /// `parameter set 1 (elastic)`, or `no material` without particles.
        wave_of: String,
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

    /// The field named by an input error (`InvalidInput`, `OverBudget`).
    pub fn field(&self) -> Option<&str> {
        match self {
            MpmError::InvalidInput { field, .. } | MpmError::OverBudget { field, .. } => {
                Some(field)
            }
            _ => None,
        }
    }
}

/// `bytes` as a short human-readable size (`3.2 GiB`), as Python's
/// `hybridmpm.limits.human` writes it.
pub fn human_bytes(bytes: f64) -> String {
    let mut x = bytes;
    for unit in ["B", "KiB", "MiB", "GiB", "TiB"] {
        if x.abs() < 1024.0 {
            return if unit == "B" {
                format!("{x:.0} B")
            } else {
                format!("{x:.1} {unit}")
            };
        }
        x /= 1024.0;
    }
    format!("{x:.1} PiB")
}

/// A number for a message: `12.5`, `0.0025`, `1.953e-4`, `1.414e30`.
fn num(x: f64) -> String {
    if x == 0.0 || (1e-3..1e7).contains(&x.abs()) {
        let s = format!("{x:.6}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{x:.3e}")
    }
}

/// A count that may be astronomically large: exact below 1e15, else `1.2e30`.
fn count(x: f64) -> String {
    if x < 1e15 {
        format!("{x:.0}")
    } else {
        format!("{x:.1e}")
    }
}

/// Refuses `bytes` (an estimate; `None`: beyond `u128`) for `what` above
/// `budget` (`None`: no budget) with [`MpmError::OverBudget`] naming `field`.
pub fn check_budget(
    field: &str,
    what: &str,
    bytes: Option<u128>,
    budget: Option<u64>,
) -> Result<()> {
    let Some(budget) = budget else {
        return Ok(());
    };
    let bytes = bytes.unwrap_or(u128::MAX);
    if bytes > budget as u128 {
        return Err(MpmError::OverBudget {
            field: field.into(),
            what: what.into(),
            bytes,
            budget,
        });
    }
    Ok(())
}

pub type Result<T> = std::result::Result<T, MpmError>;
