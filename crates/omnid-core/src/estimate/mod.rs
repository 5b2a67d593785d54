//! State estimation: encoder angles → (q, q̇, q̈) per joint.

pub(crate) mod kalman;
pub mod smoother;

pub use kalman::{Estimate, KalmanBank, KalmanConfig};
