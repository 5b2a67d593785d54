//! The CI-sized cousins of the `protocol` and `scene` fuzz targets in `tests/fuzz/`: random
//! bytes, random requests built from the protocol's own ops and fields, and random scene
//! files never panic, and every refusal is one line of bounded length (a scene's names it).

use omnid::haptics::scene::parse_scene;
use omnid::transport::json::decode_request;
use proptest::prelude::*;

fn refusal_ok(e: &str) {
    assert!(!e.contains('\n'), "multi-line refusal: {e}");
    assert!(e.len() < 2048, "refusal of {} bytes", e.len());
}

/// A JSON value of any kind, small.
fn value() -> impl Strategy<Value = serde_json::Value> {
    prop_oneof![
        Just(serde_json::Value::Null),
        any::<bool>().prop_map(serde_json::Value::from),
        any::<i64>().prop_map(serde_json::Value::from),
        any::<f64>().prop_map(|f| serde_json::json!(f)),
        "[ -~]{0,12}".prop_map(serde_json::Value::from),
        prop::collection::vec(any::<f64>(), 0..5).prop_map(|v| serde_json::json!(v)),
    ]
}

const OPS: &[&str] = &[
    "hello",
    "stream",
    "status",
    "lease",
    "release",
    "mode",
    "hold",
    "free",
    "servo_jp",
    "servo_jf",
    "servo_cf",
    "effect",
    "passivity",
    "controller",
    "adapt",
    "weights_save",
    "weights_load",
    "weights_reset",
    "record_start",
    "record_stop",
    "shutdown",
    "fly",
];
const FIELDS: &[&str] = &[
    "id",
    "protocol",
    "rate_hz",
    "fallback",
    "mode",
    "trajectory",
    "seq",
    "q",
    "tau",
    "force",
    "ttl_ms",
    "slot",
    "effect",
    "on",
    "controller",
    "path",
    "name",
    "type",
    "extra",
];

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        if let Err(e) = decode_request(&bytes) {
            refusal_ok(&e);
        }
    }

    #[test]
    fn requests_of_real_ops_with_any_fields(
        op in prop::sample::select(OPS),
        fields in prop::collection::vec((prop::sample::select(FIELDS), value()), 0..5),
    ) {
        let mut v = serde_json::json!({ "op": op });
        for (k, x) in fields {
            v[k] = x;
        }
        if let Err(e) = decode_request(v.to_string().as_bytes()) {
            refusal_ok(&e);
        }
    }

    #[test]
    fn scenes(
        kinds in prop::collection::vec(
            prop::sample::select(&["spring", "damper", "plane", "box", "constant", "fly"][..]),
            0..4,
        ),
        numbers in prop::collection::vec(-1e6f64..1e6, 12),
        junk in "[ -~\n]{0,40}",
    ) {
        let mut text = String::new();
        for (i, kind) in kinds.iter().enumerate() {
            let n = |k: usize| numbers[(i * 3 + k) % numbers.len()];
            text += &format!(
                "[[effect]]\ntype = \"{kind}\"\ncenter_mm = [{}, {}, {}]\n\
                 stiffness_n_per_mm = {}\ndamping_n_s_per_m = {}\n",
                n(0), n(1), n(2), n(3).abs() * 1e-6, n(4).abs() * 1e-4
            );
        }
        text += &junk;
        if let Err(e) = parse_scene(&text, "smoke.toml") {
            refusal_ok(&e);
            prop_assert!(e.contains("smoke.toml"), "{}", e);
        }
    }
}
