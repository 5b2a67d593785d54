//! The config parser on arbitrary UTF-8: never a panic, every error names a field or a line, and
//! a config it accepts holds every array with as many values as written (none cut off) and
//! serialises and parses back to itself. Each line also goes through the
//! fault-spec parser (`--inject`), which the config reaches only at the end of validation.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::config::{Config, ConfigError};
use omnid::device::inject::Fault;

/// Every array of `written` is in `kept` with the same number of values.
fn arrays_kept(written: &toml::Value, kept: &toml::Value, at: &str) {
    match (written, kept) {
        (toml::Value::Table(w), toml::Value::Table(k)) => {
            for (key, value) in w {
                if let Some(kv) = k.get(key) {
                    arrays_kept(value, kv, &format!("{at}.{key}"));
                }
            }
        }
        (toml::Value::Array(w), toml::Value::Array(k)) => assert_eq!(
            w.len(),
            k.len(),
            "`{at}` accepted with another number of values"
        ),
        _ => {}
    }
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    match Config::from_toml(text, "fuzz.toml") {
        Ok(cfg) => {
            cfg.validate().expect("an accepted config validates");
            let written: toml::Value = toml::from_str(text).expect("accepted TOML parses");
            let kept = toml::Value::try_from(&cfg).expect("an accepted config serialises");
            arrays_kept(&written, &kept, "");
            let again = toml::to_string(&cfg).expect("an accepted config serialises");
            let back = Config::from_toml(&again, "again.toml").expect("and parses back");
            assert_eq!(back, cfg, "round trip changed the config:\n{again}");
        }
        Err(ConfigError::Parse { message, .. }) => {
            assert!(!message.contains('\n'), "multi-line message: {message}");
            assert!(
                message.starts_with("line "),
                "parse error without a line: {message}"
            );
        }
        Err(ConfigError::InvalidIn { field, .. }) => assert!(!field.is_empty()),
        Err(e @ ConfigError::Invalid { .. }) => panic!("from_toml names its file: {e}"),
        Err(e @ ConfigError::Read { .. }) => panic!("from_toml reads no file: {e}"),
    }
    for line in text.lines() {
        if let Ok(f) = line.parse::<Fault>() {
            let values = match f {
                Fault::Disconnect { at_s } | Fault::Nan { at_s } => [at_s, 0.0],
                Fault::Stall { at_s, ms } | Fault::Slow { at_s, ms } => [at_s, ms],
                Fault::Corrupt { probability } => [probability, 1.0 - probability],
                Fault::EncoderJump { at_s, .. } => [at_s, 0.0],
            };
            assert!(
                values.iter().all(|v| v.is_finite() && *v >= 0.0),
                "{line:?} -> {f:?}"
            );
        }
    }
});
