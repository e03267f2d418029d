//! A request to stop the image loops early, for a host that cannot kill a render: the Python
//! binding sets it when Ctrl-C reaches the interpreter, waits for the loops to drain (each
//! checks it once per pixel or unit of pixels, so within milliseconds), then clears it and
//! discards what they returned. The command line never sets it: Ctrl-C ends the process.

use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);

/// Asks every running image loop to skip its remaining pixels.
pub fn request() {
    REQUESTED.store(true, Ordering::SeqCst);
}

/// Lets image loops run to the end again.
pub fn clear() {
    REQUESTED.store(false, Ordering::SeqCst);
}

/// Whether the loops should skip their remaining work: what they return is then incomplete.
#[inline]
pub fn requested() -> bool {
    REQUESTED.load(Ordering::Relaxed)
}
