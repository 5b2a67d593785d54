//! Weights file: JSON with the network sizes, the friction-net flag, each network's input and
//! output scaling and all parameters. Loading refuses, with a message naming both sides, a file
//! that does not fit the configured networks; bad, truncated or non-finite content is an
//! error, never a panic.
//!
//! The scalings travel with the weights (a network's function is its weights *and* its
//! scaling), so a loaded network keeps the scaling it was trained with, whatever the
//! configuration's scaling keys say; those only shape fresh networks.

use super::adaptive::{Identifier, Net};
use super::mlp::{Mlp, NetScaling};
use super::settings::IdentifierConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// The largest weights file read: 16 MiB, far above the biggest networks the configuration
/// allows (4 × 256 hidden units, under 1 MiB of JSON).
pub(crate) const MAX_WEIGHTS_BYTES: u64 = 16 << 20;

/// Value of the `format` field.
pub(crate) const FORMAT: &str = "omnid-identifier-weights";
/// Current `version`.
pub(crate) const VERSION: u32 = 1;

/// Why a weights file could not be read, used or written.
#[derive(Debug, Error)]
pub enum WeightsError {
    /// The file could not be read (or the operator stopped the read).
    #[error("cannot read weights file {path}: {source}")]
    Read {
        /// The file, as given.
        path: String,
        /// What the read reported.
        source: std::io::Error,
    },
    /// The file could not be written.
    #[error("weights file: {0}")]
    Write(#[from] crate::output::OutputError),
    /// Not JSON, or not the weights file's fields.
    #[error("weights file {path} is not valid weights JSON: {message}")]
    Parse {
        /// The file (or origin) named in the message.
        path: String,
        /// The parser's message.
        message: String,
    },
    /// Another format name or version than this build writes.
    #[error("weights file {path} has format \"{format}\" version {version}; expected \"{FORMAT}\" version {VERSION}")]
    Format {
        /// The file (or origin) named in the message.
        path: String,
        /// The file's `format`.
        format: String,
        /// The file's `version`.
        version: u32,
    },
    /// The networks do not match the configuration (hidden size, friction network).
    #[error("weights file {path} does not fit the configuration: {message}")]
    Mismatch {
        /// The file (or origin) named in the message.
        path: String,
        /// What differs.
        message: String,
    },
    /// The file contradicts itself or holds a network that cannot be built (sizes against
    /// parameter counts, scalings, …).
    #[error("weights file {path} is inconsistent: {message}")]
    Invalid {
        /// The file (or origin) named in the message.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// A weight is NaN or infinite: such weights are never saved.
    #[error("refusing to save weights: {message}")]
    NotFinite {
        /// Which network and entry.
        message: String,
    },
}

impl WeightsError {
    /// Reading the file was stopped by the operator.
    pub(crate) fn is_stopped(&self) -> bool {
        matches!(self, WeightsError::Read { source, .. } if crate::input::is_stopped(source))
    }
}

/// One network's sizes, scaling and parameters (layout of `Mlp::params`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NetWeights {
    pub(crate) net: Net,
    pub(crate) inputs: usize,
    pub(crate) hidden: usize,
    pub(crate) outputs: usize,
    pub(crate) scaling: NetScaling,
    pub(crate) params: Vec<f64>,
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WeightsFile {
    pub(crate) format: String,
    pub(crate) version: u32,
    pub(crate) hidden: usize,
    pub(crate) friction_net: bool,
    pub(crate) nets: Vec<NetWeights>,
}

impl WeightsFile {
    /// Snapshot of an identifier's networks.
    pub(crate) fn from_identifier(id: &Identifier) -> Self {
        let nets = Net::ALL
            .iter()
            .filter_map(|&n| id.net(n).map(|m| (n, m)))
            .map(|(net, m)| NetWeights {
                net,
                inputs: m.inputs(),
                hidden: m.hidden(),
                outputs: m.outputs(),
                scaling: m.scaling().clone(),
                params: m.params().to_vec(),
            })
            .collect();
        WeightsFile {
            format: FORMAT.to_string(),
            version: VERSION,
            hidden: id.config().hidden,
            friction_net: id.config().friction_net,
            nets,
        }
    }

    /// Parse and check internal consistency; `origin` names the source in messages.
    pub fn from_json(text: &str, origin: &str) -> Result<Self, WeightsError> {
        let w: WeightsFile = serde_json::from_str(text).map_err(|e| WeightsError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        if w.format != FORMAT || w.version != VERSION {
            return Err(WeightsError::Format {
                path: origin.to_string(),
                format: w.format,
                version: w.version,
            });
        }
        w.check_consistent(origin)?;
        Ok(w)
    }

    fn check_consistent(&self, origin: &str) -> Result<(), WeightsError> {
        let invalid = |message: String| WeightsError::Invalid {
            path: origin.to_string(),
            message,
        };
        let expected: Vec<Net> = Net::ALL
            .into_iter()
            .filter(|&n| n != Net::F || self.friction_net)
            .collect();
        let got: Vec<Net> = self.nets.iter().map(|n| n.net).collect();
        if got != expected {
            return Err(invalid(format!(
                "networks {got:?} listed, expected {expected:?} (friction_net = {})",
                self.friction_net
            )));
        }
        for nw in &self.nets {
            let name = nw.net.name();
            let (inputs, outputs) = nw.net.io();
            if (nw.inputs, nw.outputs) != (inputs, outputs) || nw.hidden != self.hidden {
                return Err(invalid(format!(
                    "{name}-net is {}-{}-{}, expected {inputs}-{}-{outputs}",
                    nw.inputs, nw.hidden, nw.outputs, self.hidden
                )));
            }
            let n = nw.hidden * (nw.inputs + 1) + nw.outputs * (nw.hidden + 1);
            if nw.params.len() != n {
                return Err(invalid(format!(
                    "{name}-net has {} parameters, a {}-{}-{} network has {n}",
                    nw.params.len(),
                    nw.inputs,
                    nw.hidden,
                    nw.outputs
                )));
            }
            if let Some(i) = nw.params.iter().position(|p| !p.is_finite()) {
                return Err(invalid(format!(
                    "{name}-net parameter {i} is {}",
                    nw.params[i]
                )));
            }
            // Finite is not enough: a weight this large saturates every neuron it feeds (a
            // trained network's are tens at most), and its predictions are torques no arm has.
            if let Some(i) = nw.params.iter().position(|p| p.abs() > MAX_PARAMETER) {
                return Err(invalid(format!(
                    "{name}-net parameter {i} is {:e}: allowed magnitude ≤ {MAX_PARAMETER:e} \
                     (a trained network's weights are tens at most)",
                    nw.params[i]
                )));
            }
            // Mlp::new checks the scaling's lengths and values.
            Mlp::new(nw.inputs, nw.hidden, nw.outputs, nw.scaling.clone())
                .map_err(|e| invalid(format!("{name}-net scaling: {e}")))?;
        }
        Ok(())
    }

    /// Refuse, naming both sides, weights that do not fit the configured networks.
    pub(crate) fn check_fits(
        &self,
        cfg: &IdentifierConfig,
        origin: &str,
    ) -> Result<(), WeightsError> {
        if self.hidden != cfg.hidden {
            return Err(WeightsError::Mismatch {
                path: origin.to_string(),
                message: format!(
                    "it has hidden = {} but the config has identifier.hidden = {}",
                    self.hidden, cfg.hidden
                ),
            });
        }
        if self.friction_net != cfg.friction_net {
            return Err(WeightsError::Mismatch {
                path: origin.to_string(),
                message: format!(
                    "it has friction_net = {} but the config has identifier.friction_net = {}",
                    self.friction_net, cfg.friction_net
                ),
            });
        }
        Ok(())
    }

    /// The file's JSON text (what `save` writes, without the final newline).
    pub fn to_json(&self) -> String {
        // Plain data with string keys: serialisation cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default()
    }
}

/// The largest weight magnitude a weights file may hold (the shipped pre-tuned networks'
/// largest is about 11).
const MAX_PARAMETER: f64 = 1e4;

/// Write the identifier's weights to `path`, whole (see [`crate::output`]: a failed write
/// leaves the old file; only a regular file or a new path is written).
pub(crate) fn save(id: &Identifier, path: &Path) -> Result<(), WeightsError> {
    let w = WeightsFile::from_identifier(id);
    for nw in &w.nets {
        if let Some(i) = nw.params.iter().position(|p| !p.is_finite()) {
            return Err(WeightsError::NotFinite {
                message: format!("{}-net parameter {i} is {}", nw.net.name(), nw.params[i]),
            });
        }
    }
    Ok(crate::output::write_bytes(
        path,
        (w.to_json() + "\n").as_bytes(),
    )?)
}

/// Read and check a weights file (without comparing it to a configuration): at most
/// [`MAX_WEIGHTS_BYTES`]; `stop` (the operator's) ends a wait on a pipe, without it only a
/// regular file is read (see [`crate::input::open`]).
pub(crate) fn load(
    path: &Path,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<WeightsFile, WeightsError> {
    let origin = path.display().to_string();
    let text = crate::input::read_capped(path, MAX_WEIGHTS_BYTES, stop).map_err(|source| {
        WeightsError::Read {
            path: origin.clone(),
            source,
        }
    })?;
    WeightsFile::from_json(&text, &origin)
}

impl Identifier {
    /// Take over the networks of `w` (which must fit this identifier's configuration); they
    /// become the σ-modification's anchor θ0.
    pub fn apply_weights(&mut self, w: &WeightsFile, origin: &str) -> Result<(), WeightsError> {
        w.check_fits(self.config(), origin)?;
        w.check_consistent(origin)?;
        let mut nets = Vec::with_capacity(w.nets.len());
        for nw in &w.nets {
            let mut mlp =
                Mlp::new(nw.inputs, nw.hidden, nw.outputs, nw.scaling.clone()).map_err(|e| {
                    WeightsError::Invalid {
                        path: origin.to_string(),
                        message: format!("{}-net: {e}", nw.net.name()),
                    }
                })?;
            mlp.set_params(&nw.params)
                .map_err(|e| WeightsError::Invalid {
                    path: origin.to_string(),
                    message: format!("{}-net: {e}", nw.net.name()),
                })?;
            nets.push((nw.net, mlp));
        }
        // Only now, with every network built, replace them: a failure leaves self untouched.
        for (net, mlp) in nets {
            self.replace_net(net, mlp);
        }
        self.set_anchor();
        Ok(())
    }

    /// An identifier for `cfg` with the weights of the file at `path` (`stop`: see `load`).
    pub fn from_weights_file(
        cfg: &IdentifierConfig,
        path: &Path,
        stop: Option<&Arc<AtomicBool>>,
    ) -> Result<Identifier, WeightsError> {
        let origin = path.display().to_string();
        let w = load(path, stop)?;
        w.check_fits(cfg, &origin)?;
        let mut id = Identifier::new(cfg).map_err(|e| WeightsError::Mismatch {
            path: origin.clone(),
            message: e.to_string(),
        })?;
        id.apply_weights(&w, &origin)?;
        Ok(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn ident(cfg: &IdentifierConfig) -> Identifier {
        Identifier::new(cfg).unwrap()
    }

    #[test]
    fn save_and_load_round_trip_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.json");
        let cfg = IdentifierConfig {
            seed: 9,
            ..IdentifierConfig::default()
        };
        let mut a = ident(&cfg);
        save(&a, &path).unwrap();
        // Different seed, then load: predictions must be identical.
        let mut b = ident(&IdentifierConfig {
            seed: 10,
            ..cfg.clone()
        });
        let q = Vector3::new(0.1, 0.7, 0.2);
        let qd = Vector3::new(0.3, -0.4, 0.5);
        let qdd = Vector3::new(2.0, 1.0, -3.0);
        assert_ne!(a.predict(&q, &qd, &qdd), b.predict(&q, &qd, &qdd));
        b.apply_weights(&load(&path, None).unwrap(), "w.json")
            .unwrap();
        assert_eq!(a.predict(&q, &qd, &qdd), b.predict(&q, &qd, &qdd));
        assert_eq!(b.weight_change_norm(), 0.0);
        let c = Identifier::from_weights_file(&cfg, &path, None).unwrap();
        assert_eq!(c.weights_norm(), a.weights_norm());
    }

    #[test]
    fn loaded_weights_keep_their_scaling() {
        let cfg = IdentifierConfig::default();
        let a = ident(&cfg);
        let w = WeightsFile::from_identifier(&a);
        let mut other = cfg.clone();
        other.q_scale = [1.0, 2.0, 3.0];
        let mut b = ident(&other);
        b.apply_weights(&w, "w").unwrap();
        assert_eq!(
            b.net(Net::G).unwrap().scaling(),
            a.net(Net::G).unwrap().scaling()
        );
    }

    #[test]
    fn mismatched_sizes_and_flags_are_refused_with_both_values() {
        let w = WeightsFile::from_identifier(&ident(&IdentifierConfig {
            hidden: 8,
            ..IdentifierConfig::default()
        }));
        let mut b = ident(&IdentifierConfig::default());
        let e = b
            .apply_weights(&w, "pretuned.json")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("pretuned.json")
                && e.contains("hidden = 8")
                && e.contains("identifier.hidden = 16"),
            "{e}"
        );
        let w = WeightsFile::from_identifier(&ident(&IdentifierConfig {
            friction_net: false,
            ..IdentifierConfig::default()
        }));
        let e = b.apply_weights(&w, "w.json").unwrap_err().to_string();
        assert!(e.contains("identifier.friction_net = true"), "{e}");
    }

    #[test]
    fn bad_files_are_errors_not_panics() {
        let good = WeightsFile::from_identifier(&ident(&IdentifierConfig::default())).to_json();
        // Truncated anywhere.
        for cut in [0, 1, good.len() / 3, good.len() / 2, good.len() - 2] {
            let e = WeightsFile::from_json(&good[..cut], "t.json").unwrap_err();
            assert!(matches!(e, WeightsError::Parse { .. }), "{e}");
            assert!(e.to_string().contains("t.json"));
        }
        // NaN is not JSON; a NaN saved by a careless tool arrives as null.
        let nan = good.replacen("\"params\": [", "\"params\": [NaN, ", 1);
        assert!(WeightsFile::from_json(&nan, "n").is_err());
        let null = good.replacen("\"params\": [", "\"params\": [null, ", 1);
        assert!(WeightsFile::from_json(&null, "n").is_err());
        let huge = good.replacen("\"params\": [", "\"params\": [1e999, ", 1);
        assert!(WeightsFile::from_json(&huge, "n").is_err());
        // A parameter too many.
        let extra = good.replacen("\"params\": [", "\"params\": [0.5, ", 1);
        let e = WeightsFile::from_json(&extra, "x.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("M-net has") && e.contains("parameters"), "{e}");
        // Wrong format tag, unknown keys, bad scaling.
        let e = WeightsFile::from_json(&good.replace(FORMAT, "other"), "f")
            .unwrap_err()
            .to_string();
        assert!(e.contains("\"other\""), "{e}");
        assert!(WeightsFile::from_json(&good.replacen("{", "{\"extra\": 1,", 1), "u").is_err());
        // Finite but absurd.
        let mut w = WeightsFile::from_json(&good, "g").unwrap();
        w.nets[2].params[3] = 1e300;
        let e = WeightsFile::from_json(&w.to_json(), "a")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("G-net parameter 3") && e.contains("magnitude"),
            "{e}"
        );
        let mut w = WeightsFile::from_json(&good, "g").unwrap();
        w.nets[1].scaling.in_scale[4] = -1.0;
        let e = WeightsFile::from_json(&w.to_json(), "s")
            .unwrap_err()
            .to_string();
        assert!(e.contains("C-net scaling"), "{e}");
        let e = load(Path::new("/nonexistent/w.json"), None).unwrap_err();
        assert!(matches!(e, WeightsError::Read { .. }));
    }

    #[test]
    fn non_finite_weights_are_not_saved() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = ident(&IdentifierConfig::default());
        a.net_mut(Net::C).unwrap().params_mut()[3] = f64::NAN;
        let e = save(&a, &dir.path().join("w.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("C-net parameter 3"), "{e}");
    }
}
