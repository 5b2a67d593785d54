//! `omnid plot`: figures from a log.

use crate::{error_exit, stop_on_signal, EXIT_BAD_INPUT};

pub(crate) fn plot_cmd(
    log: &std::path::Path,
    out: &std::path::Path,
    scene: Option<&std::path::Path>,
) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let effects = match scene.map(|p| omnid::haptics::scene::read_scene(p, Some(&stop))) {
        None => Vec::new(),
        Some(Ok(e)) => e,
        Some(Err(e)) => {
            omnid::errln!("omnid plot: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
    };
    match omnid::plot::plot_log(log, out, &effects, Some(&stop)) {
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
