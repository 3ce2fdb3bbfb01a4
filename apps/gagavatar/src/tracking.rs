//! Tracking as the commands show it: the library's tracker and cache (`gagavatar_avatar::
//! tracking`, `gagavatar_avatar::cache`) with progress bars and Ctrl-C, and one line of report.

use std::path::Path;
use std::sync::Mutex;

use anyhow::Result;
use gagavatar_avatar::cache::{TrackTo, Tracked};
use gagavatar_avatar::tracking::VideoSummary;
use gagavatar_avatar::{Engine, FlameSource, Monitor, Tracker};
use indicatif::ProgressBar;

pub use gagavatar_avatar::cache::is_tracked_folder;
pub use gagavatar_avatar::tracking::{input_kind, median, InputKind};

use crate::progress::{progress, spinner};

/// Progress bars on stderr, one per stage, and Ctrl-C as cancellation.
#[derive(Default)]
pub struct Bars {
    bar: Mutex<Option<ProgressBar>>,
}

impl Bars {
    fn slot(&self) -> std::sync::MutexGuard<'_, Option<ProgressBar>> {
        self.bar.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl Monitor for Bars {
    fn stage(&self, name: &str, total: Option<u64>) {
        let bar = match total {
            Some(n) => progress(n as usize, name),
            None => spinner(name),
        };
        if let Some(old) = self.slot().replace(bar) {
            old.finish_and_clear();
        }
    }
    fn advance(&self, steps: u64) {
        if let Some(b) = self.slot().as_ref() {
            b.inc(steps);
        }
    }
    fn finish(&self) {
        if let Some(b) = self.slot().take() {
            b.finish_and_clear();
        }
    }
    fn cancelled(&self) -> bool {
        crate::interrupted()
    }
}

/// The tracker for the FLAME on the command line (`synthetic` or a file).
pub fn tracker_for(flame: &Path) -> Result<Tracker> {
    Ok(Tracker::new(&FlameSource::from_arg(flame))?)
}

/// Tracks `input` with the engine's FLAME into the cache, or finds the folder a previous run
/// made for the same bytes; says which on stderr. `what` names the input (`source`, `driver`);
/// with `photo_only`, anything but a photo is refused.
pub fn tracked_inline(
    engine: &Engine,
    input: &Path,
    what: &str,
    photo_only: bool,
) -> Result<Tracked> {
    let t = engine.track_as(input, &TrackTo::Cache, what, photo_only, &Bars::default())?;
    report_tracked(what, input, &t);
    Ok(t)
}

fn report_tracked(what: &str, input: &Path, t: &Tracked) {
    let n = t.records.len();
    if t.cached {
        eprintln!(
            "{what}: using the cached tracking of {} ({}, {n} frame{})",
            input.display(),
            t.dir.display(),
            if n == 1 { "" } else { "s" }
        );
        return;
    }
    if let Some(s) = &t.video {
        report_video(input, s);
    }
    eprintln!(
        "{what}: tracked {} in {:.1} s (cached in {})",
        input.display(),
        t.seconds,
        t.dir.display()
    );
}

pub fn report_video(input: &Path, s: &VideoSummary) {
    let rms: Vec<f64> = s.video.frames.iter().filter_map(|f| f.fit_rms_px).collect();
    eprintln!(
        "{}: {} frames at {} fps, {} without a face (filled from their neighbours), shape from \
         keyframes {:?}, median landmark RMS {:.2} px at 512",
        input.display(),
        s.frames,
        s.fps,
        s.no_face,
        s.video.keyframes,
        median(&rms)
    );
}
