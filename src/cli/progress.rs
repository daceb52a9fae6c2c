//! The indicatif progress bar: the only place kfmc draws progress.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;

use crate::runner::{CancelToken, RunObserver};

/// A progress bar over simulated runs, with rate and ETA; hidden with `--quiet` or when
/// stderr is not a terminal, so logs and pipes stay clean.
pub struct ProgressObserver {
    bar: ProgressBar,
    cancel: Option<CancelToken>,
}

impl ProgressObserver {
    /// A bar that draws only when `visible` and stderr is a terminal.
    pub fn new(visible: bool) -> Self {
        let bar = ProgressBar::with_draw_target(
            Some(0),
            if visible && std::io::stderr().is_terminal() {
                ProgressDrawTarget::stderr()
            } else {
                ProgressDrawTarget::hidden()
            },
        );
        bar.set_style(
            ProgressStyle::with_template(
                "{elapsed_precise} [{wide_bar:.cyan/blue}] {human_pos}/{human_len} runs  {per_sec}  ETA {eta}",
            )
            .expect("the template is valid")
            .progress_chars("=> "),
        );
        ProgressObserver { bar, cancel: None }
    }

    /// The same observer, whose study also stops when `token` is cancelled.
    pub fn with_cancel(mut self, token: CancelToken) -> Self {
        self.cancel = Some(token);
        self
    }
}

impl RunObserver for ProgressObserver {
    fn on_start(&self, total_units: u64) {
        self.bar.set_length(total_units);
    }
    fn on_units_done(&self, n: u64) {
        self.bar.inc(n);
    }
    fn on_finish(&self) {
        self.bar.finish_and_clear();
    }
    fn cancelled(&self) -> bool {
        self.cancel.as_ref().is_some_and(CancelToken::is_cancelled)
    }
}

/// A spinner over an optimiser's iterations (`kfmc tune --method ml`): the start, the
/// iteration and the objective; hidden as [`ProgressObserver`] is.
pub struct IterationProgress {
    bar: ProgressBar,
}

impl IterationProgress {
    /// A spinner that draws only when `visible` and stderr is a terminal.
    pub fn new(visible: bool) -> Self {
        let bar = ProgressBar::with_draw_target(
            None,
            if visible && std::io::stderr().is_terminal() {
                ProgressDrawTarget::stderr()
            } else {
                ProgressDrawTarget::hidden()
            },
        );
        bar.set_style(
            ProgressStyle::with_template("{elapsed_precise} {spinner} {msg}")
                .expect("the template is valid"),
        );
        IterationProgress { bar }
    }

    /// Shows one iteration.
    pub fn show(&self, start: usize, iteration: usize, objective: f64) {
        self.bar.set_message(format!(
            "start {start}, iteration {iteration}: −ln L = {objective:.6}"
        ));
        self.bar.tick();
    }

    /// Clears the spinner.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}
