//! Exact replay of an action sequence (SPEC §12.8), for debugging tracks and comparing
//! against other simulators.

use std::io::Write;
use std::sync::Arc;

use crate::disturbance::Disturbances;
use crate::race::{EnvConfig, RaceEnv};
use crate::randomization::RandomizationParams;
use crate::reward::RewardParams;
use crate::track::{Pose, Track};

/// Column names of the replay CSV, in order.
pub const CSV_HEADER: &str = "t,px,py,pz,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,m1,m2,m3,m4,reward,terminated,target_gate,laps,event";

/// The post-step state of one policy step.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayRow {
    /// Time at the end of the step, (k+1)·dt (s).
    pub t: f64,
    /// Position (m).
    pub position: [f64; 3],
    /// Attitude quaternion (w, x, y, z).
    pub attitude: [f64; 4],
    /// World velocity (m/s).
    pub velocity: [f64; 3],
    /// Body rates (rad/s).
    pub body_rates: [f64; 3],
    /// Motor speeds (rad/s), rotor order fr, bl, br, fl.
    pub motor_speeds: [f64; 4],
    /// Step reward.
    pub reward: f64,
    /// The step crashed.
    pub terminated: bool,
    /// Target gate after the step.
    pub target_gate: usize,
    /// Laps completed so far.
    pub laps: u32,
    /// `pass`, `crash`, `pass+crash` or `none`.
    pub event: &'static str,
}

/// Replays `actions` from rest at the start pose (or `start`), motors at hover, nominal
/// dynamics in `disturbance` (SPEC §13; none for an exact replay); stops after the first
/// terminated row.
pub fn replay(track: Arc<Track>, start: Option<Pose>, actions: &[[f64; 4]], disturbance: Disturbances) -> Vec<ReplayRow> {
    let track = match start {
        Some(start) => Arc::new(Track { start, ..(*track).clone() }),
        None => track,
    };
    // SPEC §5's reward, not the training default: replays are what independent
    // implementations are checked against.
    let mut config =
        EnvConfig { randomization: RandomizationParams::none(), reward: RewardParams::state_based(), disturbance, ..EnvConfig::default() };
    // Replays run as long as their action file; only a crash ends them early.
    config.race.max_episode_steps = u32::MAX;
    let mut env = RaceEnv::new(track, config, 0, 0);
    let mut rows = Vec::with_capacity(actions.len());
    for action in actions {
        let out = env.step_f64(action);
        let b = env.body();
        let q = b.attitude;
        rows.push(ReplayRow {
            t: env.time(),
            position: b.position.into(),
            attitude: [q.w, q.i, q.j, q.k],
            velocity: b.velocity.into(),
            body_rates: b.body_rates.into(),
            motor_speeds: env.motor_speeds(),
            reward: out.reward.total(),
            terminated: out.terminated,
            target_gate: env.target_gate(),
            laps: env.stats().laps,
            event: match (out.passed_gate.is_some(), out.terminated) {
                (true, true) => "pass+crash",
                (true, false) => "pass",
                (false, true) => "crash",
                (false, false) => "none",
            },
        });
        if out.terminated {
            break;
        }
    }
    rows
}

/// Writes rows as CSV with [`CSV_HEADER`]; floats in shortest round-trip form.
pub fn write_csv(rows: &[ReplayRow], mut out: impl Write) -> std::io::Result<()> {
    writeln!(out, "{CSV_HEADER}")?;
    for r in rows {
        let floats: Vec<String> = std::iter::once(r.t)
            .chain(r.position)
            .chain(r.attitude)
            .chain(r.velocity)
            .chain(r.body_rates)
            .chain(r.motor_speeds)
            .chain(std::iter::once(r.reward))
            .map(|x| x.to_string())
            .collect();
        writeln!(out, "{},{},{},{},{}", floats.join(","), u8::from(r.terminated), r.target_gate, r.laps, r.event)?;
    }
    Ok(())
}

/// A line of an action file that is not four finite numbers.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum ActionsError {
    /// A row with another count of values, or a value that is not a finite number.
    #[error("expected 4 finite action values, found {found:?}")]
    BadRow {
        /// 1-based line number.
        line: usize,
        /// The line as read.
        found: String,
    },
    /// No action rows at all.
    #[error("no action rows")]
    Empty,
}

