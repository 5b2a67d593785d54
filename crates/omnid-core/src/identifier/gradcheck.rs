//! Every hand-derived gradient of the identifier against central finite differences: each
//! error term (e1, e2, e3, e4) separately, each network, each layer, weights and biases.

use super::adaptive::{Identifier, Net, Wae};
use super::IdentifierConfig;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const TERMS: [(&str, usize); 4] = [("e1", 0), ("e2", 3), ("e3", 6), ("e4", 9)];

struct Point {
    q: Vector3<f64>,
    qd: Vector3<f64>,
    qdd: Vector3<f64>,
    tau: Vector3<f64>,
}

fn vec3(rng: &mut ChaCha8Rng, c: [f64; 3], h: f64) -> Vector3<f64> {
    Vector3::from_fn(|i, _| c[i] + h * (2.0 * rng.random::<f64>() - 1.0))
}

fn base_config(seed: u64) -> IdentifierConfig {
    IdentifierConfig {
        hidden: 6,
        seed,
        lambda1: 3.0,
        lambda2: 2.5,
        lambda3: 4.0,
        // Larger than the defaults, so that every path through the networks matters.
        init_std_output: 0.7,
        init_std_hidden: 1.5,
        init_mass_diag: [4e-3, 2.5e-3, 1e-3],
        // Unsaturated F-net units, so its hidden-layer gradient is not ~0.
        friction_qd_scale: [1.0; 3],
        ..IdentifierConfig::default()
    }
}

/// An identifier whose eigenvalue bounds put the smallest eigenvalue of M̂ below eig_min
/// and the largest above eig_max at `p.q`, with margins far beyond the FD perturbation (the
/// first seed from `seed` on whose M̂ has three well separated eigenvalues, the middle one
/// positive).
fn identifier_with_active_e4(seed: u64, p: &Point) -> Identifier {
    for s in seed..seed + 100 {
        let mut id = Identifier::new(&base_config(s)).unwrap();
        let mut l: Vec<f64> = id
            .mass(&p.q)
            .symmetric_eigenvalues()
            .iter()
            .copied()
            .collect();
        l.sort_by(f64::total_cmp);
        if !(l[1] - l[0] > 1e-4 && l[2] - l[1] > 1e-4 && l[1] > 1e-4) {
            continue;
        }
        let cfg = IdentifierConfig {
            eig_min: 0.5 * (l[0].max(0.0) + l[1]),
            eig_max: 0.5 * (l[1] + l[2]),
            ..base_config(s)
        };
        return Identifier::new(&cfg).unwrap();
    }
    panic!("no seed gives separated eigenvalues");
}

fn loss(id: &mut Identifier, p: &Point, w: &Wae) -> f64 {
    id.evaluate_wae(&p.q, &p.qd, &p.qdd, &p.tau).dot(w)
}

/// (name, range) of W1, b1, W2, b2 in a network's parameter vector.
fn layers(id: &Identifier, net: Net) -> Vec<(&'static str, std::ops::Range<usize>)> {
    let m = id.net(net).unwrap();
    let (p, h, o) = (m.inputs(), m.hidden(), m.outputs());
    let b1 = h * p;
    let w2 = b1 + h;
    let b2 = w2 + o * h;
    vec![
        ("W1", 0..b1),
        ("b1", b1..w2),
        ("W2", w2..b2),
        ("b2", b2..b2 + o),
    ]
}

/// Which (term, net) pairs have a structurally non-zero gradient.
fn depends(term: &str, net: Net, layer: &str) -> bool {
    match (term, net) {
        ("e1", _) => true,
        // Ṁ̂ does not depend on the M-net's output biases.
        ("e2" | "e3", Net::M) => layer != "b2",
        ("e2" | "e3", Net::C) => true,
        ("e4", Net::M) => true,
        _ => false,
    }
}

#[test]
fn wae_gradients_match_finite_differences_for_every_term_net_and_layer() {
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let mut worst: f64 = 0.0;
    for trial in 0..3 {
        let p = Point {
            q: vec3(&mut rng, [0.0, 0.65, 0.3], 0.5),
            qd: vec3(&mut rng, [0.0; 3], 1.5),
            qdd: vec3(&mut rng, [0.0; 3], 10.0),
            tau: vec3(&mut rng, [0.0; 3], 0.05),
        };
        let mut id = identifier_with_active_e4(10 + trial, &p);
        let eps = id.evaluate_wae(&p.q, &p.qd, &p.qdd, &p.tau);
        assert!(
            eps.rows(9, 3).iter().filter(|x| **x != 0.0).count() == 2,
            "e4 must be active on two eigenvalues: {eps}"
        );
        for (term, at) in TERMS {
            let mut w = Wae::zeros();
            for k in 0..3 {
                w[at + k] = 2.0 * rng.random::<f64>() - 1.0;
            }
            id.zero_grads();
            id.evaluate_wae(&p.q, &p.qd, &p.qdd, &p.tau);
            id.accumulate_gradient(&w);
            for net in Net::ALL {
                let analytic = id.net(net).unwrap().grad().to_vec();
                let h = 1e-6;
                let fd: Vec<f64> = (0..analytic.len())
                    .map(|i| {
                        let p0 = id.net(net).unwrap().params()[i];
                        id.net_mut(net).unwrap().params_mut()[i] = p0 + h;
                        let lp = loss(&mut id, &p, &w);
                        id.net_mut(net).unwrap().params_mut()[i] = p0 - h;
                        let lm = loss(&mut id, &p, &w);
                        id.net_mut(net).unwrap().params_mut()[i] = p0;
                        (lp - lm) / (2.0 * h)
                    })
                    .collect();
                for (layer, r) in layers(&id, net) {
                    let (a, f) = (&analytic[r.clone()], &fd[r]);
                    let what = format!("{term} {}-net {layer} (trial {trial})", net.name());
                    if !depends(term, net, layer) {
                        assert!(a.iter().all(|g| *g == 0.0), "{what}: {a:?}");
                        assert!(f.iter().all(|g| g.abs() < 1e-7), "{what}: fd {f:?}");
                        continue;
                    }
                    let num: f64 = a.iter().zip(f).map(|(x, y)| (x - y).powi(2)).sum();
                    let den: f64 = f.iter().map(|y| y * y).sum();
                    assert!(den > 1e-12, "{what}: gradient vanishes, test is vacuous");
                    let rel = (num / den).sqrt();
                    worst = worst.max(rel);
                    assert!(rel < 1e-6, "{what}: relative error {rel:e}");
                }
            }
        }
    }
    crate::errln!("worst relative FD error over all terms, nets and layers: {worst:e}");
}

#[test]
fn mass_derivative_matches_finite_differences_along_qd() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for trial in 0..5 {
        let mut id = Identifier::new(&base_config(trial)).unwrap();
        let q = vec3(&mut rng, [0.0, 0.65, 0.3], 0.5);
        let qd = vec3(&mut rng, [0.0; 3], 2.0);
        let mdot = id.mass_derivative(&q, &qd);
        let h = 1e-6;
        let fd = (id.mass(&(q + qd * h)) - id.mass(&(q - qd * h))) / (2.0 * h);
        let rel = (mdot - fd).norm() / fd.norm();
        assert!(rel < 1e-6, "Ṁ̂ rel err {rel:e}");
        assert_eq!(mdot, mdot.transpose());
    }
}
