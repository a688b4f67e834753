//! Training metrics: `metrics.csv` (one row per iteration) and a TensorBoard event file, with
//! CleanRL's metric names.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;

/// One iteration's metrics: a field per `metrics.csv` column and TensorBoard tag (NaN where
/// not measured, e.g. the `eval_*` fields of iterations without an evaluation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MetricsRow {
    /// `charts/episodic_return`: Mean return of the episodes that ended.
    pub episodic_return: f64,
    /// `charts/episodic_length`: Their mean length (steps).
    pub episodic_length: f64,
    /// `charts/laps_per_episode`: Their mean completed laps.
    pub laps_per_episode: f64,
    /// `charts/crash_rate`: Fraction of them that ended in a crash.
    pub crash_rate: f64,
    /// `charts/fastest_lap`: Fastest lap among them (s).
    pub fastest_lap: f64,
    /// `charts/SPS`: Training env-steps per second of the iteration.
    pub sps: f64,
    /// `charts/learning_rate`: Learning rate used.
    pub learning_rate: f64,
    /// `losses/policy_loss`: Clipped-surrogate loss, averaged over gradient steps.
    pub policy_loss: f64,
    /// `losses/value_loss`: Value loss, averaged.
    pub value_loss: f64,
    /// `losses/approx_kl`: Approximate KL (mean of (r − 1) − ln r).
    pub approx_kl: f64,
    /// `losses/clipfrac`: Fraction of samples whose ratio was clipped.
    pub clip_fraction: f64,
    /// `losses/explained_variance`: Explained variance of the old values.
    pub explained_variance: f64,
    /// `losses/grad_norm`: Global gradient norm before clipping.
    pub grad_norm: f64,
    /// `losses/actor_grad_norm`: The policy's part of it.
    pub actor_grad_norm: f64,
    /// `losses/critic_grad_norm`: The value function's part of it.
    pub critic_grad_norm: f64,
    /// `policy/log_std`: Mean log standard deviation after the update.
    pub log_std: f64,
    /// `policy/version_lag`: Largest policy-version lag among the rollouts used.
    pub version_lag: f64,
    /// `tasks/switches`: Task switches so far.
    pub switches: f64,
    /// `tasks/mean_q`: Mean flatness score q.
    pub mean_q: f64,
    /// `eval/S_pw`: Validation S_pw (this iteration's evaluation).
    pub eval_s_pw: f64,
    /// `eval/success`: Validation success rate.
    pub eval_success: f64,
    /// `eval/mean_lap`: Validation mean lap time (s).
    pub eval_mean_lap: f64,
    /// `eval/crash_ground`: Fraction of validation deployments ending on the ground.
    pub eval_crash_ground: f64,
    /// `eval/crash_ceiling`: … on the ceiling.
    pub eval_crash_ceiling: f64,
    /// `eval/crash_wall`: … on an arena wall.
    pub eval_crash_wall: f64,
    /// `eval/crash_gate`: … on a gate frame.
    pub eval_crash_gate: f64,
    /// `eval/no_lap`: … without crashing and without a lap.
    pub eval_no_lap: f64,
    /// `eval/seconds`: Wall seconds of the evaluation.
    pub eval_seconds: f64,
}

impl Default for MetricsRow {
    fn default() -> Self {
        Self::from_columns([f64::NAN; COLUMNS])
    }
}

impl MetricsRow {
    /// `(column name, value)` in CSV order: the one place names and fields meet.
    pub fn columns(&self) -> [(&'static str, f64); COLUMNS] {
        [
            ("charts/episodic_return", self.episodic_return),
            ("charts/episodic_length", self.episodic_length),
            ("charts/laps_per_episode", self.laps_per_episode),
            ("charts/crash_rate", self.crash_rate),
            ("charts/fastest_lap", self.fastest_lap),
            ("charts/SPS", self.sps),
            ("charts/learning_rate", self.learning_rate),
            ("losses/policy_loss", self.policy_loss),
            ("losses/value_loss", self.value_loss),
            ("losses/approx_kl", self.approx_kl),
            ("losses/clipfrac", self.clip_fraction),
            ("losses/explained_variance", self.explained_variance),
            ("losses/grad_norm", self.grad_norm),
            ("losses/actor_grad_norm", self.actor_grad_norm),
            ("losses/critic_grad_norm", self.critic_grad_norm),
            ("policy/log_std", self.log_std),
            ("policy/version_lag", self.version_lag),
            ("tasks/switches", self.switches),
            ("tasks/mean_q", self.mean_q),
            ("eval/S_pw", self.eval_s_pw),
            ("eval/success", self.eval_success),
            ("eval/mean_lap", self.eval_mean_lap),
            ("eval/crash_ground", self.eval_crash_ground),
            ("eval/crash_ceiling", self.eval_crash_ceiling),
            ("eval/crash_wall", self.eval_crash_wall),
            ("eval/crash_gate", self.eval_crash_gate),
            ("eval/no_lap", self.eval_no_lap),
            ("eval/seconds", self.eval_seconds),
        ]
    }

    fn from_columns(v: [f64; COLUMNS]) -> Self {
        let [
            episodic_return,
            episodic_length,
            laps_per_episode,
            crash_rate,
            fastest_lap,
            sps,
            learning_rate,
            policy_loss,
            value_loss,
            approx_kl,
            clip_fraction,
            explained_variance,
            grad_norm,
            actor_grad_norm,
            critic_grad_norm,
            log_std,
            version_lag,
            switches,
            mean_q,
            eval_s_pw,
            eval_success,
            eval_mean_lap,
            eval_crash_ground,
            eval_crash_ceiling,
            eval_crash_wall,
            eval_crash_gate,
            eval_no_lap,
            eval_seconds,
        ] = v;
        Self {
            episodic_return,
            episodic_length,
            laps_per_episode,
            crash_rate,
            fastest_lap,
            sps,
            learning_rate,
            policy_loss,
            value_loss,
            approx_kl,
            clip_fraction,
            explained_variance,
            grad_norm,
            actor_grad_norm,
            critic_grad_norm,
            log_std,
            version_lag,
            switches,
            mean_q,
            eval_s_pw,
            eval_success,
            eval_mean_lap,
            eval_crash_ground,
            eval_crash_ceiling,
            eval_crash_wall,
            eval_crash_gate,
            eval_no_lap,
            eval_seconds,
        }
    }
}

/// Number of metric columns.
const COLUMNS: usize = 28;

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
    /// Opens (or continues) `metrics.csv` and starts a new event file in `dir`.
    pub fn open(dir: &Path) -> std::io::Result<Self> {
        let csv_path = dir.join("metrics.csv");
        let fresh = !csv_path.exists();
        let mut csv = OpenOptions::new().create(true).append(true).open(&csv_path)?;
        if fresh {
            let names: Vec<&str> = MetricsRow::default().columns().iter().map(|(name, _)| *name).collect();
            writeln!(csv, "iteration,env_steps,wall_seconds,{}", names.join(","))?;
        }
        let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs();
        let mut events = File::create(dir.join(format!("events.out.tfevents.{stamp}.dronerace")))?;
        write_record(&mut events, &event(stamp as f64, 0, EventBody::FileVersion("brain.Event:2")))?;
        Ok(Self { csv, events })
    }

