//! Evaluation during training on the validation set: every `every` iterations the current
//! policy's mean action flies the SPEC §9 protocol (fewer deployments) on generated tracks from
//! the validation seed range, which neither training nor the test set ever uses. The last
//! validated policies, averaged, are the run's `best.bin`; the test set reports on it.

use std::sync::Arc;
use std::time::Instant;

use policy::{BlobError, WeightsBlob};
use serde::{Deserialize, Serialize};
use sim::Track;
use sim::eval::{EvalConfig, EvalReport, evaluate};

/// `[eval]` of the run config.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalSettings {
    /// Iterations between evaluations; 0 turns evaluation off (then `best.bin` is the
    /// iteration with the highest mean training return). Default 50.
    pub every: u64,
    /// `best.bin` is the weight average of this many last validated policies (a vision
    /// agent's: the last one, as its normaliser differs between them). Over a run's second
    /// half the highest of many validation readings tracks the test set barely (rank
    /// correlation +0.28), while the average of the last 10 flies it ~1 point above the mean
    /// of those 10 alone (docs/notebook/generalist.md). Default 10.
    pub average: usize,
    /// Validation tracks (informed generator, seeds from 8,000,000). Default 20.
    pub tracks: usize,
    /// Deployments per track. Default 10.
    pub runs: usize,
    /// Steps per deployment. Default 1000 (SPEC §9).
    pub steps: u32,
    /// Seed of the start perturbations. Default 0.
    pub seed: u64,
    /// Library tracks to fly instead of generated validation tracks (e.g. the four core
    /// tracks, to watch a sequential curriculum forget them). Default none.
    pub library: Vec<String>,
    /// Track files, or directories of them, to fly (with `library`) instead of generated
    /// validation tracks: a user's own tracks. Default none.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<std::path::PathBuf>,
}

impl Default for EvalSettings {
    fn default() -> Self {
        Self { every: 50, average: 10, tracks: 20, runs: 10, steps: 1000, seed: 0, library: Vec::new(), files: Vec::new() }
    }
}

impl EvalSettings {
    /// True when validation flies tracks named in `library` or `files`, not the validation range.
    pub fn chosen_tracks(&self) -> bool {
        !self.library.is_empty() || !self.files.is_empty()
    }

    /// How many of the validation range's tracks (its first) the run validates on.
    pub fn range_tracks(&self) -> usize {
        if self.chosen_tracks() { 0 } else { self.tracks }
    }
}

/// The validation tracks and how to fly them.
pub struct Validator {
    every: u64,
    tracks: Vec<Arc<Track>>,
    config: EvalConfig,
}

impl Validator {
    /// The validator `settings` describe; `None` when evaluation is off.
    pub fn new(settings: &EvalSettings) -> Result<Option<Self>, ValidationSetError> {
        let chosen = settings.chosen_tracks();
        if settings.every == 0 || settings.runs == 0 || (settings.tracks == 0 && !chosen) {
            return Ok(None);
        }
        let tracks = if chosen {
            racetracks::chosen_tracks(["eval.library", "eval.files"], &settings.library, &settings.files)?
        } else {
            racetracks::validation_set(settings.tracks)?
        };
        let tracks = tracks.into_iter().map(Arc::new).collect();
        let config = EvalConfig { runs: settings.runs, steps: settings.steps, seed: settings.seed, ..EvalConfig::default() };
        Ok(Some(Self { every: settings.every, tracks, config }))
    }

    /// True when the iteration just finished (1-based) is one to evaluate.
    pub fn due(&self, iteration: u64) -> bool {
        iteration.is_multiple_of(self.every)
    }

    /// Flies `blob`'s deterministic policy on every validation track (a vision policy with
    /// its camera).
    pub fn evaluate(&self, blob: &WeightsBlob) -> Result<Validation, BlobError> {
        let started = Instant::now();
        let make = policy::controller_factory(blob)?;
        let name = format!("policy v{}", blob.version);
        let report = evaluate(&name, &self.tracks, make.as_ref(), &self.config);
        Ok(Validation { report, seconds: started.elapsed().as_secs_f64() })
    }

    /// [`Validator::evaluate`] when `iteration` is due, with weights taken only then.
    pub fn evaluate_if_due(
        validator: Option<&Self>,
        iteration: u64,
        weights: impl FnOnce() -> WeightsBlob,
    ) -> Result<Option<Validation>, BlobError> {
        match validator {
            Some(v) if v.due(iteration) => v.evaluate(&weights()).map(Some),
            _ => Ok(None),
        }
    }
}

/// Why the validation tracks cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum ValidationSetError {
    /// Generating the validation set failed.
    #[error(transparent)]
    Generated(#[from] racetracks::TrackSetError),
    /// `eval.library` or `eval.files` names a track that cannot be had (the message names the
    /// field and the name or file).
    #[error(transparent)]
    Chosen(#[from] racetracks::ChosenTracksError),
}

/// One evaluation on the validation set, with its wall time.
#[derive(Clone, Debug)]
pub struct Validation {
    /// The report.
    pub report: EvalReport,
    /// Seconds it took.
    pub seconds: f64,
}
