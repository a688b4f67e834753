//! `dronerace bench tracks`: what generating a track and one task-controller update cost.

use std::sync::Arc;
use std::time::{Duration, Instant};

use racetracks::{GenerateError, GeneratorKind, TrackGenParams, TrackGenerator};

use crate::{SwitchParams, TaskController, TaskError};

/// One generator's speed and acceptance.
#[derive(Clone, Copy, Debug)]
pub struct GeneratorTiming {
    /// The generator.
    pub kind: GeneratorKind,
    /// Tracks generated (seeds 0..count).
    pub tracks: usize,
    /// Candidates drawn for them.
    pub candidates: usize,
    /// Wall seconds on one thread.
    pub seconds: f64,
}

/// The task controller's cost per update with every window full.
#[derive(Clone, Copy, Debug)]
pub struct UpdateTiming {
    /// Seconds per update of every environment's report (new tracks generated included).
    pub seconds: f64,
    /// Switches made in all the iterations.
    pub switches: usize,
    /// Iterations run (the timed ones follow the first `window`).
    pub iterations: u64,
}

impl std::fmt::Display for GeneratorTiming {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (n, seconds, candidates) = (self.tracks, self.seconds, self.candidates);
        write!(
            f,
            "{:?} generator: {:.0} tracks/s on one thread ({n} tracks in {seconds:.2} s), acceptance {:.1} % ({n} of {candidates} candidates)",
            self.kind,
            n as f64 / seconds,
            100.0 * n as f64 / candidates as f64
        )
    }
}

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum TrackBenchError {
    /// Nothing to measure.
    #[error("--count, --envs must be ≥ 1 and --window ≥ 2")]
    Empty,
    /// A generator found no track for a seed.
    #[error(transparent)]
    Generate(#[from] GenerateError),
    /// The library could not be read.
    #[error(transparent)]
    Library(#[from] racetracks::TrackFileError),
    /// The task controller refused a report.
    #[error(transparent)]
    Task(#[from] TaskError),
}

/// Generates `count` tracks with each generator, on one thread.
pub fn time_generators(count: usize) -> Result<Vec<GeneratorTiming>, TrackBenchError> {
    if count == 0 {
        return Err(TrackBenchError::Empty);
    }
    let mut timings = Vec::new();
    for kind in [GeneratorKind::Informed, GeneratorKind::Uniform] {
        let generator = TrackGenerator { kind, params: TrackGenParams::default() };
        let started = Instant::now();
        let mut candidates = 0;
        for seed in 0..count as u64 {
            candidates += generator.generate(seed, "bench")?.attempts;
        }
        timings.push(GeneratorTiming { kind, tracks: count, candidates, seconds: started.elapsed().as_secs_f64() });
    }
    Ok(timings)
}

/// Times 200 updates of a controller of `envs` environments whose switching windows of `window`
/// iterations are full: rewards of a flat curve with noise keep every window scored every time.
pub fn time_updates(envs: usize, window: usize) -> Result<UpdateTiming, TrackBenchError> {
    if envs == 0 || window < 2 {
        return Err(TrackBenchError::Empty);
    }
    const TIMED: u64 = 200;
    let switching = SwitchParams { window, ..SwitchParams::default() };
    let first = Arc::new(racetracks::library()?.swap_remove(0));
    let tracks = std::iter::repeat_n(first, envs).collect();
    let mut controller = TaskController::with_tracks(tracks, TrackGenerator::default(), switching, 0)?;
    let iterations = window as u64 + TIMED;
    let mut timed = Duration::ZERO;
    for iteration in 0..iterations {
        let started = Instant::now();
        for env in 0..envs {
            let noise = crate::switching::uniform(1, env as u64, iteration);
            controller.report(env, iteration, 100.0 + noise)?;
        }
        if iteration >= window as u64 {
            timed += started.elapsed();
        }
    }
    Ok(UpdateTiming { seconds: timed.as_secs_f64() / TIMED as f64, switches: controller.history().len(), iterations })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_generated_track_is_counted_and_full_windows_are_scored() {
        let timings = time_generators(3).expect("generates");
        assert_eq!(timings.len(), 2);
        assert!(timings.iter().all(|t| t.tracks == 3 && t.candidates >= 3));
        let updates = time_updates(2, 3).expect("updates");
        assert_eq!(updates.iterations, 203);
        assert!(matches!(time_updates(2, 1), Err(TrackBenchError::Empty)));
    }
}
