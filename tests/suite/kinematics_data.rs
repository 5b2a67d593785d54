//! Forward kinematics against the real Geomagic Touch recording shipped in `data/`
//! (data/README.md; the formula is docs/DESIGN.md §4.1).

use omnid::omni::kinematics::from_ros;
use omnid::omni::{tip_position_mm, Geometry};

#[test]
fn forward_kinematics_reproduces_the_recorded_tip() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/touch-2016-joint-and-tip.csv"
    );
    let mut reader = csv::Reader::from_path(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let headers = reader.headers().unwrap().clone();
    let col = |n: &str| headers.iter().position(|h| h == n).unwrap();
    let (w, s, e) = (col("waist"), col("shoulder"), col("elbow"));
    let (x, y, z) = (col("x_mm"), col("y_mm"), col("z_mm"));
    let g = Geometry::default();
    let mut sq = [0.0f64; 3];
    let mut n = 0usize;
    for rec in reader.records() {
        let rec = rec.unwrap();
        let f = |i: usize| rec[i].parse::<f64>().unwrap();
        let tip = tip_position_mm(&g, &from_ros(f(w), f(s), f(e)));
        for (k, c) in [x, y, z].into_iter().enumerate() {
            sq[k] += (tip[k] - f(c)).powi(2);
        }
        n += 1;
    }
    assert_eq!(n, 2743);
    let rms = sq.map(|v| (v / n as f64).sqrt());
    eprintln!("tip RMS error per axis (mm): {rms:?}");
    for (axis, r) in ["x", "y", "z"].iter().zip(rms) {
        assert!(r <= 0.05, "{axis}: {r} mm RMS");
    }
}
