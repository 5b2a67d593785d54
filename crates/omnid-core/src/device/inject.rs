//! Fault injection: a wrapper around any device (and, for `nan@T`, `control::NanAfter`) that
//! makes the faults the safety layer must survive or stop on, at chosen device times.
//!
//! Specs (`--inject`, repeatable, or `[inject] faults = [...]`):
//! `disconnect@T`, `stall@T:MS`, `corrupt:P`, `encoder-jump@T:COUNTS`, `nan@T`, `slow@T:MS`,
//! with T in seconds of device time, MS in milliseconds, P a probability per packet.

use super::codec::STATE_LAYOUT;
use super::{Device, DeviceError, MissReason, RawSample, COMMAND_LEN};
use crate::config_check::{self as check, ConfigError};
use crate::omni::Dynamics;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::str::FromStr;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Faults to inject (testing the safety layer); same specs as `--inject`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct InjectConfig {
    /// E.g. `["disconnect@5", "stall@2:50", "corrupt:0.01", "encoder-jump@3:800", "nan@4", "slow@1:5"]`.
    pub faults: Vec<String>,
}

impl InjectConfig {
    /// The specs as faults; a bad one names its index (`inject.faults[i]`).
    pub fn parsed(&self) -> Result<Vec<Fault>, ConfigError> {
        self.faults
            .iter()
            .enumerate()
            .map(|(i, f)| {
                f.parse().map_err(|e: FaultSpecError| {
                    check::invalid(format!("inject.faults[{i}]"), format!("{f:?}"), e.why)
                })
            })
            .collect()
    }
}

impl InjectConfig {
    /// Every spec parses, and there are at most [`MAX_FAULTS`].
    pub fn validate(&self) -> Result<(), ConfigError> {
        let faults = self.parsed()?;
        if faults.len() > MAX_FAULTS {
            return Err(check::invalid(
                "inject.faults",
                format!("{} faults", faults.len()),
                format!("at most {MAX_FAULTS}"),
            ));
        }
        Ok(())
    }
}

/// One fault to inject, parsed from a spec such as `stall@2:50` (`--inject`, `[inject]`).
/// Times are device time since the run started, s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Fault {
    /// From T on, the device is gone.
    Disconnect {
        /// T, s.
        at_s: f64,
    },
    /// From T, no packet comes back for MS milliseconds.
    Stall {
        /// T, s.
        at_s: f64,
        /// MS, ms.
        ms: f64,
    },
    /// Each packet is corrupt (truncated) with probability P.
    Corrupt {
        /// P, 0..=1.
        probability: f64,
    },
    /// From T, joint 1's encoder reads COUNTS more.
    EncoderJump {
        /// T, s.
        at_s: f64,
        /// COUNTS, encoder counts.
        counts: i64,
    },
    /// At T, the controller's output turns non-finite.
    Nan {
        /// T, s.
        at_s: f64,
    },
    /// At T, one packet arrives MS milliseconds late.
    Slow {
        /// T, s.
        at_s: f64,
        /// MS, ms.
        ms: f64,
    },
}

#[derive(Debug, Clone, PartialEq, Error)]
#[error("bad fault spec `{}`: {why} (expected disconnect@T, stall@T:MS, corrupt:P, encoder-jump@T:COUNTS, nan@T or slow@T:MS)", crate::text::cut(.spec))]
/// A fault spec that does not parse.
pub struct FaultSpecError {
    /// The spec as given.
    pub spec: String,
    /// What is wrong with it.
    pub why: String,
}

fn num(spec: &str, what: &str, s: &str) -> Result<f64, FaultSpecError> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(FaultSpecError {
            spec: spec.to_string(),
            why: format!("{what} `{s}` is not a finite number ≥ 0"),
        }),
    }
}

impl FromStr for Fault {
    type Err = FaultSpecError;
    fn from_str(spec: &str) -> Result<Self, FaultSpecError> {
        let err = |why: &str| FaultSpecError {
            spec: spec.to_string(),
            why: why.to_string(),
        };
        if let Some(p) = spec.strip_prefix("corrupt:") {
            let probability = num(spec, "probability", p)?;
            if probability > 1.0 {
                return Err(err("probability must be ≤ 1"));
            }
            return Ok(Fault::Corrupt { probability });
        }
        let (kind, rest) = spec.split_once('@').ok_or_else(|| err("missing @T"))?;
        let (at, arg) = match rest.split_once(':') {
            Some((a, b)) => (a, Some(b)),
            None => (rest, None),
        };
        let at_s = num(spec, "time", at)?;
        let need = |what: &str| {
            arg.map(|a| num(spec, what, a))
                .unwrap_or_else(|| Err(err(&format!("missing :{what}"))))
        };
        match kind {
            "disconnect" => Ok(Fault::Disconnect { at_s }),
            "nan" => Ok(Fault::Nan { at_s }),
            "stall" => Ok(Fault::Stall {
                at_s,
                ms: need("MS")?,
            }),
            "slow" => Ok(Fault::Slow {
                at_s,
                ms: need("MS")?,
            }),
            "encoder-jump" => {
                let c = arg.ok_or_else(|| err("missing :COUNTS"))?;
                let counts = c
                    .trim()
                    .parse::<i64>()
                    .map_err(|_| err(&format!("COUNTS `{c}` is not an integer")))?;
                Ok(Fault::EncoderJump { at_s, counts })
            }
            other => Err(err(&format!("unknown fault `{other}`"))),
        }
    }
}

