//! The progress bar (stderr, terminals only) and `--timings` (each pipeline stage's wall time):
//! the pipeline's progress callbacks in, lines on stderr out. The only place that draws one.

use std::io::IsTerminal;

// ---- progress -----------------------------------------------------------------------------

pub(super) struct Bar(Option<indicatif::ProgressBar>);

impl Bar {
    pub(super) fn new(quiet: bool, label: &'static str) -> Self {
        if quiet || !std::io::stderr().is_terminal() {
            return Bar(None);
        }
        let pb = indicatif::ProgressBar::with_draw_target(
            Some(0),
            indicatif::ProgressDrawTarget::stderr(),
        );
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{msg:>10} [{bar:40}] {percent:>3}% {elapsed}/{eta}",
        ) {
            pb.set_style(style.progress_chars("=> "));
        }
        pb.set_message(label);
        Bar(Some(pb))
    }
}

impl crate::sample::Progress for Bar {
    fn start(&self, total: u64) {
        if let Some(p) = &self.0 {
            p.set_length(total);
        }
    }
    fn inc(&self, n: u64) {
        if let Some(p) = &self.0 {
            p.inc(n);
        }
    }
    fn finish(&self) {
        if let Some(p) = &self.0 {
            p.finish_and_clear();
        }
    }
}

/// `--timings`: the wall time of every pipeline stage on stderr, passing the progress
/// callbacks on to the bar.
pub(super) struct Timed<'a> {
    inner: &'a dyn crate::sample::Progress,
    on: bool,
    t0: std::time::Instant,
    stage: std::sync::Mutex<(std::time::Instant, &'static str)>,
}

impl<'a> Timed<'a> {
    /// Timing from `t0`, in the stage `first`.
    pub(super) fn new(
        inner: &'a dyn crate::sample::Progress,
        on: bool,
        first: &'static str,
        t0: std::time::Instant,
    ) -> Self {
        Timed {
            inner,
            on,
            t0,
            stage: std::sync::Mutex::new((t0, first)),
        }
    }

    /// Ends the current stage (printing its time) and starts `next`.
    pub(super) fn next(&self, next: &'static str) {
        if !self.on {
            return;
        }
        let now = std::time::Instant::now();
        let mut st = self.stage.lock().unwrap_or_else(|e| e.into_inner());
        eprintln!(
            "edbbgen: timing: {:<22}{:>8.3} s",
            st.1,
            (now - st.0).as_secs_f64()
        );
        *st = (now, next);
    }

    /// Ends the last stage and prints the total.
    pub(super) fn done(&self) {
        if self.on {
            self.next("");
            eprintln!(
                "edbbgen: timing: {:<22}{:>8.3} s",
                "total",
                self.t0.elapsed().as_secs_f64()
            );
        }
    }
}

impl crate::sample::Progress for Timed<'_> {
    fn stage(&self, name: &'static str) {
        self.next(name);
        self.inner.stage(name);
    }
    fn start(&self, total: u64) {
        self.inner.start(total);
    }
    fn inc(&self, n: u64) {
        self.inner.inc(n);
    }
    fn finish(&self) {
        self.inner.finish();
    }
}
