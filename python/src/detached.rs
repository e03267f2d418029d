//! Long work without the GIL, on a thread count of the caller's choosing, that Ctrl-C stops.
//!
//! The work runs on a scoped thread while the calling thread, which holds no GIL, waits for it
//! and every 50 ms takes the GIL for a moment to let Python run its signal handlers (and, on a
//! thread other than the main one, to see whether a Ctrl-C has ended the main thread). When one
//! raises (Ctrl-C's `KeyboardInterrupt`), the image loops are asked to skip their remaining pixels
//! (`render::interrupt`), the work drains within milliseconds and the exception is raised in its
//! place. The request stops every call under way, in any thread, and each raises: none returns
//! an image with pixels skipped. The last call to drain clears it.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use pyo3::exceptions::{PyKeyboardInterrupt, PyRuntimeError};
use pyo3::prelude::*;
use volgrad::render::interrupt;
use volgrad::render::scene_check::thread_count;

use crate::errors::OrRaise;

const SIGNAL_POLL: Duration = Duration::from_millis(50);

/// The calls under way, of every Python thread.
static RUNNING: AtomicUsize = AtomicUsize::new(0);

/// The pool of calls that name no thread count: rayon's default size, one per process. Not
/// rayon's global pool: a process forked from one that had started it (`multiprocessing`'s
/// default on Linux, a `DataLoader`'s workers) inherits its bookkeeping but none of its threads,
/// and work handed to it would wait forever (rayon-rs/rayon#708). A forked child builds its own,
/// and the parent's, whose threads are not in the child, is left alone rather than shut down.
fn this_process_pool() -> PyResult<Arc<rayon::ThreadPool>> {
    static POOL: Mutex<Option<(u32, Arc<rayon::ThreadPool>)>> = Mutex::new(None);
    let mut pool = POOL.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let pid = std::process::id();
    if let Some((owner, existing)) = pool.as_ref() {
        if *owner == pid {
            return Ok(existing.clone());
        }
        std::mem::forget(pool.take());
    }
    let built =
        Arc::new(rayon::ThreadPoolBuilder::new().build().map_err(|e| {
            PyRuntimeError::new_err(format!("cannot start volgrad's threads: {e}"))
        })?);
    *pool = Some((pid, built.clone()));
    Ok(built)
}

/// Python's signal handlers, run (on the main thread; elsewhere this does nothing), and an error
/// where one raised; or a `KeyboardInterrupt` where the program is ending on one that reached its
/// main thread while this call runs on another (`main_thread_ended_on_ctrl_c`).
fn signals_or_ctrl_c_ending_the_program(py: Python<'_>) -> PyResult<()> {
    py.check_signals()?;
    // A failure to look (modules torn down late in an exit) is not a reason to stop.
    match main_thread_ended_on_ctrl_c(py).unwrap_or(false) {
        true => Err(PyKeyboardInterrupt::new_err(
            "interrupted: Ctrl-C ended the main thread while this call ran on another",
        )),
        false => Ok(()),
    }
}

/// Whether the main thread has ended on a `KeyboardInterrupt`. Python hands Ctrl-C to the main
/// thread alone, and an interpreter whose main thread has ended waits for its other threads
/// before it exits: a Ctrl-C while the main thread slept or (from Python 3.13 on) waited for this
/// one in `thread.join()` ended the main thread and then waited for this call's end.
fn main_thread_ended_on_ctrl_c(py: Python<'_>) -> PyResult<bool> {
    let main = py.import("threading")?.call_method0("main_thread")?;
    if main.call_method0("is_alive")?.is_truthy()? {
        return Ok(false);
    }
    // The exception that ended it, as the interpreter recorded it for the traceback it printed:
    // `sys.last_exc` from 3.12 on, `sys.last_value` before.
    let sys = py.import("sys")?;
    Ok(["last_exc", "last_value"].iter().any(|name| {
        sys.getattr(*name)
            .is_ok_and(|e| e.is_instance_of::<PyKeyboardInterrupt>())
    }))
}

/// Runs `work` without the GIL, on `threads` worker threads (for `None`, the process's pool of
/// rayon's default size).
pub fn run<T: Send>(
    py: Python<'_>,
    threads: Option<usize>,
    work: impl FnOnce() -> anyhow::Result<T> + Send,
) -> PyResult<T> {
    if let Some(n) = threads {
        thread_count("threads", n).or_raise()?;
    }
    let pool = match threads {
        Some(n) => Arc::new(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| PyRuntimeError::new_err(format!("cannot start {n} threads: {e}")))?,
        ),
        None => this_process_pool()?,
    };
    RUNNING.fetch_add(1, Ordering::SeqCst);
    let generation = interrupt::generation();
    let (result, signal) = py.detach(|| {
        std::thread::scope(|scope| {
            let (sender, receiver) = mpsc::channel();
            let worker = scope.spawn(move || {
                let result = pool.install(work);
                // The receiver outlives the scope's threads: sending cannot fail.
                let _ = sender.send(result);
            });
            let mut signal = None;
            let result = loop {
                match receiver.recv_timeout(SIGNAL_POLL) {
                    Ok(result) => break Some(result),
                    Err(mpsc::RecvTimeoutError::Disconnected) => break None,
                    Err(mpsc::RecvTimeoutError::Timeout) if signal.is_none() => {
                        if let Err(e) = Python::attach(signals_or_ctrl_c_ending_the_program) {
                            interrupt::request();
                            signal = Some(e);
                        }
                    }
                    Err(mpsc::RecvTimeoutError::Timeout) => {}
                }
            };
            // A panic in the work ends its thread without a result: joined here, it is reported
            // below as an error instead of unwinding into Python.
            let panicked = worker.join().is_err();
            (result.filter(|_| !panicked), signal)
        })
    });
    // Skipped pixels: an interrupt came (this call's or another's) or is still draining.
    let skipped = interrupt::generation() != generation || interrupt::requested();
    // The request stands until the last running call has drained: cleared earlier, a call still
    // in a pixel would go on to its end.
    if RUNNING.fetch_sub(1, Ordering::SeqCst) == 1 {
        interrupt::clear();
    }
    if let Some(signal) = signal {
        return Err(signal);
    }
    if skipped {
        // Ctrl-C stopped another thread's call while this one ran: its pixels were skipped too.
        return Err(PyKeyboardInterrupt::new_err(
            "interrupted: Ctrl-C stopped every volgrad call running at the time",
        ));
    }
    match result {
        Some(result) => result.or_raise(),
        None => Err(PyRuntimeError::new_err(
            "volgrad failed inside (a panic): please report it with the call that caused it",
        )),
    }
}
