//! Progress and cancellation for the long calls (tracking a video, rendering a sequence): the
//! library reports through a [`Monitor`] the caller gives it and prints nothing; a caller stops
//! work by answering `true` from [`Monitor::cancelled`] (a [`CancelToken`] does this for another
//! thread, a Ctrl-C handler or a disconnected client).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::error::{AvatarError, Result};

/// What a long call reports while it works. Every method has a do-nothing default. Calls may
/// come from several threads at once (the fit of a video runs beside its cropping).
pub trait Monitor: Sync {
    /// A stage begins (the one before it is over): `total` steps, `None` when not known ahead
    /// (a video whose length its container does not say).
    fn stage(&self, _name: &str, _total: Option<u64>) {}
    /// `steps` more steps of the current stage are done.
    fn advance(&self, _steps: u64) {}
    /// The call is over (successfully or not): a progress display can go.
    fn finish(&self) {}
    /// Polled between steps: `true` stops the call with [`AvatarError::Cancelled`], and what it
    /// was writing is not left behind.
    fn cancelled(&self) -> bool {
        false
    }
}

/// A [`Monitor`] that ignores everything and never cancels.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoMonitor;
impl Monitor for NoMonitor {}

/// A flag that stops a call from elsewhere: clone it, give one clone as the monitor (or ask it
/// from your own monitor's `cancelled`) and call [`CancelToken::cancel`] on another.
#[derive(Debug, Default, Clone)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

impl Monitor for CancelToken {
    fn cancelled(&self) -> bool {
        self.is_cancelled()
    }
}

/// `Err(Cancelled)` once the monitor asks to stop.
pub(crate) fn check(monitor: &dyn Monitor) -> Result<()> {
    if monitor.cancelled() {
        Err(AvatarError::Cancelled)
    } else {
        Ok(())
    }
}

/// Calls [`Monitor::finish`] when dropped, so every way out of a call ends its progress display.
pub(crate) struct Finish<'a>(pub &'a dyn Monitor);
impl Drop for Finish<'_> {
    fn drop(&mut self) {
        self.0.finish();
    }
}
