//! Progress bars for the long commands (`plot` on big logs, `identify`, experiments, long
//! `--fast` runs). They draw on stderr only when a person is watching: when stderr is not a
//! terminal (CI, pipes, tests) the bar is hidden, so no control codes end up in captured output.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::borrow::Cow;
use std::io::IsTerminal;

/// Redraws per second: enough to look alive, too few to cost anything.
const REFRESH_HZ: u8 = 10;
const ITEMS: &str = "{msg} [{wide_bar}] {human_pos}/{human_len} ({eta} left)";
const BYTES: &str = "{msg} [{wide_bar}] {bytes}/{total_bytes} ({eta} left)";

/// A bar counting `len` items (epochs, runs, ticks), labelled `message`.
pub fn bar(len: u64, message: impl Into<Cow<'static, str>>) -> ProgressBar {
    styled(len, message, ITEMS)
}

/// A bar counting `len` bytes (reading a file), labelled `message`.
pub fn bytes(len: u64, message: impl Into<Cow<'static, str>>) -> ProgressBar {
    styled(len, message, BYTES)
}

/// Whether bars are drawn at all: only when stderr is a terminal.
pub fn visible() -> bool {
    std::io::stderr().is_terminal()
}

fn styled(len: u64, message: impl Into<Cow<'static, str>>, template: &str) -> ProgressBar {
    if !visible() {
        return ProgressBar::hidden();
    }
    let bar =
        ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr_with_hz(REFRESH_HZ));
    // The templates are constants; should one ever fail to parse, a plain bar still works.
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(message);
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_bars_accept_updates() {
        // Under `cargo test` stderr is captured, so this is the hidden path; it must be inert.
        let b = bar(10, "epochs");
        b.inc(3);
        b.finish_and_clear();
        let b = bytes(1 << 20, "reading");
        b.set_position(1 << 19);
        b.finish_and_clear();
    }

    #[test]
    fn templates_parse() {
        for t in [ITEMS, BYTES] {
            assert!(ProgressStyle::with_template(t).is_ok(), "{t}");
        }
    }
}
