//! A study on its own thread while Python waits: the progress line, Ctrl-C and SIGTERM
//! as cancellation, and the study's panic or result brought back.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use kfmc::runner::{CancelToken, RunObserver};
use pyo3::prelude::*;

use crate::errors::{Error, Failure, panic_message};

/// Counts a study's units for the progress line and carries its cancellation.
#[derive(Default)]
pub(crate) struct Observer {
    token: CancelToken,
    total: AtomicU64,
    done: AtomicU64,
}

impl RunObserver for Observer {
    fn on_start(&self, total_units: u64) {
        // A command may run the executor several times (power's replications): the line
        // counts all of them.
        self.total.fetch_add(total_units, Ordering::Relaxed);
    }
    fn on_units_done(&self, n: u64) {
        self.done.fetch_add(n, Ordering::Relaxed);
    }
    fn cancelled(&self) -> bool {
        self.token.is_cancelled()
    }
}

/// Progress written through Python's `sys.stderr` (so a terminal and a Jupyter cell both
/// show it). Where the stream redraws (a terminal, a Jupyter cell) one line is redrawn in
/// place with `\r`; elsewhere (a log file, CI) plain lines come at long intervals, since a
/// `\r` there only piles redraws into one unreadable line.
struct Progress {
    started: Instant,
    last: Option<Instant>,
    shown: bool,
    redraw: bool,
}

/// How often each kind of stream gets a new line.
const REDRAW_EVERY: Duration = Duration::from_millis(250);
const LINE_EVERY: Duration = Duration::from_secs(10);

impl Progress {
    fn new(py: Python<'_>) -> Self {
        Progress {
            started: Instant::now(),
            last: None,
            shown: false,
            redraw: redraws(py),
        }
    }

    fn show(&mut self, py: Python<'_>, obs: &Observer, last: bool) {
        let now = Instant::now();
        let every = if self.redraw {
            REDRAW_EVERY
        } else {
            LINE_EVERY
        };
        if !last && self.last.is_some_and(|t| now - t < every) {
            return;
        }
        let (done, total) = (
            obs.done.load(Ordering::Relaxed),
            obs.total.load(Ordering::Relaxed),
        );
        let elapsed = (now - self.started).as_secs_f64();
        // A study done within half a second (a second without redraws) draws nothing: a
        // loop of short calls stays quiet. A log still gets the last line, so that it
        // records what ran whatever the machine's speed.
        let quiet_for = if self.redraw { 0.5 } else { 1.0 };
        let logged_end = last && !self.redraw;
        if total == 0 || (!self.shown && elapsed < quiet_for && !logged_end) {
            return;
        }
        self.last = Some(now);
        let (start, end) = if self.redraw { ("\r", "") } else { ("", "\n") };
        let text = if last {
            if !self.shown && self.redraw {
                return;
            }
            format!("{start}{done}/{total} runs in {elapsed:.1} s\n")
        } else {
            let rate = done as f64 / elapsed.max(1e-9);
            let eta = if done == 0 {
                "?".to_string()
            } else {
                format!("{:.0} s", total.saturating_sub(done) as f64 / rate)
            };
            format!("{start}{done}/{total} runs  {rate:.0} runs/s  {elapsed:.0} s  ETA {eta}{end}")
        };
        self.shown = true;
        // Progress is best effort: a closed or replaced stderr does not stop the study.
        if let Ok(stderr) = py.import("sys").and_then(|s| s.getattr("stderr")) {
            let _ = stderr.call_method1("write", (text,));
            let _ = stderr.call_method0("flush");
        }
    }
}

/// Whether Python's `sys.stderr` redraws a `\r` line in place: a terminal, or a Jupyter
/// cell's stream (ipykernel's, which is not a tty).
fn redraws(py: Python<'_>) -> bool {
    let Ok(stderr) = py.import("sys").and_then(|s| s.getattr("stderr")) else {
        return false;
    };
    let tty = stderr
        .call_method0("isatty")
        .and_then(|t| t.extract::<bool>())
        .unwrap_or(false);
    let jupyter = stderr
        .get_type()
        .getattr("__module__")
        .and_then(|m| m.extract::<String>())
        .is_ok_and(|m| m.starts_with("ipykernel"));
    tty || jupyter
}

