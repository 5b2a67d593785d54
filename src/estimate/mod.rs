//! State estimation: encoder angles → (q, q̇, q̈) per joint.

pub mod kalman;

pub use kalman::KalmanBank;
