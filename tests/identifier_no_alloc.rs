//! The identifier's per-tick path (update, predict, the model accessors) must not allocate:
//! a counting allocator watches this thread while it runs.

use nalgebra::Vector3;
use omnid::identifier::{Identifier, IdentifierConfig};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    static WATCH: Cell<bool> = const { Cell::new(false) };
    static COUNT: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // try_with: the thread-locals may be gone while a thread shuts down.
        let _ = WATCH.try_with(|w| {
            if w.get() {
                COUNT.with(|c| c.set(c.get() + 1));
            }
        });
        System.alloc(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

fn allocations(f: impl FnOnce()) -> usize {
    COUNT.with(|c| c.set(0));
    WATCH.with(|w| w.set(true));
    f();
    WATCH.with(|w| w.set(false));
    COUNT.with(|c| c.get())
}

fn tick_inputs(k: usize) -> [Vector3<f64>; 4] {
    let t = k as f64 * 1e-3;
    let q = Vector3::new(
        0.4 * t.sin(),
        0.65 + 0.3 * (1.3 * t).sin(),
        0.3 + 0.3 * t.cos(),
    );
    let qd = Vector3::new(0.4 * t.cos(), 0.39 * (1.3 * t).cos(), -0.3 * t.sin());
    let qdd = Vector3::new(-0.4 * t.sin(), -0.5 * (1.3 * t).sin(), -0.3 * t.cos());
    let tau = Vector3::new(0.01 * t.sin(), 0.03, -0.05 * q[2].sin());
    [q, qd, qdd, tau]
}

#[test]
fn update_and_accessors_do_not_allocate() {
    for cfg in [
        IdentifierConfig::default(),
        IdentifierConfig {
            friction_net: false,
            hidden: 5,
            // Tight eigenvalue bounds: the eigen-decomposition path runs every tick.
            eig_min: 3e-3,
            eig_max: 3.1e-3,
            ..IdentifierConfig::default()
        },
    ] {
        let mut id = Identifier::new(&cfg).unwrap();
        let mut sink = 0.0;
        let n = allocations(|| {
            for k in 0..2000 {
                let [q, qd, qdd, tau] = tick_inputs(k);
                let tau_hat = id.update(&q, &qd, &qdd, &tau, 1e-3);
                let v = id.inverse_dynamics(&q, &qd, &qdd);
                sink += tau_hat.sum() + v.sum() + id.last_errors().modified_norm;
                sink += id.mass(&q).sum() + id.coriolis(&q, &qd).sum();
                sink += id.gravity(&q).sum() + id.friction(&qd).sum();
                sink += id.weights_norm()[0] + id.weight_change_norm();
            }
        });
        assert!(sink.is_finite());
        assert!(id.healthy());
        assert_eq!(
            n, 0,
            "{n} allocations in 2000 ticks (hidden {})",
            cfg.hidden
        );
    }
}
