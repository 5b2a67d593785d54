//! `[serve]`: the daemon's client interface (socket, access, stream time to live, fault ring).

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// Where a stale or abandoned stream leaves the arm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum StaleFallback {
    /// Hold the arm where it is (amplifiers on).
    Hold,
    /// Amplifiers off: the arm rests.
    Idle,
}

impl StaleFallback {
    /// The servo activity it falls back to.
    pub fn activity(self) -> crate::servo::Activity {
        match self {
            StaleFallback::Hold => crate::servo::Activity::Hold,
            StaleFallback::Idle => crate::servo::Activity::Idle,
        }
    }
}

/// The `[serve]` section: the client interface of `omnid serve` (docs/PROTOCOL.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ServeConfig {
    /// Socket path; empty: `$XDG_RUNTIME_DIR/omnid/<device>.sock` (or /run/omnid/ as root).
    pub socket: String,
    /// A stream command (`servo_jp`, `servo_jf`) stays in effect this long unless renewed, ms.
    pub stream_ttl_ms: f64,
    /// Where a stale or abandoned stream leaves the arm: hold or idle.
    pub stale_fallback: StaleFallback,
    /// Crossfade of a controller switch, s (0: switch at once, the kick limit still holds).
    pub switch_fade_s: f64,
    /// Members of this group may read the state stream (empty: only the daemon's own user
    /// and root).
    pub read_group: String,
    /// Members of this group may also command (empty: only the daemon's own user and root).
    pub control_group: String,
    /// Most clients connected at once (root and the daemon's own user have 8 more slots, so
    /// the one who can stop the arm always gets in).
    pub max_clients: usize,
    /// Most connections one user (other than root and the daemon's user) may hold.
    pub max_clients_per_user: usize,
    /// A connection that has not said hello within this long is closed, ms.
    pub hello_timeout_ms: f64,
    /// A lease holder whose socket stays full this long (it stopped reading) loses the lease,
    /// and what it set up that makes force ends at its fallback, ms.
    pub lease_lapse_ms: f64,
    /// With several arms: one arm's device or safety fault stops them all (false: that arm
    /// stops, the others go on).
    pub fail_together: bool,
    /// At most one fault dump per arm this often, s (later trips are counted, not dumped).
    pub dump_interval_s: f64,
    /// Fault dumps kept per arm in `<dump_dir>/faults` (the oldest are removed).
    pub max_dumps: usize,
    /// State messages queued per client before the oldest are dropped (and counted).
    pub client_queue: usize,
    /// Seconds of ticks kept in memory for the fault dump.
    pub ring_s: f64,
    /// Format of fault dumps and of recordings started without a path: `csv` or `mcap`
    /// (a recording given a path follows its extension).
    pub log_format: crate::telemetry::mcap_log::LogKind,
    /// Directory for fault dumps; empty: $OMNID_STATE_DIR or ~/.local/state/omnid.
    pub dump_dir: String,
    /// SCHED_FIFO priority of the thread that serves clients (1..=98, below
    /// `realtime.fifo_priority`); 0 leaves the normal scheduler. The hub is on every stream
    /// client's round trip (state out, command in, within one tick), so a busy machine must
    /// not preempt it.
    pub hub_fifo_priority: i32,
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            socket: String::new(),
            stream_ttl_ms: 20.0,
            stale_fallback: StaleFallback::Hold,
            switch_fade_s: 0.2,
            read_group: String::new(),
            control_group: String::new(),
            max_clients: 128,
            max_clients_per_user: 32,
            hello_timeout_ms: 2000.0,
            lease_lapse_ms: 1000.0,
            fail_together: false,
            dump_interval_s: 10.0,
            max_dumps: 20,
            client_queue: 1024,
            ring_s: 10.0,
            log_format: Default::default(),
            dump_dir: String::new(),
            hub_fifo_priority: 70,
        }
    }
}

impl ServeConfig {
    /// Check every value; the first problem names its field (`serve.…`).
    /// `servo_fifo_priority` is `realtime.fifo_priority`: the hub must stay below the servo.
    pub fn validate(&self, servo_fifo_priority: i32) -> Result<(), ConfigError> {
        self.check_streams()?;
        self.check_priority(servo_fifo_priority)?;
        self.check_limits()?;
        self.check_access()
    }

