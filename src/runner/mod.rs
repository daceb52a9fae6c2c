//! The runner role: a parallel executor that knows nothing about models, filters or metrics.
//!
//! Units run on a rayon pool in windows; each window's results are handed to a sink **in unit
//! order**. Because every unit is computed independently from its own seed and the sink folds
//! in a fixed order, the output is bit-identical for any thread count, while only one window
//! of results is in memory at a time.

pub mod lanes;

use rayon::prelude::*;

use crate::error::KfmcError;

/// Progress notifications (argmin's observers). Only the CLI's implementation draws a bar.
pub trait RunObserver: Sync {
    /// Before the first unit: how many there are.
    fn on_start(&self, _total_units: u64) {}
    /// After `n` more units finished (called from worker threads).
    fn on_units_done(&self, _n: u64) {}
    /// After the last unit.
    fn on_finish(&self) {}
    /// Whether the caller asked this run to stop (a [`CancelToken`] it holds): polled by the
    /// executor between windows exactly as a signal is, so a cancelled study stops with the
    /// same checkpoint semantics as an interrupted one, without any process-wide handler.
    fn cancelled(&self) -> bool {
        false
    }
}

/// A per-study stop request: an embedding (the Python module) cancels one study through it
/// instead of installing signal handlers for the whole process. Clones share the request.
#[derive(Clone, Debug, Default)]
pub struct CancelToken(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl CancelToken {
    /// A token nobody has cancelled yet.
    pub fn new() -> Self {
        Self::default()
    }
    /// Asks the study holding this token to stop at its next window.
    pub fn cancel(&self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    /// Whether [`CancelToken::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// An observer that ignores everything (tests, library use).
pub struct NullObserver;
impl RunObserver for NullObserver {}

static INTERRUPTED: std::sync::OnceLock<std::sync::Arc<std::sync::atomic::AtomicBool>> =
    std::sync::OnceLock::new();

/// Whether no [`StopSection`] is open: a signal then ends the process at once.
fn outside_sections() -> &'static std::sync::Arc<std::sync::atomic::AtomicBool> {
    static OUTSIDE: std::sync::OnceLock<std::sync::Arc<std::sync::atomic::AtomicBool>> =
        std::sync::OnceLock::new();
    OUTSIDE.get_or_init(|| std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true)))
}

/// The open [`StopSection`]s.
static SECTIONS: std::sync::Mutex<usize> = std::sync::Mutex::new(0);

/// Makes SIGINT and SIGTERM request a clean stop while a [`StopSection`] is open (a command
/// writing into a folder it holds): the executor finishes the window in flight, returns
/// [`crate::error::OutputError::Interrupted`], and every partial file is removed as the
/// study unwinds. With no section open (reading a spec or estimates, designing a gate,
/// drawing figures) the loops that would see the request are not running and there is
/// nothing to clean up: the process exits at once with status 130, so that no wait, however
/// long or blocked, makes it deaf. A second signal while stopping also exits at once.
///
/// The signals are taken by a thread of their own (not in a signal handler), which may
/// print and exit safely.
pub fn stop_on_signals() {
    static WATCHING: std::sync::Once = std::sync::Once::new();
    WATCHING.call_once(|| {
        let flag = INTERRUPTED.get_or_init(Default::default).clone();
        let sigs = [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM];
        let watcher = signal_hook::iterator::Signals::new(sigs).and_then(|mut signals| {
            std::thread::Builder::new()
                .name("kfmc-signals".into())
                .spawn(move || {
                    for _ in signals.forever() {
                        let again = flag.swap(true, std::sync::atomic::Ordering::SeqCst);
                        if again || outside_sections().load(std::sync::atomic::Ordering::SeqCst) {
                            eprintln!(
                                "error: interrupted{}",
                                if again {
                                    " again while stopping; exiting at once"
                                } else {
                                    " (no output folder was being written)"
                                }
                            );
                            std::process::exit(130);
                        }
                    }
                })
        });
        if watcher.is_err() {
            // No thread: the flag alone, and a second signal's default action.
            let flag = INTERRUPTED.get_or_init(Default::default);
            for sig in sigs {
                let _ = signal_hook::flag::register_conditional_default(sig, flag.clone());
                let _ = signal_hook::flag::register(sig, flag.clone());
            }
        }
    });
}

