//! A configuration value's error and the checks every section uses. It depends on no other
//! module of the crate (but the leaves `text`, `toml_place` and `input`), so each component can define and validate its own section beside its
//! code while `config` only gathers the sections (no import cycle between them).

use serde::Deserialize;
use std::fmt::Display;
use thiserror::Error;

/// Why a configuration was refused: the file could not be read, was not valid TOML for the
/// schema, or a value is out of its range.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read (or the operator stopped the read: see
    /// [`is_stopped`](Self::is_stopped)).
    #[error("cannot read config {path}: {source}")]
    Read {
        /// The file, as given.
        path: String,
        /// What the read reported.
        source: std::io::Error,
    },
    /// Not TOML, or a key, type or table the schema does not have.
    #[error("config {path}: {message}")]
    Parse {
        /// The file, as given (or the origin named by the caller).
        path: String,
        /// The parser's message, with the line and column when it has them.
        message: String,
    },
    /// A value outside what its field allows.
    #[error("config: `{field}` = {} is out of range: allowed {allowed}", crate::text::cut(&crate::text::number(.value)))]
    Invalid {
        /// Dotted key of the field, `section.key` (`control.omega_n`).
        field: String,
        /// The value as it was given.
        value: String,
        /// The allowed range or values, in words (`0.1 ..= 200 rad/s`).
        allowed: String,
    },
    /// A value outside what its field allows, in a file: where it is.
    #[error("config {path}: {}`{field}` = {} is out of range: allowed {allowed}",
        .place.as_ref().map(|p| format!("{p}: ")).unwrap_or_default(), crate::text::cut(&crate::text::number(.value)))]
    InvalidIn {
        /// The file, as given.
        path: String,
        /// The value's line and column (None when the file does not hold it: a default).
        place: Option<Box<crate::toml_place::Place>>,
        /// As [`ConfigError::Invalid`].
        field: String,
        /// The value as it was given.
        value: String,
        /// The allowed range or values.
        allowed: String,
    },
}

impl ConfigError {
    /// This error told in file `path` whose text is `text`: a value out of range gets the file
    /// and the value's place.
    pub fn in_file(self, path: &str, text: &str) -> ConfigError {
        match self {
            ConfigError::Invalid {
                field,
                value,
                allowed,
            } => ConfigError::InvalidIn {
                path: path.to_string(),
                place: crate::toml_place::place_of(text, &field, crate::toml_place::Part::Value)
                    .map(Box::new),
                field,
                value,
                allowed,
            },
            other => other,
        }
    }

    /// Reading the file was stopped by the operator.
    pub fn is_stopped(&self) -> bool {
        matches!(self, ConfigError::Read { source, .. } if crate::input::is_stopped(source))
    }
}

/// `field` = `value` is not allowed; `allowed` says what is.
pub(crate) fn invalid(
    field: impl Into<String>,
    value: impl Display,
    allowed: impl Into<String>,
) -> ConfigError {
    ConfigError::Invalid {
        field: field.into(),
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

/// A finite `v` in `lo ..= hi`.
pub(crate) fn in_range(
    field: &str,
    v: f64,
    lo: f64,
    hi: f64,
    allowed: &str,
) -> Result<(), ConfigError> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(invalid(field, v, allowed))
    }
}

/// A finite `v` > 0.
pub(crate) fn positive(field: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(field, v, "finite and > 0"))
    }
}

/// An integer (or any ordered value) in `lo ..= hi`.
pub(crate) fn int_in<T: PartialOrd + Display>(
    field: &str,
    v: T,
    lo: T,
    hi: T,
    allowed: &str,
) -> Result<(), ConfigError> {
    if v >= lo && v <= hi {
        Ok(())
    } else {
        Err(invalid(field, v, allowed))
    }
}

/// `check` on every element, each named `field[i]`.
pub(crate) fn each<const N: usize>(
    field: &str,
    v: &[f64; N],
    check: impl Fn(&str, f64) -> Result<(), ConfigError>,
) -> Result<(), ConfigError> {
    for (i, x) in v.iter().enumerate() {
        check(&format!("{field}[{i}]"), *x)?;
    }
    Ok(())
}

/// `[T; N]` from exactly N values. serde's own impl for arrays stops after N elements without
/// looking further, so with `toml` a longer array was silently cut to its first N; every
/// fixed-length field of a config or stored-state file takes its values through this
/// (`#[serde(deserialize_with = "crate::config_check::exact")]`).
pub(crate) fn exact<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    let values = Vec::<T>::deserialize(d)?;
    let got = values.len();
    values
        .try_into()
        .map_err(|_| serde::de::Error::invalid_length(got, &ArrayOf(N)))
}

/// What [`exact`] expects, for its message.
struct ArrayOf(usize);

impl serde::de::Expected for ArrayOf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "an array of exactly {} values", self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_name_the_field_and_refuse_non_finite_values() {
        assert!(in_range("a.b", 0.5, 0.0, 1.0, "0 ..= 1").is_ok());
        for bad in [f64::NAN, f64::INFINITY, -0.1, 1.1] {
            let e = in_range("a.b", bad, 0.0, 1.0, "0 ..= 1").unwrap_err();
            assert!(e.to_string().contains("`a.b`"), "{e}");
        }
        assert!(positive("p", 0.0).is_err() && positive("p", f64::NAN).is_err());
        assert!(int_in("n", 7u32, 1, 5, "1 ..= 5").is_err());
        let e = each("v", &[1.0, -1.0], |f, v| {
            in_range(f, v, 0.0, 2.0, "0 ..= 2")
        })
        .unwrap_err();
        assert!(e.to_string().contains("`v[1]` = -1"), "{e}");
    }

    #[test]
    fn a_huge_value_is_quoted_cut() {
        let e = invalid("k", "é".repeat(10_000), "short");
        let text = e.to_string();
        assert!(text.len() < 400 && text.contains("(20000 bytes)"), "{text}");
    }
}
