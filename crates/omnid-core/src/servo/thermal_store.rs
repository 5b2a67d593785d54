//! Motor heat persisted across runs: saved at the end of a run with the wall-clock time, loaded
//! at the start of the next and cooled by the time in between (same first-order model), so
//! back-to-back runs cannot each start from cold. What is loaded is range-checked like the
//! config: a file whose heat this configuration could never produce is ignored with a warning.

use super::safety::SafetyConfig;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Saved {
    #[serde(deserialize_with = "crate::config_check::exact")]
    heat: [f64; 3],
    unix_time_s: f64,
}

/// `$OMNID_STATE_DIR`, else `$XDG_STATE_HOME/omnid`, else `~/.local/state/omnid`.
pub fn state_dir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("OMNID_STATE_DIR") {
        return Some(PathBuf::from(d));
    }
    if let Some(d) = std::env::var_os("XDG_STATE_HOME") {
        return Some(PathBuf::from(d).join("omnid"));
    }
    std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/state/omnid"))
}

/// The heat file of one device (`thermal-<device>.json`).
pub fn heat_file(dir: &Path, device: &str) -> PathBuf {
    dir.join(format!("thermal-{device}.json"))
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// The most heat a motor can hold under `safety`: the steady state at its torque clamp (the
/// model heats toward (τ/τ_cont)², and τ never exceeds `max_torque_nm`).
pub fn max_heat(safety: &SafetyConfig, joint: usize) -> f64 {
    (safety.max_torque_nm[joint] / safety.continuous_torque_nm[joint]).powi(2)
}

/// What a run assumes when the heat file cannot be believed: motors at the thermal limit, so
/// torque is held to the continuous torque until they cool as modelled. A file that lies
/// must not make hot motors look cold.
pub fn assumed_hot(safety: &SafetyConfig) -> [f64; 3] {
    [0, 1, 2].map(|j| safety.thermal_limit.min(max_heat(safety, j)))
}

/// Heat at start: the saved heat cooled over the elapsed time (`safety`'s time constant). A
/// missing file means cold motors (a first run). An unreadable or malformed file, or one whose
/// heat is outside 0 ..= [`max_heat`] or whose time is not a time, fails closed: motors
/// [`assumed_hot`], reported through the returned note, which names the file and the value.
pub fn load(path: &Path, safety: &SafetyConfig) -> ([f64; 3], Option<String>) {
    let hot = assumed_hot(safety);
    let assuming = "; assuming the motors at the thermal limit (torque held to the continuous \
                    torque until they cool as modelled; delete the file if they are known cold)";
    // A regular file of at most 64 KiB (it is under 100 bytes): never a wait, never a big read.
    let text = match crate::input::read_capped(path, 64 << 10, None) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return ([0.0; 3], None),
        Err(e) => {
            return (
                hot,
                Some(format!("cannot read {}: {e}{assuming}", path.display())),
            )
        }
    };
    let saved = match serde_json::from_str::<Saved>(&text) {
        Ok(s) => s,
        Err(e) => {
            return (
                hot,
                Some(format!(
                    "ignoring malformed motor heat file {}: {e}{assuming}",
                    path.display()
                )),
            )
        }
    };
    let out_of_range = |field: String, value: f64, allowed: String| {
        Some(format!(
            "ignoring motor heat file {}: `{field}` = {value:?} is out of range: allowed \
             {allowed}{assuming}",
            path.display()
        ))
    };
    for (j, &h) in saved.heat.iter().enumerate() {
        let most = max_heat(safety, j);
        if !(h.is_finite() && (0.0..=most).contains(&h)) {
            let allowed = format!("0 ..= {most} (the steady state at safety.max_torque_nm)");
            return (hot, out_of_range(format!("heat[{j}]"), h, allowed));
        }
    }
    let t = saved.unix_time_s;
    if !(t.is_finite() && t >= 0.0) {
        let allowed = "a time in seconds since 1970".to_string();
        return (hot, out_of_range("unix_time_s".into(), t, allowed));
    }
    let elapsed = (now_s() - t).max(0.0);
    let cool = (-elapsed / safety.thermal_time_constant_s).exp();
    (saved.heat.map(|h| h * cool), None)
}