/// While one is held, a signal asks for a clean stop ([`stop_on_signals`]); the holder
/// must then see [`interrupted`] within moments (the executor does between windows).
/// Sections nest; the last one dropped makes signals end the process at once again.
#[must_use = "the section ends when this is dropped"]
#[derive(Debug)]
pub struct StopSection(());

impl StopSection {
    /// Opens a section.
    pub fn open() -> StopSection {
        let mut open = SECTIONS.lock().unwrap_or_else(|e| e.into_inner());
        *open += 1;
        outside_sections().store(false, std::sync::atomic::Ordering::SeqCst);
        StopSection(())
    }
}

impl Drop for StopSection {
    fn drop(&mut self) {
        let mut open = SECTIONS.lock().unwrap_or_else(|e| e.into_inner());
        *open = open.saturating_sub(1);
        if *open == 0 {
            outside_sections().store(true, std::sync::atomic::Ordering::SeqCst);
        }
    }
}

/// Whether a stop was requested by a signal.
pub fn interrupted() -> bool {
    INTERRUPTED
        .get()
        .is_some_and(|f| f.load(std::sync::atomic::Ordering::Relaxed))
}

/// Units per window: large enough to keep every core busy, small enough to bound memory.
const WINDOW: usize = 256;

/// Bytes of results one window may hold. Up to three windows are alive at once (being run,
/// queued, being folded), so results that keep a run's trajectories (every run of `kfmc
/// run --export-estimates` or `kfmc simulate`) stay near 100 MB whatever the run count.
pub const WINDOW_BYTES: u64 = 32 << 20;

/// Units per window when each unit's result holds about `unit_bytes` bytes: at most
/// `WINDOW`, at most `WINDOW_BYTES` of results, and never fewer than the threads (0 =
/// all cores) so that every core has a unit. The window does not change any result, only
/// how many are held at once.
pub fn window_for(unit_bytes: u64, threads: usize) -> usize {
    let threads = if threads == 0 {
        default_threads()
    } else {
        threads
    };
    let fit = usize::try_from(WINDOW_BYTES / unit_bytes.max(1)).unwrap_or(WINDOW);
    fit.clamp(threads.clamp(1, WINDOW), WINDOW)
}

/// Runs `work(i)` for every unit index `i` in `0..units` on `threads` threads (0 = all
/// cores) and feeds each result to `sink` in index order. Units are indices, not a list, so
/// nothing here grows with the number of runs.
///
/// The sink runs on its own thread, one window behind the workers: folding and Parquet
/// encoding overlap the next window's runs instead of leaving the pool idle, and the order
/// the sink sees never changes.
pub fn execute<R, E>(
    units: usize,
    threads: usize,
    work: impl Fn(usize) -> R + Sync,
    observer: &dyn RunObserver,
    sink: impl FnMut(R) -> Result<(), E> + Send,
) -> Result<(), E>
where
    R: Send,
    E: From<KfmcError> + Send,
{
    execute_windowed(units, threads, WINDOW, work, observer, sink)
}

/// [`execute`] with `window` units per window ([`window_for`]).
pub fn execute_windowed<R, E>(
    units: usize,
    threads: usize,
    window: usize,
    work: impl Fn(usize) -> R + Sync,
    observer: &dyn RunObserver,
    sink: impl FnMut(R) -> Result<(), E> + Send,
) -> Result<(), E>
where
    R: Send,
    E: From<KfmcError> + Send,
{
    let executor = Executor::new(threads, window, observer, units as u64)?;
    let result = executor.run(0..units, work, sink);
    executor.finish();
    result
}

/// One pool and one observer for several batches of units run one after the other (a
/// sequential study decides between its looks which runs come next): the observer sees one
/// start and one finish, and the batches share the pool instead of building one each.
pub struct Executor<'o> {
    pool: rayon::ThreadPool,
    window: usize,
    observer: &'o dyn RunObserver,
}

