//! `omnid identify`: pre-tune the identifier on logs.

use crate::{error_exit, load_config, stop_on_signal};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct IdentifyArgs {
    /// Logs to learn from (omnid logs, or any CSV with t, q1..3, tau1..3).
    #[arg(required = true)]
    logs: Vec<PathBuf>,
    /// Where to write the weights (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Passes over the data.
    #[arg(long, default_value_t = 20)]
    epochs: usize,
    /// TOML configuration file (its [identifier] and [kalman] sections apply).
    #[arg(long)]
    config: Option<PathBuf>,
    /// The joint states to learn from: the whole log smoothed (no filter lag), or the live
    /// loop's causal filter.
    #[arg(long, value_enum, default_value_t = omnid::cmd::identify::States::Smoothed)]
    states: omnid::cmd::identify::States,
}

pub(crate) fn identify_cmd(args: IdentifyArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let cfg = match load_config(args.config.as_deref(), Some(&stop)) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    let pretune_cfg = omnid::identifier::PretuneConfig {
        epochs: args.epochs,
        ..Default::default()
    };
    let bar = omnid::progress::bar(args.epochs as u64, "identify");
    let result = omnid::cmd::identify::identify(
        &args.logs,
        &args.out,
        &cfg,
        &pretune_cfg,
        args.states,
        Some(&stop),
        |p| match p {
            omnid::identifier::Progress::Batch { .. } => {}
            omnid::identifier::Progress::Epoch(r) => {
                bar.inc(1);
                bar.suspend(|| omnid::errln!(
                    "epoch {:>3}/{}: train NRMSE {:.3} / {:.3} / {:.3}   validation {:.3} / {:.3} / {:.3}",
                    r.epoch,
                    r.epochs,
                    r.train_nrmse[0],
                    r.train_nrmse[1],
                    r.train_nrmse[2],
                    r.val_nrmse[0],
                    r.val_nrmse[1],
                    r.val_nrmse[2]
                ));
            }
        },
    );
    bar.finish_and_clear();
    match result {
        Ok(report) => {
            let best = &report.epochs[report.kept_epoch - 1];
            omnid::outln!(
                "identify: {} training and {} validation samples; kept epoch {}: training NRMSE {:.3} / {:.3} / {:.3}, validation NRMSE {:.3} / {:.3} / {:.3}; weights in {}",
                report.train_samples,
                report.val_samples,
                report.kept_epoch,
                best.train_nrmse[0],
                best.train_nrmse[1],
                best.train_nrmse[2],
                best.val_nrmse[0],
                best.val_nrmse[1],
                best.val_nrmse[2],
                args.out.display()
            );
            Ok(0)
        }
        Err(e) => {
            omnid::errln!("omnid identify: {e}");
            Ok(error_exit(e.is_stopped(), e.is_bad_input()))
        }
    }
}
