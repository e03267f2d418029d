//! A request to stop the image loops early, for a host that cannot kill a render: the Python
//! binding sets it when Ctrl-C reaches the interpreter, waits for the loops to drain (the render
//! checks it once per path, the gradient passes once per pixel: within milliseconds), discards
//! what they returned and clears it once no call is left running. The command line never sets
//! it: Ctrl-C ends the process.
//!
//! The request stops every loop of the process, so each request is counted: a caller whose work
//! overlapped one (`generation` changed) knows its result is incomplete even if the request was
//! another thread's.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);
static GENERATION: AtomicU64 = AtomicU64::new(0);

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
    REQUESTED.load(Ordering::Relaxed)
}
