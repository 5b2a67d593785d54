//! `omnid plot`: figures from a log.

use crate::{error_exit, stop_on_signal, EXIT_BAD_INPUT};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct PlotArgs {
    /// The log (CSV or MCAP; at least `t`: figures whose columns are missing are skipped).
    log: PathBuf,
    /// Directory for the figures (created if needed).
    #[arg(long)]
    out: PathBuf,
    /// The scene the run rendered: its walls are drawn on the tip path.
    #[arg(long, value_name = "SCENE.toml")]
    scene: Option<PathBuf>,
    /// Draw only from this time on (s, the log's `t`).
    #[arg(long, value_name = "SECONDS", allow_negative_numbers = true)]
    from: Option<f64>,
    /// Draw only up to this time (s, the log's `t`).
    #[arg(long, value_name = "SECONDS", allow_negative_numbers = true)]
    to: Option<f64>,
    /// Figure width, px (the SVG's too).
    #[arg(long, default_value_t = omnid::plot::PlotOptions::default().width)]
    width: u32,
    /// Figure height, px.
    #[arg(long, default_value_t = omnid::plot::PlotOptions::default().height)]
    height: u32,
    /// Text size relative to the default (0.5 to 3; e.g. 1.5 for a two-column paper).
    #[arg(long, default_value_t = 1.0)]
    font_scale: f64,
}

pub(crate) fn plot_cmd(args: PlotArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let effects = match args
        .scene
        .as_deref()
        .map(|p| omnid::haptics::scene::read_scene(p, Some(&stop)))
    {
        None => Vec::new(),
        Some(Ok(e)) => e,
        Some(Err(e)) => {
            omnid::errln!("omnid plot: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
    };
    let options = omnid::plot::PlotOptions {
        from_s: args.from,
        to_s: args.to,
        width: args.width,
        height: args.height,
        font_scale: args.font_scale,
    };
    match omnid::plot::plot_log(&args.log, &args.out, &effects, &options, Some(&stop)) {
        Ok(report) => {
            omnid::out!("{report}");
            Ok(0)
        }
        Err(e) => {
            omnid::errln!("omnid plot: {e}");
            Ok(error_exit(e.is_stopped(), e.is_bad_input()))
        }
    }
}
