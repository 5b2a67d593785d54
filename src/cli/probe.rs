//! `omnid probe`: first contact with a FireWire Omni.

use crate::{
    load_config, stop_on_signal, EXIT_BAD_INPUT, EXIT_DEVICE_FAULT, EXIT_INTERNAL,
    EXIT_OPERATOR_STOP,
};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct ProbeArgs {
    /// firewire (a USB bridge has no registers or bus timestamps to probe)
    #[arg(long, default_value = "firewire")]
    device: String,
    /// A configured arm (`[[arm]]` in --config): its sections, and its lock.
    #[arg(long, value_name = "NAME")]
    arm: Option<String>,
    /// Capture file [default: omnid-capture-<UTC time>.txt]; replayable after
    /// `omnid convert --from capture`.
    #[arg(long)]
    capture: Option<PathBuf>,
    /// How long to capture with the amplifiers off, s (ends early once every step was seen).
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Then the output steps: lamp, amplifiers at zero torque, each motor's sign.
    #[arg(long)]
    outputs: bool,
    /// DAC counts of the sign pulses (1..=200; the default is about 9 mN·m).
    #[arg(long, default_value_t = 40)]
    counts: u16,
    /// TOML configuration file ([firewire], device.rate_hz, device.nm_per_count).
    #[arg(long)]
    config: Option<PathBuf>,
}

pub(crate) fn probe_cmd(args: ProbeArgs) -> Result<u8, anyhow::Error> {
    use omnid::device::probe::{probe_firewire, ProbeError, ProbePlan, TerminalOperator};
    let mut cfg = match load_config(args.config.as_deref(), None) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    // The arm is this process's while it probes: a daemon or a run on it is refused, and so
    // is this probe while one of them has it.
    let arm = args.arm.clone().unwrap_or_else(|| "firewire".into());
    // A configured arm that is simulated is locked as its runs and daemons lock it (per user).
    let mut simulated = false;
    if args.arm.is_some() {
        match cfg.arm_named(&arm) {
            Ok(a) => {
                simulated = !matches!(
                    a.device,
                    omnid::device::registry::DeviceSpec::Usb
                        | omnid::device::registry::DeviceSpec::Firewire
                );
                cfg = a.config
            }
            Err(e) => {
                omnid::errln!("omnid probe: --arm: {e}");
                return Ok(EXIT_BAD_INPUT);
            }
        }
    }
    if args.device != "firewire" {
        omnid::errln!(
            "omnid probe: --device {}: only firewire can be probed (a USB bridge has no device \
             registers or bus timestamps; `omnid run --device usb` reports what it finds)",
            args.device
        );
        return Ok(EXIT_BAD_INPUT);
    }
    let stop = stop_on_signal()?;
    let plan = ProbePlan {
        capture: args.capture.unwrap_or_else(|| {
            PathBuf::from(format!(
                "omnid-capture-{}.txt",
                omnid::telemetry::utc_stamp(std::time::SystemTime::now())
            ))
        }),
        seconds: args.seconds,
        outputs: args.outputs,
        counts: args.counts,
        lock: args.arm.is_none().then(|| arm.clone()),
    };
    if let Err(e) = plan.check(&cfg) {
        omnid::errln!("omnid probe: {e}");
        return Ok(EXIT_BAD_INPUT);
    }
    // A named arm is locked now (it may be a daemon's); the default one once the Omni is found.
    let _lock = match args.arm.as_ref().map(|_| match simulated {
        true => omnid::arm::ArmLock::acquire_simulated(&arm),
        false => omnid::arm::ArmLock::acquire(&arm),
    }) {
        Some(Err(e)) => {
            omnid::errln!("omnid probe: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
        held => held,
    };
    let mut op = TerminalOperator { stop: &stop };
    match probe_firewire(&cfg, &plan, &mut op, &stop) {
        Ok(report) => {
            omnid::outln!(
                "omnid probe: serial {}; {} packets captured in {}",
                report.serial.as_deref().unwrap_or("?"),
                report.captured,
                plan.capture.display()
            );
            for (what, seen) in &report.checks {
                omnid::outln!("  [{}] {what}", if *seen { "x" } else { " " });
            }
            if let Some(s) = report.dac_sign {
                omnid::outln!("[firewire]\ndac_sign = [{}, {}, {}]", s[0], s[1], s[2]);
            }
            if let Some(why) = &report.aborted {
                omnid::errln!(
                    "omnid probe: output steps stopped: {why}; zero torque, amplifiers off"
                );
                return Ok(EXIT_OPERATOR_STOP);
            }
            Ok(0)
        }
        Err(e @ ProbeError::BadInput(_)) => {
            omnid::errln!("omnid probe: {e}");
            Ok(EXIT_BAD_INPUT)
        }
        Err(e @ ProbeError::Device(_)) => {
            omnid::errln!("omnid: {e}");
            Ok(EXIT_DEVICE_FAULT)
        }
        Err(e @ ProbeError::Capture { .. }) => {
            omnid::errln!("omnid probe: {e}");
            Ok(EXIT_INTERNAL)
        }
    }
}
