//! Why a product or staff holon process stops with an error. (A resource holon has more
//! ways to fail, its components and its controller's claim: [`crate::node::NodeError`].)

/// Why a product or staff holon process stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum HolonError {
    /// A step of the holon's life cycle: its session, its name, a take-over, a
    /// hand-over.
    #[error(transparent)]
    Life(#[from] holon::life::LifeError),
    /// Zenoh refused a declaration (described).
    #[error("zenoh: {0}")]
    Zenoh(String),
}