/// Fixed-capacity list of faults (no allocation in the loop).
pub const MAX_FAULTS: usize = 16;

/// A device with faults injected.
pub struct FaultyDevice {
    inner: Box<dyn Device>,
    faults: [Option<Fault>; MAX_FAULTS],
    rng: ChaCha8Rng,
    last_time: f64,
    stalled_until: Option<f64>,
    slow_done: [bool; MAX_FAULTS],
    /// The operator's stop: ends a `slow` wait of any length.
    stop: Arc<AtomicBool>,
}

impl FaultyDevice {
    /// `inner` with `faults` injected (at most [`MAX_FAULTS`]; more are ignored), its random
    /// corruption seeded by `seed`; `stop` ends a `slow` wait early.
    pub fn new(inner: Box<dyn Device>, faults: &[Fault], seed: u64, stop: Arc<AtomicBool>) -> Self {
        let mut list = [None; MAX_FAULTS];
        for (slot, f) in list.iter_mut().zip(faults) {
            *slot = Some(*f);
        }
        FaultyDevice {
            inner,
            faults: list,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0xFA17),
            last_time: 0.0,
            stalled_until: None,
            slow_done: [false; MAX_FAULTS],
            stop,
        }
    }
}

impl Device for FaultyDevice {
    fn kind(&self) -> &'static str {
        self.inner.kind()
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let t = self.last_time;
        for f in self.faults.iter().flatten() {
            if let Fault::Disconnect { at_s } = *f {
                if t >= at_s {
                    return Err(DeviceError::Disconnected("injected disconnect".into()));
                }
            }
        }
        let mut sample = self.inner.exchange(command)?;
        self.last_time = sample.device_time_s;
        let t = sample.device_time_s;
        for (i, f) in self.faults.iter().enumerate() {
            match *f {
                Some(Fault::Stall { at_s, ms }) if t >= at_s && self.stalled_until.is_none() => {
                    self.stalled_until = Some(at_s + ms * 1e-3);
                }
                // A truncated packet: the codec must reject it.
                Some(Fault::Corrupt { probability }) if self.rng.random::<f64>() < probability => {
                    sample.len = STATE_LAYOUT.counter;
                }
                Some(Fault::EncoderJump { at_s, counts }) if t >= at_s => {
                    let at = STATE_LAYOUT.encoder[0];
                    let raw = u16::from_le_bytes([sample.bytes[at], sample.bytes[at + 1]]);
                    let jumped = (raw as i64 + counts) as u16;
                    sample.bytes[at..at + 2].copy_from_slice(&jumped.to_le_bytes());
                }
                Some(Fault::Slow { at_s, ms }) if t >= at_s && !self.slow_done[i] => {
                    self.slow_done[i] = true;
                    let until = crate::clock::now_ns().saturating_add((ms * 1e6) as u64);
                    crate::clock::sleep_until_ns_or_stop(until, &self.stop);
                }
                _ => {}
            }
        }
        if let Some(until) = self.stalled_until {
            if t < until {
                return Err(DeviceError::Missed(MissReason::InjectedStall));
            }
        }
        Ok(sample)
    }

    fn close(&mut self) -> Result<(), DeviceError> {
        self.inner.close()
    }

    fn recorded_torque(&self) -> Option<[f64; 3]> {
        self.inner.recorded_torque()
    }

    fn plant_model(&self) -> Option<&Dynamics> {
        self.inner.plant_model()
    }

    fn hand_force(&self) -> Option<[f64; 3]> {
        self.inner.hand_force()
    }

    fn contact_force(&self) -> Option<[f64; 3]> {
        self.inner.contact_force()
    }

    fn stylus(&mut self, action: super::StylusAction) -> bool {
        self.inner.stylus(action)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_every_spec() {
        assert_eq!(
            "disconnect@2.5".parse(),
            Ok(Fault::Disconnect { at_s: 2.5 })
        );
        assert_eq!(
            "stall@1:50".parse(),
            Ok(Fault::Stall {
                at_s: 1.0,
                ms: 50.0
            })
        );
        assert_eq!(
            "corrupt:0.01".parse(),
            Ok(Fault::Corrupt { probability: 0.01 })
        );
        assert_eq!(
            "encoder-jump@3:-1200".parse(),
            Ok(Fault::EncoderJump {
                at_s: 3.0,
                counts: -1200
            })
        );
        assert_eq!("nan@4".parse(), Ok(Fault::Nan { at_s: 4.0 }));
        assert_eq!("slow@1:5".parse(), Ok(Fault::Slow { at_s: 1.0, ms: 5.0 }));
    }

    #[test]
    fn bad_specs_say_what_is_wrong() {
        for (spec, says) in [
            ("explode@1", "unknown fault `explode`"),
            ("stall@1", "missing :MS"),
            ("disconnect", "missing @T"),
            ("corrupt:2", "≤ 1"),
            ("nan@-1", "time `-1`"),
            ("encoder-jump@1:x", "COUNTS `x`"),
        ] {
            let e = spec.parse::<Fault>().unwrap_err().to_string();
            assert!(e.contains(says) && e.contains(spec), "{spec}: {e}");
        }
    }
}