/// Runs `job` on its own thread while the caller waits in released-GIL slices; between
/// slices Python's signal handlers run (`py.check_signals`), and an exception there (Ctrl-C's
/// `KeyboardInterrupt`) cancels the study, which stops at its next window (keeping its
/// checkpoint). SIGTERM does the same ([`SigtermStop`]) and then ends the process as SIGTERM
/// would have. What is raised depends on what the study did, not on when the signal came:
/// a study that committed its tables before it saw the request returns its result (the
/// interrupt is taken and dropped), one that was stopped raises the interrupt.
pub(crate) fn run_study<T: Send + 'static>(
    py: Python<'_>,
    quiet: bool,
    job: impl FnOnce(&Observer) -> Result<T, Failure> + Send + 'static,
) -> PyResult<T> {
    let observer = Arc::new(Observer::default());
    let theirs = observer.clone();
    let handle = std::thread::Builder::new()
        .name("kfmc-study".into())
        .spawn(move || job(&theirs))
        .map_err(|e| Error::new_err(format!("cannot start the study's thread: {e}")))?;
    // Best effort: without it SIGTERM keeps Python's default (the process ends at once).
    let sigterm = SigtermStop::install(py).ok().flatten();
    let mut progress = (!quiet).then(|| Progress::new(py));
    let mut interrupt: Option<PyErr> = None;
    loop {
        let finished = py.detach(|| {
            let until = Instant::now() + Duration::from_millis(100);
            while !handle.is_finished() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(5));
            }
            handle.is_finished()
        });
        if finished {
            break;
        }
        if interrupt.is_none()
            && let Err(e) = py.check_signals()
        {
            observer.token.cancel();
            interrupt = Some(e);
        }
        if let Some(p) = progress.as_mut() {
            p.show(py, &observer, false);
        }
    }
    let joined = py.detach(|| handle.join());
    // A signal that came while the study was finishing is taken here, where what the study
    // did is known, rather than raised by Python as soon as this returns.
    if interrupt.is_none()
        && let Err(e) = py.check_signals()
    {
        interrupt = Some(e);
    }
    let terminated = sigterm.map(|s| s.restore(py)).transpose()?.unwrap_or(false);
    if let Some(p) = progress.as_mut() {
        p.show(py, &observer, true);
    }
    let result = match joined {
        Ok(r) => r,
        Err(panic) => {
            return Err(Error::new_err(format!(
                "internal error in kfmc (please report it): {}",
                panic_message(&*panic)
            )));
        }
    };
    if terminated {
        // Stopped cleanly or committed: now end as SIGTERM asked, with its default action.
        py.import("signal")?
            .call_method1("raise_signal", (sigterm_number(py)?,))?;
        // Still here (the signal blocked): say so as an exit would.
        return Err(pyo3::exceptions::PySystemExit::new_err(128 + 15));
    }
    match (result, interrupt) {
        // Committed: a KeyboardInterrupt that came too late to stop it is dropped; any other
        // exception a signal handler raised (a `SystemExit`, say) is the caller's.
        (Ok(r), Some(e)) if e.is_instance_of::<pyo3::exceptions::PyKeyboardInterrupt>(py) => Ok(r),
        (Ok(r), None) => Ok(r),
        (_, Some(e)) => Err(e),
        (Err(f), None) => Err(f.into_py()),
    }
}

/// SIGTERM's number, from Python's `signal` module.
fn sigterm_number(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    py.import("signal")?.getattr("SIGTERM")
}

/// While a study runs, SIGTERM stops it as Ctrl-C does (its handler raises
/// `KeyboardInterrupt` where `run_study` checks signals, and records that it came), so that
/// a terminated Python process leaves a final checkpoint and no partial files instead of
/// dying mid-write. Installed only over SIGTERM's default action and only on the main
/// thread (where Python runs handlers); a handler of the caller's own is left alone.
struct SigtermStop {
    came: Arc<std::sync::atomic::AtomicBool>,
}

impl SigtermStop {
    fn install(py: Python<'_>) -> PyResult<Option<SigtermStop>> {
        let threading = py.import("threading")?;
        let main = threading
            .call_method0("current_thread")?
            .is(&threading.call_method0("main_thread")?);
        let signal = py.import("signal")?;
        let sigterm = signal.getattr("SIGTERM")?;
        if !main
            || !signal
                .call_method1("getsignal", (&sigterm,))?
                .eq(signal.getattr("SIG_DFL")?)?
        {
            return Ok(None);
        }
        let came = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = came.clone();
        let handler = pyo3::types::PyCFunction::new_closure(
            py,
            Some(c"kfmc_sigterm"),
            None,
            move |_, _| -> PyResult<()> {
                flag.store(true, Ordering::SeqCst);
                Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
                    "SIGTERM: the study was stopped",
                ))
            },
        )?;
        signal.call_method1("signal", (&sigterm, handler))?;
        Ok(Some(SigtermStop { came }))
    }

    /// Puts SIGTERM's default action back; returns whether SIGTERM came meanwhile.
    fn restore(self, py: Python<'_>) -> PyResult<bool> {
        let signal = py.import("signal")?;
        signal.call_method1(
            "signal",
            (signal.getattr("SIGTERM")?, signal.getattr("SIG_DFL")?),
        )?;
        Ok(self.came.load(Ordering::SeqCst))
    }
}