    /// One iteration's row.
    pub fn write(&mut self, iteration: u64, env_steps: u64, wall_seconds: f64, row: &MetricsRow) -> std::io::Result<()> {
        let columns = row.columns();
        let cells: Vec<String> = columns.iter().map(|(_, v)| if v.is_nan() { String::new() } else { format!("{v}") }).collect();
        writeln!(self.csv, "{iteration},{env_steps},{wall_seconds:.3},{}", cells.join(","))?;
        self.csv.flush()?;
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_secs_f64();
        let scalars: Vec<(&str, f32)> = columns.iter().filter(|(_, v)| v.is_finite()).map(|(n, v)| (*n, *v as f32)).collect();
        write_record(&mut self.events, &event(now, env_steps as i64, EventBody::Scalars(&scalars)))?;
        self.events.flush()
    }
}

enum EventBody<'a> {
    FileVersion(&'a str),
    Scalars(&'a [(&'a str, f32)]),
}

/// A `tensorboard.Event` protobuf: wall_time (1, double), step (2, varint), then either
/// file_version (3, string) or summary (5) holding values (1) of tag (1) and simple_value (2).
fn event(wall_time: f64, step: i64, body: EventBody<'_>) -> Vec<u8> {
    let mut out = vec![0x09];
    out.extend_from_slice(&wall_time.to_le_bytes());
    out.push(0x10);
    varint(&mut out, step as u64);
    match body {
        EventBody::FileVersion(v) => length_delimited(&mut out, 0x1a, v.as_bytes()),
        EventBody::Scalars(values) => {
            let mut summary = Vec::new();
            for (tag, value) in values {
                let mut v = Vec::new();
                length_delimited(&mut v, 0x0a, tag.as_bytes());
                v.push(0x15);
                v.extend_from_slice(&value.to_le_bytes());
                length_delimited(&mut summary, 0x0a, &v);
            }
            length_delimited(&mut out, 0x2a, &summary);
        }
    }
    out
}

fn varint(out: &mut Vec<u8>, mut x: u64) {
    while x >= 0x80 {
        out.push((x as u8) | 0x80);
        x >>= 7;
    }
    out.push(x as u8);
}

fn length_delimited(out: &mut Vec<u8>, key: u8, bytes: &[u8]) {
    out.push(key);
    varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

/// TFRecord framing: length, masked CRC-32C of the length, data, masked CRC-32C of the data.
fn write_record(file: &mut File, data: &[u8]) -> std::io::Result<()> {
    let len = (data.len() as u64).to_le_bytes();
    file.write_all(&len)?;
    file.write_all(&masked_crc32c(&len).to_le_bytes())?;
    file.write_all(data)?;
    file.write_all(&masked_crc32c(data).to_le_bytes())
}

fn masked_crc32c(data: &[u8]) -> u32 {
    let crc = crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// CRC-32C (Castagnoli), bitwise: event records are small and few.
fn crc32c(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0x82F6_3B78 } else { crc >> 1 };
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_standard_check_value() {
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
    }

    #[test]
    fn csv_rows_follow_the_header_and_events_are_framed() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = MetricsWriter::open(dir.path()).unwrap();
        w.write(3, 72_000, 9.5, &MetricsRow { episodic_return: 12.5, eval_seconds: 4.0, ..MetricsRow::default() }).unwrap();
        let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0].split(',').count(), lines[1].split(',').count());
        assert!(lines[1].starts_with("3,72000,9.500,12.5,"));
        assert!(lines[1].ends_with(",4"), "{}", lines[1]);
        assert!(lines[0].starts_with("iteration,env_steps,wall_seconds,charts/episodic_return,") && lines[0].ends_with(",eval/seconds"));
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
