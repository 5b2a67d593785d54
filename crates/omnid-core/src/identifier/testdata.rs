//! Test data from the rigid-body model: i.i.d. random states and multisine streams.

use super::pretune::Sample;
use crate::config::ReferenceConfig;
use crate::control::{Reference, Trajectory};
use crate::omni::{Dynamics, Geometry, ModelParams};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The simulator's plant: default parameters, friction on.
pub fn plant() -> Dynamics {
    Dynamics::new(ModelParams::default(), Geometry::default())
}

fn uniform(rng: &mut ChaCha8Rng, centre: [f64; 3], half: [f64; 3]) -> Vector3<f64> {
    Vector3::from_fn(|i, _| centre[i] + half[i] * (2.0 * rng.random::<f64>() - 1.0))
}

/// States drawn uniformly over the workspace the reference trajectories cover.
pub fn random_samples(n: usize, seed: u64) -> Vec<Sample> {
    let d = plant();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let q = uniform(&mut rng, [0.0, 0.65, 0.3], [0.5, 0.35, 0.35]);
            let qd = uniform(&mut rng, [0.0; 3], [1.5; 3]);
            let qdd = uniform(&mut rng, [0.0; 3], [12.0; 3]);
            let tau = d.inverse_dynamics(&q, &qd, &qdd);
            Sample { q, qd, qdd, tau }
        })
        .collect()
}

/// A multisine trajectory (the `--trajectory multisine` reference) sampled every `dt`, with
/// the exact torque of the plant.
pub fn multisine_samples(seconds: f64, dt: f64, seed: u64) -> Vec<Sample> {
    let d = plant();
    let r = Reference::new(Trajectory::Multisine, &ReferenceConfig::default(), seed);
    let n = (seconds / dt).round() as usize;
    (0..n)
        .map(|k| {
            let p = r.target(k as f64 * dt);
            let tau = d.inverse_dynamics(&p.q, &p.qd, &p.qdd);
            Sample {
                q: p.q,
                qd: p.qd,
                qdd: p.qdd,
                tau,
            }
        })
        .collect()
}