impl<'o> Executor<'o> {
    /// A pool of `threads` threads (0 = all cores) running `window` units per window, for at
    /// most `total_units` units (what the observer is told to expect).
    pub fn new(
        threads: usize,
        window: usize,
        observer: &'o dyn RunObserver,
        total_units: u64,
    ) -> Result<Self, KfmcError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|source| KfmcError::ThreadPool { threads, source })?;
        observer.on_start(total_units);
        Ok(Executor {
            pool,
            window: window.max(1),
            observer,
        })
    }

    /// Tells the observer that `n` expected units will not be run (a batch the caller
    /// decided to skip), so its rate and ETA stay true.
    pub fn skip(&self, n: u64) {
        if n > 0 {
            self.observer.on_units_done(n);
        }
    }

    /// After the last batch.
    pub fn finish(self) {
        self.observer.on_finish();
    }

    /// Runs `work(i)` for every `i` of `units` and feeds each result to `sink` in index
    /// order, returning once the sink has taken the last one.
    ///
    /// The sink runs on its own thread, one window behind the workers: folding and Parquet
    /// encoding overlap the next window's runs instead of leaving the pool idle, and the
    /// order the sink sees never changes.
    pub fn run<R, E>(
        &self,
        units: std::ops::Range<usize>,
        work: impl Fn(usize) -> R + Sync,
        sink: impl FnMut(R) -> Result<(), E> + Send,
    ) -> Result<(), E>
    where
        R: Send,
        E: From<KfmcError> + Send,
    {
        self.run_groups(units, 1, 1, |g| g.map(&work).collect(), sink)
    }

    /// [`Executor::run`] in groups: `work(g)` runs the units of group `g` (up to `width`
    /// consecutive runs of one cell, [`lanes::groups`], for `runs` runs per cell) and returns
    /// one result per unit, in order. A group never crosses a window, so a checkpoint or a
    /// shard boundary (always at a cell) never splits one; the sink still sees every unit's
    /// result in index order.
    pub fn run_groups<R, E>(
        &self,
        units: std::ops::Range<usize>,
        runs: usize,
        width: usize,
        work: impl Fn(std::ops::Range<usize>) -> Vec<R> + Sync,
        mut sink: impl FnMut(R) -> Result<(), E> + Send,
    ) -> Result<(), E>
    where
        R: Send,
        E: From<KfmcError> + Send,
    {
        let (pool, observer, window_units) = (&self.pool, self.observer, self.window);
        let failed = std::sync::atomic::AtomicBool::new(false);
        std::thread::scope(|scope| {
            // One window in flight towards the sink bounds memory at two windows.
            let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Vec<R>>>(1);
            let failed = &failed;
            let consumer = scope.spawn(move || {
                for window in rx {
                    for r in window.into_iter().flatten() {
                        if let Err(e) = sink(r) {
                            failed.store(true, std::sync::atomic::Ordering::Relaxed);
                            return Err(e);
                        }
                    }
                }
                Ok(())
            });
            let mut stopped = false;
            for start in units.clone().step_by(window_units) {
                if failed.load(std::sync::atomic::Ordering::Relaxed) {
                    break;
                }
                if interrupted() || observer.cancelled() {
                    stopped = true;
                    break;
                }
                let window = start..(start + window_units).min(units.end);
                let groups: Vec<_> = lanes::groups(window, runs, width).collect();
                let results: Vec<Vec<R>> = pool.install(|| {
                    groups
                        .into_par_iter()
                        .map(|g| {
                            let n = g.len();
                            let r = work(g);
                            debug_assert_eq!(r.len(), n, "one result per unit of a group");
                            observer.on_units_done(n as u64);
                            r
                        })
                        .collect()
                });
                if tx.send(results).is_err() {
                    break; // the sink stopped on an error; it reports it below
                }
            }
            drop(tx);
            let sunk = consumer
                .join()
                .unwrap_or_else(|p| std::panic::resume_unwind(p));
            match (sunk, stopped) {
                (Ok(()), true) => Err(E::from(KfmcError::Output(
                    crate::error::OutputError::Interrupted,
                ))),
                (r, _) => r,
            }
        })
    }
}

