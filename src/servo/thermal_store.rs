//! Motor heat persisted across runs: saved at the end of a run with the wall-clock time, loaded
//! at the start of the next and cooled by the time in between (same first-order model), so
//! back-to-back runs cannot each start from cold.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct Saved {
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

/// Heat at start: the saved heat cooled over the elapsed time. A missing, unreadable or
/// malformed file means cold motors (the file is a convenience, not a safety mechanism of its
/// own: the clamp still applies), reported through the returned note.
pub fn load(path: &Path, time_constant_s: f64) -> ([f64; 3], Option<String>) {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return ([0.0; 3], None),
        Err(e) => {
            return (
                [0.0; 3],
                Some(format!("cannot read {}: {e}", path.display())),
            )
        }
    };
    match serde_json::from_str::<Saved>(&text) {
        Ok(s) if s.heat.iter().all(|h| h.is_finite() && *h >= 0.0) => {
            let elapsed = (now_s() - s.unix_time_s).max(0.0);
            let cool = (-elapsed / time_constant_s).exp();
            (s.heat.map(|h| h * cool), None)
        }
        _ => (
            [0.0; 3],
            Some(format!(
                "ignoring malformed motor heat file {}",
                path.display()
            )),
        ),
    }
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

    #[test]
    fn round_trip_and_cooling() {
        let dir = tempfile::tempdir().unwrap();
        let path = heat_file(dir.path(), "sim");
        assert_eq!(load(&path, 30.0), ([0.0; 3], None));
        save(&path, [0.5, 0.0, 2.0]).unwrap();
        let files: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(files, ["thermal-sim.json"], "nothing left beside it");
        let (h, note) = load(&path, 30.0);
        assert!(note.is_none());
        // Saved a moment ago: barely cooled.
        assert!((h[0] - 0.5).abs() < 0.01 && (h[2] - 2.0).abs() < 0.04 && h[1] == 0.0);
        // An hour-old file has cooled right down.
        let old = Saved {
            heat: [1.0; 3],
            unix_time_s: now_s() - 3600.0,
        };
        std::fs::write(&path, serde_json::to_string(&old).unwrap()).unwrap();
        assert!(load(&path, 30.0).0[0] < 1e-20);
    }

    #[test]
    fn malformed_file_is_cold_with_a_note() {
        let dir = tempfile::tempdir().unwrap();
        let path = heat_file(dir.path(), "sim");
        for bad in [
            "{",
            "{\"heat\":[1,2],\"unix_time_s\":0}",
            "{\"heat\":[-1,0,0],\"unix_time_s\":0}",
        ] {
            std::fs::write(&path, bad).unwrap();
            let (h, note) = load(&path, 30.0);
            assert_eq!(h, [0.0; 3]);
            assert!(note.unwrap().contains("malformed"));
        }
    }
}
