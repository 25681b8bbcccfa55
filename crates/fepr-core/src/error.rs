//! The crate's error type. Every message names the offending item (tet index, parameter name).

use thiserror::Error;

/// Errors reported by fepr-core. Messages are meant for end users: they name the tet, vertex or
/// parameter and say what is wrong.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum FeprError {
    /// The mesh is invalid (index out of range, repeated vertex, degenerate tet, non-finite coordinate...).
    #[error("{0}")]
    Mesh(String),
    /// A parameter is out of its valid range.
    #[error("{name}: {message}")]
    InvalidParameter { name: &'static str, message: String },
    /// The simulation cannot continue (non-finite state).
    #[error("{0}")]
    Simulation(String),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, FeprError>;

pub(crate) fn invalid(name: &'static str, message: impl Into<String>) -> FeprError {
    FeprError::InvalidParameter {
        name,
        message: message.into(),
    }
}