/// [`execute_windowed`] in groups ([`Executor::run_groups`]): `work(g)` returns one result
/// per unit of group `g`.
pub fn execute_groups<R, E>(
    units: usize,
    threads: usize,
    window: usize,
    (runs, width): (usize, usize),
    work: impl Fn(std::ops::Range<usize>) -> Vec<R> + Sync,
    observer: &dyn RunObserver,
    sink: impl FnMut(R) -> Result<(), E> + Send,
) -> Result<(), E>
where
    R: Send,
    E: From<KfmcError> + Send,
{
    let executor = Executor::new(threads, window, observer, units as u64)?;
    let result = executor.run_groups(0..units, runs, width, work, sink);
    executor.finish();
    result
}

/// The number of worker threads `threads = 0` resolves to.
pub fn default_threads() -> usize {
    rayon::current_num_threads()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_holds_about_window_bytes_of_results_and_a_unit_per_thread() {
        // Runs that keep no trajectory: the full window.
        assert_eq!(window_for(0, 2), WINDOW);
        // An exported planar run (1,001 samples × 155 values): 27 of them fill 32 MiB.
        assert_eq!(window_for(1001 * 8 * 155, 2), 27);
        // Huge units: one per thread, never none.
        assert_eq!(window_for(u64::MAX, 8), 8);
        assert_eq!(window_for(u64::MAX, 1000), WINDOW);
    }

    #[test]
    fn results_arrive_in_unit_order_for_any_thread_count() {
        let units: Vec<usize> = (0..2000).collect();
        for threads in [1, 2, 3] {
            let mut seen = Vec::new();
            execute::<_, KfmcError>(
                units.len(),
                threads,
                |u| u * 3,
                &NullObserver,
                |r| {
                    seen.push(r);
                    Ok(())
                },
            )
            .unwrap();
            assert_eq!(seen, units.iter().map(|u| u * 3).collect::<Vec<_>>());
        }
        // Any window size, down to one unit, gives the same order.
        for window in [1, 7, 1000] {
            let mut seen = Vec::new();
            execute_windowed::<_, KfmcError>(
                units.len(),
                2,
                window,
                |u| u * 3,
                &NullObserver,
                |r| {
                    seen.push(r);
                    Ok(())
                },
            )
            .unwrap();
            assert_eq!(seen, units.iter().map(|u| u * 3).collect::<Vec<_>>());
        }
    }

    #[test]
    fn groups_reach_the_sink_in_unit_order_and_never_cross_a_cell() {
        let mut seen = Vec::new();
        execute_groups::<_, KfmcError>(
            50,
            2,
            16,
            (7, 4),
            |g| {
                // Every unit of a group is of one cell (7 runs per cell).
                assert!(g.clone().all(|u| u / 7 == g.start / 7), "{g:?}");
                assert!(g.len() <= 4);
                g.map(|u| u * 3).collect()
            },
            &NullObserver,
            |r| {
                seen.push(r);
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(seen, (0..50).map(|u| u * 3).collect::<Vec<_>>());
    }

    /// Cancels its token once `after` units are done.
    struct CancelAfter {
        token: CancelToken,
        done: std::sync::atomic::AtomicU64,
        after: u64,
    }
    impl RunObserver for CancelAfter {
        fn on_units_done(&self, n: u64) {
            let done = self.done.fetch_add(n, std::sync::atomic::Ordering::Relaxed) + n;
            if done >= self.after {
                self.token.cancel();
            }
        }
        fn cancelled(&self) -> bool {
            self.token.is_cancelled()
        }
    }

    #[test]
    fn a_cancelled_token_stops_the_run_between_windows_as_a_signal_does() {
        let observer = CancelAfter {
            token: CancelToken::new(),
            done: Default::default(),
            after: 10,
        };
        let mut seen = Vec::new();
        let result = execute_windowed::<_, KfmcError>(
            1000,
            1,
            4,
            |u| u,
            &observer,
            |r| {
                seen.push(r);
                Ok(())
            },
        );
        assert!(matches!(
            result,
            Err(KfmcError::Output(crate::error::OutputError::Interrupted))
        ));
        // The window in flight when the token was cancelled (units 8..12) still reaches the
        // sink, in order; nothing after it is run.
        assert_eq!(seen, (0..12).collect::<Vec<_>>());
        assert!(!interrupted(), "no process-wide flag was set");
    }
}
