//! Property-based smoke of the config parser, the CI-sized cousin of the `config` fuzz target in
//! `tests/fuzz/`: random TOML-ish text and random values for every real key never panic, and
//! every refusal names a line (syntax, types, unknown keys) or a field (values out of range, at
//! its line when the file holds it),
//! and an accepted config holds every array exactly as written (nothing cut off).

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
            ConfigError::Invalid { .. } => panic!("from_toml names the file: {msg}"),
            ConfigError::InvalidIn { field, place, .. } => {
                assert!(
                    !field.is_empty() && msg.contains(field.as_str()) && msg.contains("smoke.toml"),
                    "{msg}"
                );
                // A value written in the file is told at its line.
                if omnid::toml_place::place_of(text, field, omnid::toml_place::Part::Value)
                    .is_some()
                {
                    let p = place.as_ref().expect("a written value has a place");
                    assert!(msg.contains(&format!("line {}, column", p.line)), "{msg}");
                }
            }
            ConfigError::Read { .. } => panic!("from_toml reads no file: {msg}"),
        }
    }
    result
}

/// Every array of `written` (the parsed input text) is in `kept` (the accepted config,
/// serialised) with the same number of values: a value more or fewer is refused, never cut.
fn arrays_kept(written: &toml::Value, kept: &toml::Value, at: &str) -> Result<(), String> {
    match (written, kept) {
        (toml::Value::Table(w), toml::Value::Table(k)) => {
            for (key, value) in w {
                if let Some(kv) = k.get(key) {
                    arrays_kept(value, kv, &format!("{at}.{key}"))?;
                }
            }
            Ok(())
        }
        (toml::Value::Array(w), toml::Value::Array(k)) if w.len() != k.len() => Err(format!(
            "`{}` was written with {} values and accepted as {}",
            at.trim_start_matches('.'),
            w.len(),
            k.len()
        )),
        _ => Ok(()),
    }
}

/// The accepted `cfg` keeps every array of `text`.
fn check_arrays(text: &str, cfg: &Config) -> Result<(), String> {
    let written: toml::Value = toml::from_str(text).map_err(|e| e.to_string())?;
    let kept = toml::Value::try_from(cfg).map_err(|e| e.to_string())?;
    arrays_kept(&written, &kept, "")
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
        if let Ok(cfg) = check(&text) {
            prop_assert_eq!(check_arrays(&text, &cfg), Ok(()));
        }
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
            Ok(cfg) => {
                cfg.validate().unwrap();
                prop_assert_eq!(check_arrays(&text, &cfg), Ok(()), "`{} = {}`", key, v);
            }
            Err(ConfigError::Parse { message, .. }) => {
                // A type error points at the line that was changed.
                let line = format!("line {}, ", at + 1);
                prop_assert!(message.starts_with(&line), "`{key} = {v}`: {message}");
            }
            Err(ConfigError::InvalidIn { field, place, allowed, .. }) => {
                // Range errors name the field that was changed (its element, or the group of
                // fields checked together, like `model.k1..k7`), at its line when it is that
                // field; a value checked against another section's (the reference's centre
                // inside the joint limits) names the changed key in what is allowed.
                let section = &key[..=key.find('.').unwrap()];
                let base = key.split('[').next().unwrap();
                prop_assert!(
                    field.starts_with(section) || allowed.contains(base),
                    "`{key} = {v}`: field `{field}`, allowed `{allowed}`"
                );
                if &field == key {
                    prop_assert_eq!(place.map(|p| p.line), Some(at + 1), "`{} = {}`", key, v);
                }
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

/// Every fixed-length array of the config, one value too many or too few: refused on its line,
/// never cut or padded (a list such as `inject.faults` takes any length and keeps it).
#[test]
fn every_array_refuses_a_value_more_or_less() {
    let (lines, keys) = default_keys();
    let mut arrays = 0;
    for (at, key) in &keys {
        let (name, value) = lines[*at].split_once(" = ").unwrap();
        let value = value.split(" #").next().unwrap().trim();
        let Some(inner) = value.strip_prefix('[').and_then(|v| v.strip_suffix(']')) else {
            continue;
        };
        let values: Vec<&str> = inner.split(',').map(str::trim).collect();
        if inner.trim().is_empty() {
            continue;
        }
        arrays += 1;
        let longer = [&values[..], &values[values.len() - 1..]].concat();
        let shorter = &values[..values.len() - 1];
        for changed in [&longer[..], shorter] {
            let mut edited = lines.clone();
            edited[*at] = format!("{name} = [{}]", changed.join(", "));
            let text = edited.join("\n");
            match check(&text) {
                Ok(cfg) => assert_eq!(check_arrays(&text, &cfg), Ok(()), "{key}"),
                Err(ConfigError::Parse { message, .. }) => assert!(
                    message.starts_with(&format!("line {}, ", at + 1))
                        && message.contains(&format!("length {}", changed.len())),
                    "{key}: {message}"
                ),
                Err(e) => panic!("{key} with {} values: {e}", changed.len()),
            }
        }
    }
    assert!(arrays >= 25, "only {arrays} arrays found");
}

/// The `config` fuzz target's seed `tests/fuzz/seeds/config/default.toml` is what
/// `omnid config --print-default` prints today (tests/fuzz/README.md): a key added or a comment
/// changed in the code without the seed regenerated fails here, not months later in a fuzz run
/// seeded with an older default.
#[test]
fn the_fuzz_seeds_default_config_is_what_print_default_prints() {
    let out = crate::common::run_ok(&["config", "--print-default"]);
    let seed = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz/seeds/config/default.toml");
    let kept = std::fs::read(&seed).unwrap();
    assert!(
        kept == out.stdout,
        "{} differs from `omnid config --print-default` ({} bytes kept, {} printed); regenerate \
         it: cargo run -q -- config --print-default > tests/fuzz/seeds/config/default.toml",
        seed.display(),
        kept.len(),
        out.stdout.len()
    );
}