/// Reads one `a0,a1,a2,a3` action per line; blank lines and `#` comments are skipped, and so
/// is a first line with no numbers in it (a header).
pub fn parse_actions(text: &str) -> Result<Vec<[f64; 4]>, ActionsError> {
    let mut actions = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let is_header = actions.is_empty() && line.split(',').all(|f| f.trim().parse::<f64>().is_err());
        if is_header {
            continue;
        }
        let numbers: Vec<Option<f64>> = line.split(',').map(|f| f.trim().parse::<f64>().ok().filter(|x| x.is_finite())).collect();
        match numbers[..] {
            [Some(a0), Some(a1), Some(a2), Some(a3)] => actions.push([a0, a1, a2, a3]),
            _ => return Err(ActionsError::BadRow { line: i + 1, found: line.to_string() }),
        }
    }
    if actions.is_empty() {
        return Err(ActionsError::Empty);
    }
    Ok(actions)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::QuadrotorParams;
    use crate::quadrotor::Command;
    use crate::track::{Arena, Gate};
    use nalgebra::Vector3;

    fn track() -> Arc<Track> {
        let gates = vec![Gate::new(Vector3::new(0.0, 0.0, 2.0), 0.0), Gate::new(Vector3::new(6.0, 4.0, 2.0), 3.0)];
        Arc::new(Track::new("t", gates, None, Arena::default()).unwrap())
    }

    #[test]
    fn hover_replay_starts_at_rest_at_hover_speed_and_stays() {
        let hover = Command::hover().to_action(&QuadrotorParams::default());
        let rows = replay(track(), None, &vec![hover; 50], Disturbances::default());
        assert_eq!(rows.len(), 50);
        assert!((rows[0].t - 0.02).abs() < 1e-15);
        let hover_speed = QuadrotorParams::default().hover_motor_speed();
        for r in &rows {
            assert!((r.position[2] - 2.0).abs() < 1e-6 && (r.position[0] + 2.0).abs() < 1e-6);
            assert!(r.motor_speeds.iter().all(|m| (m - hover_speed).abs() < 1e-6));
            assert_eq!(r.event, "none");
        }
    }

    #[test]
    fn replay_stops_after_the_crash_row_and_csv_has_every_column() {
        // No thrust: falls 2 m to the ground in well under 100 steps.
        let rows = replay(track(), None, &vec![[-1.0, 0.0, 0.0, 0.0]; 100], Disturbances::default());
        assert!(rows.len() < 100);
        let last = rows.last().unwrap();
        assert!(last.terminated && last.event == "crash");
        assert!(rows[..rows.len() - 1].iter().all(|r| !r.terminated));
        let mut csv = Vec::new();
        write_csv(&rows, &mut csv).unwrap();
        let text = String::from_utf8(csv).unwrap();
        let columns = CSV_HEADER.split(',').count();
        assert_eq!(columns, 23);
        assert!(text.lines().all(|l| l.split(',').count() == columns));
        assert_eq!(text.lines().count(), rows.len() + 1);
    }

    #[test]
    fn a_start_override_moves_the_start() {
        let start = Pose { position: Vector3::new(1.0, 2.0, 3.0), yaw: 0.5 };
        let hover = Command::hover().to_action(&QuadrotorParams::default());
        let rows = replay(track(), Some(start), &[hover], Disturbances::default());
        assert!((rows[0].position[1] - 2.0).abs() < 1e-6 && (rows[0].position[2] - 3.0).abs() < 1e-6);
    }

    #[test]
    fn action_files_skip_a_header_and_comments_and_name_a_bad_line() {
        assert_eq!(parse_actions("a0,a1,a2,a3\n# hover\n0,0,0,0\n\n1,-1,0.5,0\n"), Ok(vec![[0.0; 4], [1.0, -1.0, 0.5, 0.0]]));
        assert_eq!(parse_actions("0,0,0\n"), Err(ActionsError::BadRow { line: 1, found: "0,0,0".into() }));
        assert_eq!(parse_actions("0,0,0,0\n0,nan,0,0\n"), Err(ActionsError::BadRow { line: 2, found: "0,nan,0,0".into() }));
        assert_eq!(parse_actions("# nothing\n"), Err(ActionsError::Empty));
    }

    #[test]
    fn a_replay_in_wind_drifts_downwind_and_the_same_replay_without_is_unchanged() {
        let hover = crate::quadrotor::Command::hover().to_action(&crate::QuadrotorParams::default());
        let still = replay(track(), None, &vec![hover; 100], Disturbances::default());
        let wind = Disturbances { wind_speed: 5.0, wind_direction_deg: Some(90.0), gust_intensity: Some(0.0), ..Disturbances::default() };
        let windy = replay(track(), None, &vec![hover; 100], wind);
        assert_eq!(still, replay(track(), None, &vec![hover; 100], Disturbances::default()));
        let drift = |rows: &[ReplayRow]| rows.last().unwrap().position[1] - rows[0].position[1];
        assert!(drift(&windy) > drift(&still) + 0.1, "blown to +y: {} against {}", drift(&windy), drift(&still));
    }
}