    /// A stream's time to live and the fade between sources.
    fn check_streams(&self) -> Result<(), ConfigError> {
        check::in_range(
            "serve.stream_ttl_ms",
            self.stream_ttl_ms,
            1.0,
            10_000.0,
            "1 ..= 10000 ms",
        )?;
        check::in_range(
            "serve.switch_fade_s",
            self.switch_fade_s,
            0.0,
            10.0,
            "0 ..= 10 s",
        )
    }

    /// The hub's SCHED_FIFO priority, below the servo's.
    fn check_priority(&self, servo_fifo_priority: i32) -> Result<(), ConfigError> {
        check::int_in(
            "serve.hub_fifo_priority",
            self.hub_fifo_priority,
            0,
            98,
            "0 ..= 98",
        )?;
        if self.hub_fifo_priority > 0
            && servo_fifo_priority > 0
            && self.hub_fifo_priority >= servo_fifo_priority
        {
            return Err(check::invalid(
                "serve.hub_fifo_priority",
                self.hub_fifo_priority.to_string(),
                format!("below realtime.fifo_priority ({servo_fifo_priority}), so the hub never delays a tick"),
            ));
        }
        Ok(())
    }

    /// The ring, clients, dumps, timeouts and queues.
    fn check_limits(&self) -> Result<(), ConfigError> {
        check::in_range("serve.ring_s", self.ring_s, 0.0, 600.0, "0 ..= 600 s")?;
        check::int_in("serve.max_clients", self.max_clients, 1, 1024, "1 ..= 1024")?;
        check::in_range(
            "serve.dump_interval_s",
            self.dump_interval_s,
            0.0,
            86_400.0,
            "0 ..= 86400 s",
        )?;
        check::int_in("serve.max_dumps", self.max_dumps, 1, 10_000, "1 ..= 10000")?;
        check::int_in(
            "serve.max_clients_per_user",
            self.max_clients_per_user,
            1,
            1024,
            "1 ..= 1024",
        )?;
        check::in_range(
            "serve.hello_timeout_ms",
            self.hello_timeout_ms,
            10.0,
            60_000.0,
            "10 ..= 60000 ms",
        )?;
        check::in_range(
            "serve.lease_lapse_ms",
            self.lease_lapse_ms,
            50.0,
            60_000.0,
            "50 ..= 60000 ms",
        )?;
        check::int_in(
            "serve.client_queue",
            self.client_queue,
            16,
            1_000_000,
            "16 ..= 1000000",
        )
    }

    /// Who may read and command (the groups), and the paths.
    fn check_access(&self) -> Result<(), ConfigError> {
        for (field, group) in [
            ("serve.read_group", &self.read_group),
            ("serve.control_group", &self.control_group),
        ] {
            if group.len() > 32 || group.contains(|c: char| c.is_whitespace() || c == ':') {
                return Err(check::invalid(
                    field,
                    format!("{group:?}"),
                    "a group name (no spaces or colons, at most 32 characters)",
                ));
            }
        }
        if self.socket.contains('\0') || self.dump_dir.contains('\0') {
            return Err(check::invalid(
                "serve.socket",
                "a path with a NUL byte",
                "a path",
            ));
        }
        Ok(())
    }

    /// `stream_ttl_ms` in seconds.
    pub fn stream_ttl_s(&self) -> f64 {
        self.stream_ttl_ms * 1e-3
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_name_the_field() {
        ServeConfig::default().validate(80).unwrap();
        let bad = ServeConfig {
            stream_ttl_ms: 0.0,
            ..Default::default()
        };
        assert!(bad
            .validate(80)
            .unwrap_err()
            .to_string()
            .contains("serve.stream_ttl_ms"));
        let bad = ServeConfig {
            control_group: "lab users".into(),
            ..Default::default()
        };
        assert!(bad
            .validate(80)
            .unwrap_err()
            .to_string()
            .contains("serve.control_group"));
        let above_servo = ServeConfig {
            hub_fifo_priority: 80,
            ..Default::default()
        };
        let e = above_servo.validate(80).unwrap_err().to_string();
        assert!(
            e.contains("serve.hub_fifo_priority") && e.contains("below"),
            "{e}"
        );
        // With the servo on the normal scheduler, any hub priority is allowed.
        above_servo.validate(0).unwrap();
    }
}
