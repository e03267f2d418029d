//! A request to stop the image loops early, for a host that cannot kill a render: the Python
//! binding sets it when Ctrl-C reaches the interpreter, waits for the loops to drain (the render
//! checks it once per path, the gradient passes once per pixel: within milliseconds), discards
//! what they returned and clears it once no call is left running. The command line never sets
//! it: Ctrl-C ends the process, or with `optimize` stops a stoppable stretch (below).
//!
//! The request stops every loop of the process, so each request is counted: a caller whose work
//! overlapped one (`generation` changed) knows its result is incomplete even if the request was
//! another thread's.
//!
//! A stoppable stretch of work (an optimisation's evaluation, which can take minutes) is stopped
//! alone: `stop_stoppable`, which a signal handler may call, cuts its loops and no others, so
//! that a step under way still ends whole.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);
static GENERATION: AtomicU64 = AtomicU64::new(0);

/// The stoppable stretch under way when odd (each begins and ends with an increment), and the
/// stretch a stop was asked for.
static STOPPABLE: AtomicU64 = AtomicU64::new(0);
static STOPPED: AtomicU64 = AtomicU64::new(0);

/// A stoppable stretch of work, from `begin` until dropped; one at a time.
pub struct Stoppable(u64);

impl Stoppable {
    pub fn begin() -> Self {
        Stoppable(STOPPABLE.fetch_add(1, Ordering::SeqCst) + 1)
    }

    /// Whether `stop_stoppable` cut this stretch short.
    pub fn stopped(&self) -> bool {
        STOPPED.load(Ordering::SeqCst) == self.0
    }
}

impl Drop for Stoppable {
    fn drop(&mut self) {
        STOPPABLE.fetch_add(1, Ordering::SeqCst);
    }
}

/// Cuts the stoppable stretch under way short, if any. Async-signal-safe (two atomic operations):
/// a stop that comes as the stretch ends names it, not the work after it.
pub fn stop_stoppable() {
    let stretch = STOPPABLE.load(Ordering::SeqCst);
    if stretch % 2 == 1 {
        STOPPED.store(stretch, Ordering::SeqCst);
    }
}

/// Asks every running image loop to skip its remaining pixels.
pub fn request() {
    GENERATION.fetch_add(1, Ordering::SeqCst);
    REQUESTED.store(true, Ordering::SeqCst);
}

/// Lets image loops run to the end again.
pub fn clear() {
    REQUESTED.store(false, Ordering::SeqCst);
}

/// How many requests there have been: work that saw it change may have skipped pixels.
pub fn generation() -> u64 {
    GENERATION.load(Ordering::SeqCst)
}

/// Whether the loops should skip their remaining work: what they return is then incomplete.
#[inline]
pub fn requested() -> bool {
    let stretch = STOPPABLE.load(Ordering::Relaxed);
    REQUESTED.load(Ordering::Relaxed)
        || (stretch % 2 == 1 && STOPPED.load(Ordering::Relaxed) == stretch)
}