/// Save the heat at the end of a run, whole (see [`crate::output`]): a run killed meanwhile
/// leaves the old file as it was (and ext4 need not wait, as it does when truncating a file,
/// for the run's log to reach the disk first).
pub fn save(path: &Path, heat: [f64; 3]) -> Result<(), crate::output::OutputError> {
    let saved = Saved {
        heat,
        unix_time_s: now_s(),
    };
    // Plain numbers: serialisation cannot fail.
    let text = serde_json::to_string(&saved).unwrap_or_default() + "\n";
    crate::output::write_bytes(path, text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn safety(time_constant_s: f64) -> SafetyConfig {
        SafetyConfig {
            thermal_time_constant_s: time_constant_s,
            ..SafetyConfig::default()
        }
    }

    #[test]
    fn round_trip_and_cooling() {
        let dir = tempfile::tempdir().unwrap();
        let path = heat_file(dir.path(), "sim");
        assert_eq!(load(&path, &safety(30.0)), ([0.0; 3], None));
        save(&path, [0.5, 0.0, 2.0]).unwrap();
        let files: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(files, ["thermal-sim.json"], "nothing left beside it");
        let (h, note) = load(&path, &safety(30.0));
        assert!(note.is_none());
        // Saved a moment ago: barely cooled.
        assert!((h[0] - 0.5).abs() < 0.01 && (h[2] - 2.0).abs() < 0.04 && h[1] == 0.0);
        // An hour-old file has cooled right down.
        let old = Saved {
            heat: [1.0; 3],
            unix_time_s: now_s() - 3600.0,
        };
        std::fs::write(&path, serde_json::to_string(&old).unwrap()).unwrap();
        assert!(load(&path, &safety(30.0)).0[0] < 1e-20);
    }

    #[test]
    fn a_malformed_file_fails_closed_with_a_note() {
        let dir = tempfile::tempdir().unwrap();
        let path = heat_file(dir.path(), "sim");
        for bad in [
            "{",
            "{\"heat\":[1,2],\"unix_time_s\":0}",
            "{\"heat\":[1,2,3,4],\"unix_time_s\":0}",
            "{\"heat\":[1,2,3],\"unix_time_s\":\"now\"}",
        ] {
            std::fs::write(&path, bad).unwrap();
            let (h, note) = load(&path, &safety(30.0));
            assert_eq!(h, assumed_hot(&safety(30.0)));
            assert!(h.iter().all(|&h| h > 0.0));
            let note = note.unwrap();
            assert!(
                note.contains("malformed") && note.contains("assuming"),
                "{bad}"
            );
        }
    }

    #[test]
    fn heat_this_config_cannot_produce_is_refused_naming_file_and_value() {
        let dir = tempfile::tempdir().unwrap();
        let path = heat_file(dir.path(), "sim");
        let cfg = safety(30.0);
        // (0.45 / 0.13)² ≈ 11.98 is the most a motor can hold at the default clamp.
        let most = max_heat(&cfg, 1);
        assert!((most - 11.98).abs() < 0.01, "{most}");
        let now = now_s();
        for (heat, field, value) in [
            ("[1e300, 0, 0]".to_string(), "heat[0]", "1e300"),
            (format!("[0, {}, 0]", most * 1.01), "heat[1]", "12.1"),
            ("[0, 0, -1]".to_string(), "heat[2]", "-1.0"),
        ] {
            let text = format!("{{\"heat\":{heat},\"unix_time_s\":{now}}}");
            std::fs::write(&path, text).unwrap();
            let (h, note) = load(&path, &cfg);
            assert_eq!(h, assumed_hot(&cfg), "{heat}");
            let note = note.unwrap();
            assert!(
                note.contains(&path.display().to_string())
                    && note.contains(&format!("`{field}` = {value}"))
                    && note.contains("out of range"),
                "{note}"
            );
        }
        std::fs::write(&path, "{\"heat\":[1,0,0],\"unix_time_s\":-5}").unwrap();
        let (h, note) = load(&path, &cfg);
        assert_eq!(h, assumed_hot(&cfg));
        assert!(note.unwrap().contains("`unix_time_s` = -5.0"));
        // At the ceiling is fine: a motor held at the clamp long enough gets there.
        std::fs::write(
            &path,
            format!("{{\"heat\":[{most},0,0],\"unix_time_s\":{now}}}"),
        )
        .unwrap();
        let (h, note) = load(&path, &cfg);
        assert!(note.is_none() && h[0] > 0.99 * most, "{note:?}");
    }
}
