//! Telemetry: the per-tick log record, the writer thread that turns it into the CSV of
//! docs/DESIGN.md §2.2, the streaming reader that reads such logs back (for replay), and the
//! run summary of docs/DESIGN.md §2.3.

pub mod mcap_log;
pub mod reader;
pub mod record;
pub mod recorder;
pub mod writer;

pub use reader::{LogReader, LogRow, ReadError, SkipReport};
pub use record::{LogSchema, Mode, TickRecord};
pub use writer::LogError;
pub(crate) use writer::{
    dump_path, spawn_writer_with, write_dump, DumpTo, LogFile, Watch, WriterFault, WriterReport,
};

use serde::{Deserialize, Serialize};

/// `[telemetry]`: how the ticks travel from the servo loop to the log writer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TelemetryConfig {
    /// Capacity of the bounded channel from the servo loop to the log writer, ticks.
    pub channel_capacity: usize,
}

impl Default for TelemetryConfig {
    fn default() -> Self {
        TelemetryConfig {
            channel_capacity: 8192,
        }
    }
}

impl TelemetryConfig {
    /// Check every value; the first problem names its field (`telemetry.…`).
    pub(crate) fn validate(&self) -> Result<(), crate::config_check::ConfigError> {
        crate::config_check::int_in(
            "telemetry.channel_capacity",
            self.channel_capacity,
            16,
            10_000_000,
            "16 ..= 10000000",
        )
    }
}

/// `YYYYMMDD-HHMMSS` in UTC, for file names.
pub fn utc_stamp(time: std::time::SystemTime) -> String {
    let secs = time
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}{month:02}{day:02}-{:02}{:02}{:02}",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {
    #[test]
    fn utc_stamp_matches_known_dates() {
        let at =
            |s: u64| super::utc_stamp(std::time::UNIX_EPOCH + std::time::Duration::from_secs(s));
        assert_eq!(at(0), "19700101-000000");
        // 2000-02-29 12:34:56 UTC (a leap day) and 2026-11-23 16:21:00 UTC.
        assert_eq!(at(951_827_696), "20000229-123456");
        assert_eq!(at(1_795_450_860), "20261123-162100");
    }
}
