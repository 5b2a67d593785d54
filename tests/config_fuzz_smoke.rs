//! Property-based smoke of the config parser, the CI-sized cousin of the `config` fuzz target in
//! `tests/fuzz/`: random TOML-ish text and random values for every real key never panic, and
//! every refusal names a line (syntax, types, unknown keys) or a field (values out of range).

use omnid::config::{Config, ConfigError};
use proptest::prelude::*;

/// Check one parse: a refusal is one line that names a line or a field.
fn check(text: &str) -> Result<Config, ConfigError> {
    let result = Config::from_toml(text, "smoke.toml");
    if let Err(e) = &result {
        let msg = e.to_string();
        assert!(!msg.contains('\n'), "not one line: {msg}");
        match e {
            ConfigError::Parse { message, .. } => {
                assert!(message.starts_with("line "), "names no line: {msg}\n{text}")
            }
            ConfigError::Invalid { field, .. } => {
                assert!(!field.is_empty() && msg.contains(field.as_str()), "{msg}")
            }
            ConfigError::Read { .. } => panic!("from_toml reads no file: {msg}"),
        }
    }
    result
}

/// `(line index, section.key)` of every key of the default config, with the default's lines.
fn default_keys() -> (Vec<String>, Vec<(usize, String)>) {
    let lines: Vec<String> = Config::default_toml().lines().map(String::from).collect();
    let mut section = String::new();
    let mut keys = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        if let Some(s) = line.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
            section = s.to_string();
        } else if let Some((key, _)) = line.split_once(" = ") {
            keys.push((i, format!("{section}.{key}")));
        }
    }
    (lines, keys)
}

/// A TOML value of any type, in or out of every field's range.
fn value() -> impl Strategy<Value = String> {
    let float = prop_oneof![
        any::<f64>().prop_map(|v| format!("{v:?}")),
        (-1e4f64..1e4).prop_map(|v| format!("{v:?}")),
        Just("nan".to_string()),
        Just("-inf".to_string()),
        Just("0.0".to_string()),
        Just("-0.0".to_string()),
    ];
    let scalar = prop_oneof![
        float.clone(),
        any::<i64>().prop_map(|v| v.to_string()),
        (0i64..200).prop_map(|v| v.to_string()),
        any::<bool>().prop_map(|v| v.to_string()),
        "[a-z@:.0-9 -]{0,12}".prop_map(|s| format!("{s:?}")),
    ];
    prop_oneof![
        4 => scalar.clone(),
        2 => proptest::collection::vec(float, 0..5).prop_map(|v| format!("[{}]", v.join(", "))),
        1 => proptest::collection::vec(scalar, 0..4).prop_map(|v| format!("[{}]", v.join(", "))),
        1 => Just("{}".to_string()),
        1 => Just("1979-05-27T07:32:00Z".to_string()),
    ]
}

/// Fragments that TOML (and broken TOML) is made of.
fn toml_ish() -> impl Strategy<Value = String> {
    let piece = prop_oneof![
        Just("[sim]".to_string()),
        Just("[control]".to_string()),
        Just("[[device]]".to_string()),
        Just("[kalman".to_string()),
        Just("\n".to_string()),
        Just("\r\n".to_string()),
        Just(" = ".to_string()),
        Just("=".to_string()),
        Just("\"".to_string()),
        Just("'''".to_string()),
        Just("# ü comment é\n".to_string()),
        Just(",".to_string()),
        Just("[".to_string()),
        Just("]".to_string()),
        Just("{".to_string()),
        Just("}".to_string()),
        Just(".".to_string()),
        Just("seed".to_string()),
        Just("omega_n".to_string()),
        Just("faults".to_string()),
        "[a-z_]{1,10}",
        value(),
        any::<char>().prop_map(String::from),
    ];
    proptest::collection::vec(piece, 0..40).prop_map(|v| v.concat())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    #[test]
    fn random_toml_ish_text_never_panics(text in toml_ish()) {
        let _ = check(&text);
    }

    #[test]
    fn random_values_for_real_keys_are_accepted_or_named(pick in any::<prop::sample::Index>(),
                                                         v in value()) {
        let (mut lines, keys) = default_keys();
        let (at, key) = &keys[pick.index(keys.len())];
        let (name, _) = lines[*at].split_once(" = ").unwrap();
        lines[*at] = format!("{name} = {v}");
        let text = lines.join("\n");
        match check(&text) {
            Ok(cfg) => cfg.validate().unwrap(),
            Err(ConfigError::Parse { message, .. }) => {
                // A type error points at the line that was changed.
                let line = format!("line {} ", at + 1);
                prop_assert!(message.starts_with(&line), "`{key} = {v}`: {message}");
            }
            Err(ConfigError::Invalid { field, .. }) => {
                // Range errors name the field that was changed (its element, or the group of
                // fields checked together, like `model.k1..k7`).
                let section = &key[..=key.find('.').unwrap()];
                prop_assert!(field.starts_with(section), "`{key} = {v}`: field `{field}`");
            }
            Err(e) => prop_assert!(false, "{e}"),
        }
    }
}

#[test]
fn every_default_key_is_reached() {
    let (_, keys) = default_keys();
    assert!(keys.len() > 40, "only {} keys found", keys.len());
    assert!(keys.iter().any(|(_, k)| k == "control.omega_n"));
}
