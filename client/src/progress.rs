//! Progress bars for long runs: shown on an interactive terminal, silent in CI and pipes.
//!
//! It must not know what is being measured; callers label and advance the bars.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

/// Whether progress bars should be drawn: stderr is a terminal and `CI` is not set.
pub fn interactive() -> bool {
    on_terminal() && std::env::var_os("CI").is_none()
}

/// Whether progress may be shown at all: stderr is a terminal (a CI job's log may be one, then
/// progress comes as plain lines). Into pipes and files, progress is never written.
pub fn on_terminal() -> bool {
    std::io::stderr().is_terminal()
}

/// A bar of `len` steps labelled `what`, hidden when not interactive.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    if !interactive() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    // The label is the prefix, so that `set_message` (progress details) does not replace it.
    let style = ProgressStyle::with_template("{prefix:>14} [{bar:32}] {pos}/{len} {wide_msg}")
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ");
    bar.set_style(style);
    bar.set_prefix(what.to_string());
    bar
}
