//! `[[arm]]`: several arms in one configuration. Each entry names an arm, its device and
//! serial, and may give any of the per-arm sections (`[arm.safety]`, `[arm.sim]`, …), which lay
//! over the file's own sections key by key; per-process sections (`[device]`, `[realtime]`
//! but for the arm's `cpu`, `[telemetry]`, `[serve]` but for the arm's `socket`) stay global.
//! A file without arms is one arm, as before.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One per-arm section's keys, as written.
pub(crate) type Section = Option<BTreeMap<String, toml::Value>>;
type SectionSchema = Option<BTreeMap<String, serde_json::Value>>;

/// One `[[arm]]` entry as written.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ArmEntry {
    /// The arm's name: its socket (`<name>.sock`), lock, heat file and fault dumps.
    pub name: String,
    /// The backend: sim, replay:PATH, usb or firewire.
    #[serde(default = "default_device")]
    pub device: String,
    /// The serial this arm must have (FireWire: the 11-digit label; empty: the only one).
    #[serde(default)]
    pub serial: String,
    /// Other names clients may open it by (OpenHaptics programs' "PHANToM 1", …).
    #[serde(default)]
    pub aliases: Vec<String>,
    /// CPU to pin this arm's servo thread to (-1: `realtime.cpu`).
    #[serde(default = "any_cpu")]
    pub cpu: i32,
    /// Socket path (empty: `<runtime dir>/<name>.sock`).
    #[serde(default)]
    pub socket: String,
    /// This arm's `[sim]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub sim: Section,
    /// This arm's `[model]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub model: Section,
    /// This arm's `[geometry]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub geometry: Section,
    /// This arm's `[kalman]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub kalman: Section,
    /// This arm's `[control]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub control: Section,
    /// This arm's `[reference]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub reference: Section,
    /// This arm's `[safety]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub safety: Section,
    /// This arm's `[identifier]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub identifier: Section,
    /// This arm's `[usb]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub usb: Section,
    /// This arm's `[firewire]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub firewire: Section,
    /// This arm's `[inject]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub inject: Section,
    /// This arm's `[haptics]` keys.
    #[serde(default)]
    #[schemars(with = "SectionSchema")]
    pub haptics: Section,
}

fn default_device() -> String {
    "sim".into()
}

fn any_cpu() -> i32 {
    -1
}
