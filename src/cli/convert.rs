//! `omnid convert`: other recordings into replayable logs.

use crate::{error_exit, stop_on_signal, EXIT_OPERATOR_STOP};
use omnid::convert::{convert, SourceFormat};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct ConvertArgs {
    /// Format of the input.
    #[arg(long, value_enum)]
    from: SourceFormat,
    /// The recording to convert (CSV; `--from log`: CSV or MCAP).
    input: PathBuf,
    /// Where to write the replayable log (CSV; `--from log`: MCAP when it ends in .mcap).
    #[arg(long)]
    out: PathBuf,
    /// Skip damaged rows (reported) instead of refusing the file.
    #[arg(long)]
    lenient: bool,
}

pub(crate) fn convert_cmd(args: ConvertArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    match convert(args.from, &args.input, &args.out, args.lenient, Some(&stop)) {
        Ok(report) => {
            // A long header is named by its first columns and its count, not all of them.
            const SHOWN: usize = 6;
            let columns = if report.columns.len() <= SHOWN {
                report.columns.join(",")
            } else {
                format!(
                    "{},… ({} in all)",
                    report.columns[..SHOWN].join(","),
                    report.columns.len()
                )
            };
            omnid::outln!(
                "omnid convert: {} rows from {} to {} (columns: {columns})",
                report.rows,
                args.input.display(),
                args.out.display(),
            );
            if report.skipped.count > 0 {
                omnid::errln!("omnid: warning: --lenient: {}", report.skipped);
            }
            Ok(0)
        }
        Err(e) if e.is_stopped() => {
            omnid::errln!("omnid: {e}; nothing written");
            Ok(EXIT_OPERATOR_STOP)
        }
        Err(e) => {
            omnid::errln!("omnid: {e}");
            Ok(error_exit(false, e.is_bad_input()))
        }
    }
}
