//! Training metrics: `metrics.csv` (one row per iteration) and a TensorBoard event file, with
//! CleanRL's metric names.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;

/// Declares [`MetricsRow`] from one list of `field => "column name"` pairs, so a field and its
/// column cannot drift apart.
macro_rules! metrics_row {
    ($($(#[doc = $doc:expr])* $field:ident => $name:literal,)*) => {
        /// One iteration's metrics: a field per `metrics.csv` column and TensorBoard tag (NaN
        /// where not measured, e.g. the `eval_*` fields of iterations without an evaluation).
        #[derive(Clone, Copy, Debug, PartialEq)]
        pub struct MetricsRow {
            $($(#[doc = $doc])* pub $field: f64,)*
        }

        impl Default for MetricsRow {
            fn default() -> Self {
                Self { $($field: f64::NAN,)* }
            }
        }

        impl MetricsRow {
            /// `(column name, value)` in CSV order.
            pub fn columns(&self) -> [(&'static str, f64); COLUMNS] {
                [$(($name, self.$field),)*]
            }
        }
    };
}

metrics_row! {
    /// Mean return of the episodes that ended.
    episodic_return => "charts/episodic_return",
    /// Their mean length (steps).
    episodic_length => "charts/episodic_length",
    /// Their mean completed laps.
    laps_per_episode => "charts/laps_per_episode",
    /// Fraction of them that ended in a crash.
    crash_rate => "charts/crash_rate",
    /// Fastest lap among them (s).
    fastest_lap => "charts/fastest_lap",
    /// Training env-steps per second of the iteration.
    sps => "charts/SPS",
    /// Learning rate used.
    learning_rate => "charts/learning_rate",
    /// Clipped-surrogate loss, averaged over gradient steps.
    policy_loss => "losses/policy_loss",
    /// Value loss, averaged.
    value_loss => "losses/value_loss",
    /// Approximate KL (mean of (r − 1) − ln r).
    approx_kl => "losses/approx_kl",
    /// Fraction of samples whose ratio was clipped.
    clip_fraction => "losses/clipfrac",
    /// Explained variance of the old values.
    explained_variance => "losses/explained_variance",
    /// Global gradient norm before clipping.
    grad_norm => "losses/grad_norm",
    /// The policy's part of it.
    actor_grad_norm => "losses/actor_grad_norm",
    /// The value function's part of it.
    critic_grad_norm => "losses/critic_grad_norm",
    /// Mean log standard deviation after the update.
    log_std => "policy/log_std",
    /// Largest policy-version lag among the rollouts used.
    version_lag => "policy/version_lag",
    /// Task switches so far.
    switches => "tasks/switches",
    /// Mean flatness score q.
    mean_q => "tasks/mean_q",
    /// Validation S_pw (this iteration's evaluation).
    eval_s_pw => "eval/S_pw",
    /// Validation success rate.
    eval_success => "eval/success",
    /// Validation mean lap time (s).
    eval_mean_lap => "eval/mean_lap",
    /// Fraction of validation deployments ending on the ground.
    eval_crash_ground => "eval/crash_ground",
    /// … on the ceiling.
    eval_crash_ceiling => "eval/crash_ceiling",
    /// … on an arena wall.
    eval_crash_wall => "eval/crash_wall",
    /// … on a gate frame.
    eval_crash_gate => "eval/crash_gate",
    /// … without crashing and without a lap.
    eval_no_lap => "eval/no_lap",
    /// Wall seconds of the evaluation.
    eval_seconds => "eval/seconds",
    /// Divergence of the mirror-symmetry term, averaged (last, so that a run resumed by this
    /// version keeps its earlier columns where they were).
    mirror_loss => "losses/mirror",
}

/// Number of metric columns.
const COLUMNS: usize = 29;

/// Columns of `validation.csv`: one row per validation track per evaluation.
pub const VALIDATION_COLUMNS: &str = "iteration,env_steps,track,success,s_pw,mean_lap,crash_gate,crash_other,no_lap";

/// Appends one evaluation's per-track results to `<dir>/validation.csv` (a resumed run may
/// repeat iterations after its last checkpoint; readers keep the later rows).
pub fn append_validation(dir: &Path, iteration: u64, env_steps: u64, report: &sim::eval::EvalReport) -> std::io::Result<()> {
    let path = dir.join("validation.csv");
    let fresh = !path.exists();
    let mut file = OpenOptions::new().create(true).append(true).open(&path)?;
    let mut text = String::new();
    if fresh {
        text.push_str(VALIDATION_COLUMNS);
        text.push('\n');
    }
    for t in &report.tracks {
        let o = &t.outcomes;
        let other = o.ground + o.ceiling + o.wall;
        text.push_str(&format!(
            "{iteration},{env_steps},{},{},{},{},{},{},{}\n",
            t.track,
            t.success_rate,
            t.s_pw,
            t.mean_lap.unwrap_or(f64::NAN),
            o.fraction(o.gate_total()),
            o.fraction(other),
            o.fraction(o.no_lap)
        ));
    }
    file.write_all(text.as_bytes())
}

/// Appends metric rows to the CSV and the TensorBoard file of a run directory.
pub struct MetricsWriter {
    csv: File,
    events: File,
}

impl MetricsWriter {
    /// Opens (or continues) `metrics.csv` and starts a new event file in `dir`, with the
    /// columns of [`MetricsRow`].
    pub fn open(dir: &Path) -> std::io::Result<Self> {
        let names: Vec<&str> = MetricsRow::default().columns().iter().map(|(name, _)| *name).collect();
        Self::open_with_columns(dir, &names)
    }

    /// [`MetricsWriter::open`] for rows of other columns (e.g. distillation's); `names` is the
    /// CSV header after `iteration,env_steps,wall_seconds`.
    pub fn open_with_columns(dir: &Path, names: &[&str]) -> std::io::Result<Self> {
        let csv_path = dir.join("metrics.csv");
        let fresh = !csv_path.exists();
        let mut csv = OpenOptions::new().create(true).append(true).open(&csv_path)?;
        if fresh {
            writeln!(csv, "iteration,env_steps,wall_seconds,{}", names.join(","))?;
        }
        let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs();
        let mut events = File::create(dir.join(format!("events.out.tfevents.{stamp}.dronerace")))?;
        write_record(&mut events, &event(stamp as f64, 0, EventBody::FileVersion("brain.Event:2".into())))?;
        Ok(Self { csv, events })
    }

    /// One iteration's row.
    pub fn write(&mut self, iteration: u64, env_steps: u64, wall_seconds: f64, row: &MetricsRow) -> std::io::Result<()> {
        self.write_columns(iteration, env_steps, wall_seconds, &row.columns())
    }

    /// One row of `(column, value)` pairs in the order the writer was opened with (NaN: empty
    /// cell, no TensorBoard scalar).
    pub fn write_columns(&mut self, iteration: u64, env_steps: u64, wall_seconds: f64, columns: &[(&str, f64)]) -> std::io::Result<()> {
        let cells: Vec<String> = columns.iter().map(|(_, v)| if v.is_nan() { String::new() } else { format!("{v}") }).collect();
        // One write of the whole line: a reader of the growing file sees whole rows.
        self.csv.write_all(format!("{iteration},{env_steps},{wall_seconds:.3},{}\n", cells.join(",")).as_bytes())?;
        self.csv.flush()?;
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs_f64();
        let values: Vec<(&str, f32)> = columns.iter().filter(|(_, v)| v.is_finite()).map(|(n, v)| (*n, *v as f32)).collect();
        write_record(&mut self.events, &event(now, env_steps as i64, scalars(&values)))?;
        self.events.flush()
    }
}

/// `tensorboard.Event`: the fields dronerace writes.
#[derive(Clone, PartialEq, prost::Message)]
struct Event {
    /// Seconds since the epoch.
    #[prost(double, tag = "1")]
    wall_time: f64,
    /// The x of every value (env steps).
    #[prost(int64, tag = "2")]
    step: i64,
    /// The file version (first record) or a summary.
    #[prost(oneof = "EventBody", tags = "3, 5")]
    body: Option<EventBody>,
}

/// What an event holds.
#[derive(Clone, PartialEq, prost::Oneof)]
enum EventBody {
    /// `brain.Event:2`, the first record of a file.
    #[prost(string, tag = "3")]
    FileVersion(String),
    /// Scalars.
    #[prost(message, tag = "5")]
    Summary(Summary),
}

/// `tensorboard.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
struct Summary {
    /// One value per tag.
    #[prost(message, repeated, tag = "1")]
    value: Vec<SummaryValue>,
}

/// `tensorboard.Summary.Value` with a simple value.
#[derive(Clone, PartialEq, prost::Message)]
struct SummaryValue {
    /// The chart's name.
    #[prost(string, tag = "1")]
    tag: String,
    /// Its value (in TensorBoard's oneof, so written even when zero).
    #[prost(float, optional, tag = "2")]
    simple_value: Option<f32>,
}

/// An encoded event.
fn event(wall_time: f64, step: i64, body: EventBody) -> Vec<u8> {
    prost::Message::encode_to_vec(&Event { wall_time, step, body: Some(body) })
}

/// A summary of `(tag, value)` scalars.
fn scalars(values: &[(&str, f32)]) -> EventBody {
    let value = values.iter().map(|(tag, v)| SummaryValue { tag: (*tag).to_string(), simple_value: Some(*v) }).collect();
    EventBody::Summary(Summary { value })
}

/// TFRecord framing: length, masked CRC-32C of the length, data, masked CRC-32C of the data.
fn write_record(file: &mut File, data: &[u8]) -> std::io::Result<()> {
    let len = (data.len() as u64).to_le_bytes();
    file.write_all(&len)?;
    file.write_all(&masked_crc32c(&len).to_le_bytes())?;
    file.write_all(data)?;
    file.write_all(&masked_crc32c(data).to_le_bytes())
}

/// TFRecord's masked CRC-32C.
fn masked_crc32c(data: &[u8]) -> u32 {
    crc32c::crc32c(data).rotate_right(15).wrapping_add(0xa282_ead8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_is_castagnolis_and_events_decode_as_tensorboard_reads_them() {
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        let bytes = event(1.5, 72_000, scalars(&[("charts/return", 0.0), ("eval/S_pw", 0.25)]));
        let back = <Event as prost::Message>::decode(bytes.as_slice()).unwrap();
        assert_eq!((back.wall_time, back.step), (1.5, 72_000));
        let Some(EventBody::Summary(summary)) = back.body else { panic!("a summary") };
        assert_eq!(summary.value.len(), 2);
        assert_eq!(summary.value[0].simple_value, Some(0.0), "a zero is written, not left out");
        // The hand-checked encoding of one value: tag (1, string), simple_value (2, fixed32).
        let one = event(0.0, 0, scalars(&[("a", 1.0)]));
        assert_eq!(one, [0x2a, 0x0a, 0x0a, 0x08, 0x0a, 0x01, b'a', 0x15, 0x00, 0x00, 0x80, 0x3f]);
    }

    #[test]
    fn csv_rows_follow_the_header_and_events_are_framed() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = MetricsWriter::open(dir.path()).unwrap();
        w.write(3, 72_000, 9.5, &MetricsRow { episodic_return: 12.5, eval_seconds: 4.0, mirror_loss: 0.5, ..MetricsRow::default() })
            .unwrap();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0].split(',').count(), lines[1].split(',').count());
        assert!(lines[1].starts_with("3,72000,9.500,12.5,"));
        assert!(lines[1].ends_with(",4,0.5"), "{}", lines[1]);
        assert!(
            lines[0].starts_with("iteration,env_steps,wall_seconds,charts/episodic_return,")
                && lines[0].ends_with(",eval/seconds,losses/mirror")
        );
        let event_file =
            std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().path()).find(|p| p.to_string_lossy().contains("tfevents")).unwrap();
        let bytes = std::fs::read(event_file).unwrap();
        // Walk the records: each length must be followed by its masked CRC and the data's.
        let mut at = 0;
        let mut records = 0;
        while at < bytes.len() {
            let len = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
            assert_eq!(u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap()), masked_crc32c(&bytes[at..at + 8]));
            let data = &bytes[at + 12..at + 12 + len];
            assert_eq!(u32::from_le_bytes(bytes[at + 12 + len..at + 16 + len].try_into().unwrap()), masked_crc32c(data));
            at += 16 + len;
            records += 1;
        }
        assert_eq!(records, 2);
    }
}
