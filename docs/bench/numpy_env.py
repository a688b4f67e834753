"""A numpy port of the state-based agent's racing environment, batched over environments: the
speed baseline "how fast would this environment step if it were written in numpy", checked
step for step against `dronerace.RaceVecEnv` (the Rust simulator).

    python docs/bench/numpy_env.py --envs 96 --steps 300      # env-steps/s, as python_vecenv.py
    python docs/bench/numpy_env.py --check                    # against dronerace.RaceVecEnv

What it ports (the Rust sources are the truth; section names below follow them):

- `EnvConfig::state_agent()`: the nominal quadrotor (`params.rs`), the nominal controller model,
  SPEC §5's 40 numbers in the heading frame plus 4 racing-line points 2.5 m apart (52 numbers),
  the state-based (SB) randomisation, 50 Hz policy steps of 8 RK4 substeps, 1,500-step episodes,
  the state-based reward with progress measured the `approach` way.
- `quadrotor.rs`: action -> command, the body-rate controller on the believed (nominal) vehicle,
  first-order motor lag, allocation, RK4 of the rigid body on the drawn (plant) vehicle, command
  delay in whole substeps, the crash test after every substep (integration stops at the first
  crashing one), attitude re-normalised once per policy step.
- `track.rs` / `race.rs`: ground, ceiling, wall and gate-frame crashes (sphere against the four
  bars), passing the target gate (segment through the opening from back to front), target
  advance, laps, termination and truncation.
- `reward.rs`: progress, pass, crash, body-rate and command-change (6 Hz low-pass) terms.
- `observation.rs` / `racing_line.rs`: the observation, including the reference pilot's racing
  line (Hermite legs through the gate centres, tangent length chosen to keep clear of frames
  and walls) searched on the target leg and walked by arc length.
- `randomization.rs` and the random streams: rand_chacha's ChaCha8Rng (seeded by
  `seed_from_u64`, environment i on stream i) and rand 0.9's uniform f64 draws, in Rust's draw
  order, so the port draws the same vehicles, delays and start states as Rust for a seed.
- `python/src/env.rs`: gymnasium's next-step autoreset as `RaceVecEnv` does it (the step that ends
  an episode returns its last observation; the next step ignores that environment's action,
  starts a new episode and returns its first observation with reward 0).

Precision: as Rust, float64 for all physics, geometry and rewards; observations and rewards are
handed out as float32 (Rust writes `v as f32`). Arithmetic follows nalgebra's evaluation order
(sums left to right, its quaternion, rotation and 4x4-inverse formulas, no fused multiply-adds)
and takes sin, cos and atan2 from glibc (Python's `math`) where Rust's values must be met
exactly, so states, rewards and episode ends agree with Rust bit for bit (`--check`). The one
exception, kept for speed: the heading-frame rotation is computed every step with numpy's own
`arctan2` (and `sin`, `cos`, which equal glibc's on the machine this was checked on);
`arctan2` differs from glibc's `atan2` in the last bit for a few per cent of arguments, which
moves observation column 1 (the heading-frame y of the body x axis, zero up to rounding) by
~1e-16, nothing else. `NumpyRaceEnv(..., libm_atan2=True)` removes that too.

What it leaves out: the vision agent (camera, images), the other observation frames, gate
sight and the `line`/`centre` progress measures, the vision-based reward, the compensating
controller model, track generation and task switching (tracks are fixed per environment,
`switching="none"`), the infos dict and episode statistics (`laps` and `target` are kept as
arrays), crash causes (only whether a step crashed), and `sim::VecEnv`'s same-step reset
(training's Rust loop; `RaceVecEnv` from Python resets at the next step, as here).
"""

import argparse
import math
import pathlib
import time

import numpy as np

# ---------------------------------------------------------------------------- constants
# params.rs: the nominal vehicle (QuadrotorParams::default) and the race timing.
GRAVITY = 9.8066
MASS = 0.752
INERTIA = np.array([0.0025, 0.0021, 0.0043])
ROTOR_POSITIONS = [(0.075, -0.10), (-0.075, 0.10), (-0.075, -0.10), (0.075, 0.10)]  # fr, bl, br, fl
YAW_TORQUE_PER_THRUST = 0.022
SPIN_SIGNS = [-1.0, -1.0, 1.0, 1.0]
THRUST_COEFFICIENT = 1.562522e-6
MOTOR_SPEED_MIN, MOTOR_SPEED_MAX = 150.0, 2333.0
MOTOR_THRUST_MAX = 8.5
MOTOR_TIME_CONSTANT = 0.033
DRAG = np.array([0.26, 0.28, 0.42])
RATE_LIMITS = np.array([10.0, 10.0, 4.0])
RATE_GAINS = np.array([20.0, 20.0, 40.0])
COLLISION_RADIUS = 0.15  # SPEC's, which evaluation (randomize=False) keeps
TRAINING_COLLISION_RADIUS = 0.25  # race.rs: the state-based agent's training environment
DT, SUBSTEPS, MAX_EPISODE_STEPS = 0.02, 8, 1500
SUBSTEP = DT / SUBSTEPS

# track.rs: gate geometry.
GATE_HALF_OPENING, GATE_HALF_OUTER, GATE_HALF_DEPTH = 0.75, 1.0, 0.05
GATE_CORNERS_LOCAL = [(0.75, 0.75), (-0.75, 0.75), (-0.75, -0.75), (0.75, -0.75)]  # (y, z), observation order
_O, _W, _D = GATE_HALF_OUTER, GATE_HALF_OPENING, GATE_HALF_DEPTH
FRAME_BARS_MIN = np.array([[-_D, -_O, _W], [-_D, -_O, -_O], [-_D, _W, -_O], [-_D, -_O, -_O]])  # top, bottom, left, right
FRAME_BARS_MAX = np.array([[_D, _O, _O], [_D, _O, -_W], [_D, _O, _O], [_D, -_W, _O]])

# reward.rs: the state-based weights, progress measured the `approach` way (EnvConfig::default).
APPROACH_DEPTH = 1.5
REWARD_PROGRESS, REWARD_PASS, REWARD_CRASH, REWARD_RATE = 1.0, 1.0, -4.0, -0.001
COMMAND_WEIGHTS = np.array([-0.0001, -0.0002, -0.0002, -0.0002])  # thrust, roll, pitch, yaw
COMMAND_LINEAR = 0.01
FILTER_ALPHA = DT / (DT + 1.0 / (2.0 * math.pi * 6.0))  # 6 Hz low-pass of the action

# observation.rs: the state agent's layout.
LINE_POINTS, LINE_SPACING = 4, 2.5
OBS_DIM = 40 + 3 * LINE_POINTS

# racing_line.rs: the default pilot's path limits that shape the line.
SAMPLES_PER_SEGMENT = 200
TANGENT_SCALES = [1.0, 0.75, 1.25, 1.5, 0.5, 2.0, 2.5, 3.0]
MIN_TURN_SPEED = 2.5
FRAME_CLEARANCE = 0.45
MAX_LATERAL_ACCEL = 10.0
MIN_TANGENT = 5.0

# randomization.rs: relative ranges (mass, inertia, drag, thrust map), command delay (s), start
# offsets (m), start velocity (m/s), start attitude (rad), start body rates (rad/s).
STATE_BASED = dict(mass=0.05, inertia=0.2, drag=0.5, thrust_map=0.2, command_delay=0.02, start_xy=0.8, start_z=0.6,
                   start_velocity=0.8, start_attitude=math.radians(20.0), start_body_rates=math.radians(45.0))
EVALUATION = dict(mass=0.0, inertia=0.0, drag=0.0, thrust_map=0.0, command_delay=0.0, start_xy=0.8, start_z=0.6,
                  start_velocity=0.0, start_attitude=0.0, start_body_rates=0.0)


def _allocation():
    """B with [F, tau_x, tau_y, tau_z] = B [T_fr, T_bl, T_br, T_fl] (params.rs)."""
    b = np.zeros((4, 4))
    for i, (x, y) in enumerate(ROTOR_POSITIONS):
        b[:, i] = [1.0, y, -x, YAW_TORQUE_PER_THRUST * SPIN_SIGNS[i]]
    return b


def _inverse4(a):
    """nalgebra's `try_inverse` of a 4x4 matrix (cofactor expansion, linalg/inverse.rs), so the
    controller's allocation inverse has Rust's last bits rather than LAPACK's."""
    m = a.T.ravel()  # nalgebra's column-major storage
    out = np.zeros((4, 4))
    c00 = m[5] * m[10] * m[15] - m[5] * m[11] * m[14] - m[9] * m[6] * m[15] + m[9] * m[7] * m[14] + m[13] * m[6] * m[11] - m[13] * m[7] * m[10]
    c01 = -m[4] * m[10] * m[15] + m[4] * m[11] * m[14] + m[8] * m[6] * m[15] - m[8] * m[7] * m[14] - m[12] * m[6] * m[11] + m[12] * m[7] * m[10]
    c02 = m[4] * m[9] * m[15] - m[4] * m[11] * m[13] - m[8] * m[5] * m[15] + m[8] * m[7] * m[13] + m[12] * m[5] * m[11] - m[12] * m[7] * m[9]
    c03 = -m[4] * m[9] * m[14] + m[4] * m[10] * m[13] + m[8] * m[5] * m[14] - m[8] * m[6] * m[13] - m[12] * m[5] * m[10] + m[12] * m[6] * m[9]
    det = m[0] * c00 + m[1] * c01 + m[2] * c02 + m[3] * c03
    out[0, 0], out[0, 1], out[0, 2], out[0, 3] = c00, c01, c02, c03
    out[1, 0] = -m[1] * m[10] * m[15] + m[1] * m[11] * m[14] + m[9] * m[2] * m[15] - m[9] * m[3] * m[14] - m[13] * m[2] * m[11] + m[13] * m[3] * m[10]
    out[2, 0] = m[1] * m[6] * m[15] - m[1] * m[7] * m[14] - m[5] * m[2] * m[15] + m[5] * m[3] * m[14] + m[13] * m[2] * m[7] - m[13] * m[3] * m[6]
    out[3, 0] = -m[1] * m[6] * m[11] + m[1] * m[7] * m[10] + m[5] * m[2] * m[11] - m[5] * m[3] * m[10] - m[9] * m[2] * m[7] + m[9] * m[3] * m[6]
    out[1, 1] = m[0] * m[10] * m[15] - m[0] * m[11] * m[14] - m[8] * m[2] * m[15] + m[8] * m[3] * m[14] + m[12] * m[2] * m[11] - m[12] * m[3] * m[10]
    out[2, 1] = -m[0] * m[6] * m[15] + m[0] * m[7] * m[14] + m[4] * m[2] * m[15] - m[4] * m[3] * m[14] - m[12] * m[2] * m[7] + m[12] * m[3] * m[6]
    out[3, 1] = m[0] * m[6] * m[11] - m[0] * m[7] * m[10] - m[4] * m[2] * m[11] + m[4] * m[3] * m[10] + m[8] * m[2] * m[7] - m[8] * m[3] * m[6]
    out[1, 2] = -m[0] * m[9] * m[15] + m[0] * m[11] * m[13] + m[8] * m[1] * m[15] - m[8] * m[3] * m[13] - m[12] * m[1] * m[11] + m[12] * m[3] * m[9]
    out[2, 2] = m[0] * m[5] * m[15] - m[0] * m[7] * m[13] - m[4] * m[1] * m[15] + m[4] * m[3] * m[13] + m[12] * m[1] * m[7] - m[12] * m[3] * m[5]
    out[3, 2] = -m[0] * m[5] * m[11] + m[0] * m[7] * m[9] + m[4] * m[1] * m[11] - m[4] * m[3] * m[9] - m[8] * m[1] * m[7] + m[8] * m[3] * m[5]
    out[1, 3] = m[0] * m[9] * m[14] - m[0] * m[10] * m[13] - m[8] * m[1] * m[14] + m[8] * m[2] * m[13] + m[12] * m[1] * m[10] - m[12] * m[2] * m[9]
    out[2, 3] = -m[0] * m[5] * m[14] + m[0] * m[6] * m[13] + m[4] * m[1] * m[14] - m[4] * m[2] * m[13] - m[12] * m[1] * m[6] + m[12] * m[2] * m[5]
    out[3, 3] = m[0] * m[5] * m[10] - m[0] * m[6] * m[9] - m[4] * m[1] * m[10] + m[4] * m[2] * m[9] + m[8] * m[1] * m[6] - m[8] * m[2] * m[5]
    return out * (1.0 / det)


ALLOCATION = _allocation()
ALLOCATION_INVERSE = _inverse4(ALLOCATION)
COLLECTIVE_THRUST_MAX = 4.0 * MOTOR_THRUST_MAX / MASS
MOTOR_THRUST_MIN = THRUST_COEFFICIENT * MOTOR_SPEED_MIN * MOTOR_SPEED_MIN
MOTOR_LAG = 1.0 - math.exp(-SUBSTEP / MOTOR_TIME_CONSTANT)  # the time constant is never randomised


# ---------------------------------------------------------------------------- random streams
class ChaCha8Streams:
    """rand_chacha 0.9's `ChaCha8Rng::seed_from_u64(seed)` with `set_stream(i)` for environment i
    (race.rs `RaceEnv::new`), one independent stream per row, and rand 0.9's `random_range(lo..=hi)`
    for f64: each draw takes one u64 (two 32-bit words, low first) of the ChaCha keystream."""

    CONSTANTS = np.array([0x61707865, 0x3320646E, 0x79622D32, 0x6B206574], dtype=np.uint32)

    def __init__(self, seed, streams, double_rounds=4):
        self.double_rounds = double_rounds
        self.key = np.array(self._pcg32_words(seed, 8), dtype=np.uint32)
        streams = np.asarray(streams, dtype=np.uint64)
        self.nonce = np.stack([streams & np.uint64(0xFFFFFFFF), streams >> np.uint64(32)], axis=1).astype(np.uint32)
        n = len(streams)
        self.counter = np.zeros(n, dtype=np.uint64)
        # rand_core's BlockRng buffers four ChaCha blocks (64 words); it starts empty.
        self.buffer = np.zeros((n, 64), dtype=np.uint32)
        self.index = np.full(n, 64, dtype=np.int64)

    @staticmethod
    def _pcg32_words(state, count):
        """rand_core 0.9's `seed_from_u64`: PCG32 outputs, little-endian, fill the 32-byte key."""
        mask = (1 << 64) - 1
        words = []
        for _ in range(count):
            state = (state * 6364136223846793005 + 11634580027462260723) & mask
            xorshifted = (((state >> 18) ^ state) >> 27) & 0xFFFFFFFF
            rot = state >> 59
            words.append(((xorshifted >> rot) | (xorshifted << ((32 - rot) & 31))) & 0xFFFFFFFF)
        return words

    def _blocks(self, rows):
        """Four consecutive keystream blocks for each of `rows`, as 64 words a row."""
        m = len(rows)
        counters = self.counter[rows][:, None] + np.arange(4, dtype=np.uint64)  # (m, 4)
        x = np.empty((16, m, 4), dtype=np.uint32)
        x[0:4] = self.CONSTANTS[:, None, None]
        x[4:12] = self.key[:, None, None]
        x[12] = (counters & np.uint64(0xFFFFFFFF)).astype(np.uint32)
        x[13] = (counters >> np.uint64(32)).astype(np.uint32)
        x[14] = self.nonce[rows, 0][:, None]
        x[15] = self.nonce[rows, 1][:, None]
        start = x.copy()
        # Column rounds then diagonal rounds, four quarter-rounds at a time.
        columns = ([0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11], [12, 13, 14, 15])
        diagonals = ([0, 1, 2, 3], [5, 6, 7, 4], [10, 11, 8, 9], [15, 12, 13, 14])
        for _ in range(self.double_rounds):
            for a, b, c, d in (columns, diagonals):
                xa, xb, xc, xd = x[a], x[b], x[c], x[d]
                xa += xb; xd ^= xa; xd = (xd << np.uint32(16)) | (xd >> np.uint32(16))
                xc += xd; xb ^= xc; xb = (xb << np.uint32(12)) | (xb >> np.uint32(20))
                xa += xb; xd ^= xa; xd = (xd << np.uint32(8)) | (xd >> np.uint32(24))
                xc += xd; xb ^= xc; xb = (xb << np.uint32(7)) | (xb >> np.uint32(25))
                x[a], x[b], x[c], x[d] = xa, xb, xc, xd
        x += start
        return x.transpose(1, 2, 0).reshape(m, 64)  # block-major, word order within a block

    def next_u64(self, rows):
        """One u64 from each of `rows` (distinct). Draws always take whole u64s, so a u64 never
        straddles a buffer refill here."""
        empty = rows[self.index[rows] >= 64]
        if len(empty):
            self.buffer[empty] = self._blocks(empty)
            self.counter[empty] += np.uint64(4)
            self.index[empty] = 0
        i = self.index[rows]
        low = self.buffer[rows, i].astype(np.uint64)
        high = self.buffer[rows, i + 1].astype(np.uint64)
        self.index[rows] = i + 2
        return low | (high << np.uint64(32))

    def uniform(self, rows, low, high):
        """rand 0.9 `random_range(low..=high)` for f64: 52 random bits as a float in [1, 2),
        less one, times (high - low), plus low."""
        bits = (self.next_u64(rows) >> np.uint64(12)) | np.uint64(0x3FF0000000000000)
        return (bits.view(np.float64) - 1.0) * (high - low) + low


# ---------------------------------------------------------------------------- vector helpers
def cross(a, b):
    """Row-wise a x b of (n, 3) arrays, nalgebra's component formulas (twice as fast as
    np.cross or fancy-indexed columns at these sizes)."""
    out = np.empty_like(a)
    ax, ay, az = a.T
    bx, by, bz = b.T
    out[:, 0] = ay * bz - az * by
    out[:, 1] = az * bx - ax * bz
    out[:, 2] = ax * by - ay * bx
    return out


def norm(v):
    """Euclidean norm over the last axis, summed x, y, z in order as nalgebra's `dot`."""
    return np.sqrt((v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1]) + v[..., 2] * v[..., 2])


def rotate(qw, u, v):
    """Rotates v by the quaternion (qw, u) as nalgebra's `UnitQuaternion * Vector3` does, without
    assuming it is unit (RK4's intermediate attitudes are not): v + w t + u x t, t = 2 u x v."""
    t = cross(u, v) * 2.0
    return t * qw + cross(u, t) + v


def quat_times_rates(q, w):
    """q * (0, w), nalgebra's product formula with the zero scalar's terms (exact zeros) left out;
    w, x, y, z columns, each sum left to right as Rust evaluates it."""
    qw, qx, qy, qz = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    return np.stack([
        (-(qx * wx) - qy * wy) - qz * wz,
        (qw * wx + qy * wz) - qz * wy,
        (qw * wy - qx * wz) + qz * wx,
        (qw * wz + qx * wy) - qy * wx,
    ], axis=1)


def quat_mul(a, b):
    """Hamilton product of (w, x, y, z) rows, nalgebra's formula."""
    aw, ax, ay, az = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    bw, bx, by, bz = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=1)


def libm(f, x):
    """f (a `math` function: glibc's, as Rust calls) element by element. numpy's own float64 sin
    and cos may differ from glibc's in the last bit on some CPUs; where few values need them
    (episode starts) bit-identical start states are worth the loop."""
    return np.array([f(v) for v in x], dtype=np.float64)


def quat_from_euler(roll, pitch, yaw):
    """nalgebra's `UnitQuaternion::from_euler_angles` (yaw about z after pitch after roll)."""
    sr, cr = libm(math.sin, roll * 0.5), libm(math.cos, roll * 0.5)
    sp, cp = libm(math.sin, pitch * 0.5), libm(math.cos, pitch * 0.5)
    sy, cy = libm(math.sin, yaw * 0.5), libm(math.cos, yaw * 0.5)
    return np.stack([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ], axis=1)


def frame_distance_squared(local):
    """Squared distance from gate-local points (..., 3) to the nearest of the four frame bars
    (track.rs `nearest_frame_point_local`: each bar's nearest point is the point clamped into it)."""
    nearest = np.clip(local[..., None, :], FRAME_BARS_MIN, FRAME_BARS_MAX)
    d = nearest - local[..., None, :]
    return ((d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]).min(axis=-1)


def to_gate_local(p, gpos, gcos, gsin):
    """World points -> gate-local (x along the flight direction, y left, z up); broadcasts."""
    d = p - gpos
    return np.stack([gcos * d[..., 0] + gsin * d[..., 1], -gsin * d[..., 0] + gcos * d[..., 1], d[..., 2]], axis=-1)


def frame_touches(local, radius):
    """track.rs `frame_touches_sphere` for gate-local points, cheap rejection included."""
    touch = ((np.abs(local[..., 0]) <= GATE_HALF_DEPTH + radius) & (np.abs(local[..., 1]) <= GATE_HALF_OUTER + radius)
             & (np.abs(local[..., 2]) <= GATE_HALF_OUTER + radius))
    if touch.any():
        touch[touch] = frame_distance_squared(local[touch]) <= radius * radius
    return touch


# ---------------------------------------------------------------------------- tracks
class TrackGeometry:
    """What the environment reads of a track: gate centres and yaws, start pose, arena; and the
    reference pilot's racing line through it (racing_line.rs `RacingLine::new`)."""

    def __init__(self, name, gates, start, arena):
        self.name = name
        gates = np.asarray(gates, dtype=np.float64)
        self.position = gates[:, :3].copy()
        self.yaw = gates[:, 3].copy()
        # Gate::new caches cos and sin of the yaw; math's are glibc's, as Rust's.
        self.cos = np.array([math.cos(y) for y in self.yaw])
        self.sin = np.array([math.sin(y) for y in self.yaw])
        self.start_position = np.array(start[:3], dtype=np.float64)
        self.start_yaw = float(start[3])
        self.arena_min = np.array(arena[0], dtype=np.float64)
        self.arena_max = np.array(arena[1], dtype=np.float64)
        # Gate::corners: to_world(0, y, z) of the inner-opening corners.
        self.corners = np.stack([
            np.stack([self.position[:, 0] + (self.cos * 0.0 - self.sin * y), self.position[:, 1] + (self.sin * 0.0 + self.cos * y),
                      self.position[:, 2] + z], axis=1)
            for y, z in GATE_CORNERS_LOCAL], axis=1)  # (gates, 4, 3)
        self.line, self.arc, self.length = self._racing_line()

    @classmethod
    def from_dronerace(cls, track):
        """From a `dronerace.Track` or a library track's name."""
        if isinstance(track, str):
            import dronerace
            track = next(t for t in dronerace.tracks.library() if t.name.lower() == track.lower())
        return cls(track.name, track.gates, track.start, track.arena)

    @classmethod
    def resolve(cls, tracks):
        """One geometry per entry of `tracks` (`TrackGeometry`s, `dronerace.Track`s or library
        names), built once per distinct track: the racing line takes a moment to build."""
        built, out = {}, []
        for t in tracks:
            if isinstance(t, TrackGeometry):
                key = id(t)
                built.setdefault(key, t)
            else:
                key = t.lower() if isinstance(t, str) else (t.name, tuple(t.gates), t.start, tuple(map(tuple, t.arena)))
                if key not in built:
                    built[key] = cls.from_dronerace(t)
            out.append(built[key])
        return out

    def _touches_any_frame(self, points, radius):
        local = to_gate_local(points[:, None, :], self.position, self.cos, self.sin)
        return frame_touches(local, radius).any(axis=1)

    def _racing_line(self):
        gates = len(self.yaw)
        normals = np.stack([self.cos, self.sin, np.zeros(gates)], axis=1)
        inside_min, inside_max = self.arena_min + FRAME_CLEARANCE, self.arena_max - FRAME_CLEARANCE
        legs = []
        for i in range(gates):
            j = (i + 1) % gates
            p0, d0, p1, d1 = self.position[i], normals[i], self.position[j], normals[j]
            chord = max(float(norm(p1 - p0)), MIN_TANGENT)
            # clear_segment: the first tangent scale (in preference order) with the fewest samples
            # too close to a frame or wall, then without a near-cusp turn.
            best = None
            for scale in TANGENT_SCALES:
                points, curvature = _hermite(p0, d0, p1, d1, scale * chord, SAMPLES_PER_SEGMENT)
                outside = ~np.all((points >= inside_min) & (points <= inside_max), axis=1)
                too_close = int((outside | self._touches_any_frame(points, FRAME_CLEARANCE)).sum())
                cusp = bool((MAX_LATERAL_ACCEL / np.maximum(norm(curvature), 1e-9) < MIN_TURN_SPEED ** 2).any())
                if best is None or (too_close, cusp) < best[0]:
                    best = ((too_close, cusp), points)
            legs.append(best[1])
        line = np.concatenate(legs)
        steps = norm(np.roll(line, -1, axis=0) - line)
        arc = np.concatenate([[0.0], np.cumsum(steps)[:-1]])  # a running sum, as Rust's loop
        length = float(np.cumsum(steps)[-1])
        return line, arc, length


def _hermite(p0, d0, p1, d1, scale, samples):
    """racing_line.rs `hermite_samples`: positions and curvature vectors of the cubic Hermite
    curve between two (position, unit direction) ends with tangent length `scale`."""
    m0, m1 = d0 * scale, d1 * scale
    u = (np.arange(samples) / samples)[:, None]
    u2, u3 = u * u, u * u * u
    position = p0 * (2.0 * u3 - 3.0 * u2 + 1.0) + m0 * (u3 - 2.0 * u2 + u) + p1 * (-2.0 * u3 + 3.0 * u2) + m1 * (u3 - u2)
    first = p0 * (6.0 * u2 - 6.0 * u) + m0 * (3.0 * u2 - 4.0 * u + 1.0) + p1 * (-6.0 * u2 + 6.0 * u) + m1 * (3.0 * u2 - 2.0 * u)
    second = p0 * (12.0 * u - 6.0) + m0 * (6.0 * u - 4.0) + p1 * (-12.0 * u + 6.0) + m1 * (6.0 * u - 2.0)
    speed = norm(first)[:, None]
    moving = speed > 1e-12
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent = np.where(moving, first / speed, d0)
        along = (second[:, 0] * tangent[:, 0] + second[:, 1] * tangent[:, 1] + second[:, 2] * tangent[:, 2])[:, None]
        curvature = np.where(moving, (second - tangent * along) / (speed * speed), 0.0)
    return position, curvature


# ---------------------------------------------------------------------------- environment
class NumpyRaceEnv:
    """`num_envs` racing environments of the state-based agent (`EnvConfig::state_agent()`),
    stepped together as numpy arrays, with `RaceVecEnv`'s next-step autoreset.

    `tracks`: `dronerace.Track`s, library names or `TrackGeometry`s, cycled over the
    environments. Environment i draws its episodes from random stream i of `seed`, as in Rust, so
    the same seed and actions fly the same trajectories as `dronerace.RaceVecEnv(num_envs, tracks,
    seed=seed, switching="none")`. `randomize=False` is `RaceVecEnv`'s evaluation setting (nominal
    vehicle, only the start position perturbed).
    """

    def __init__(self, num_envs, tracks, seed=0, randomize=True, max_episode_steps=MAX_EPISODE_STEPS, libm_atan2=False):
        self.num_envs = n = num_envs
        # numpy's arctan2 may differ from glibc's atan2 (Rust's) in the last bit; `libm_atan2`
        # takes Python's math.atan2 (glibc's) element by element instead, for bit-identical
        # observations at some cost.
        self.atan2 = np.frompyfunc(math.atan2, 2, 1) if libm_atan2 else np.arctan2
        self.randomization = STATE_BASED if randomize else EVALUATION
        self.collision_radius = TRAINING_COLLISION_RADIUS if randomize else COLLISION_RADIUS
        self.max_episode_steps = max_episode_steps
        geometry = TrackGeometry.resolve(tracks)
        geometry = [geometry[i % len(geometry)] for i in range(n)]  # cycled, as RaceVecEnv does
        self.tracks = list({id(g): g for g in geometry}.values())
        index_of = {id(g): k for k, g in enumerate(self.tracks)}
        self.track_index = np.array([index_of[id(g)] for g in geometry])
        env_tracks = [self.tracks[k] for k in self.track_index]

        # Gates padded to the longest track; padding gates are never hit, passed or observed.
        gmax = max(len(t.yaw) for t in self.tracks)
        self.gate_count = np.array([len(t.yaw) for t in env_tracks])
        self.gate_valid = np.arange(gmax)[None, :] < self.gate_count[:, None]
        pad = lambda a, fill: np.concatenate([a, np.full((gmax - len(a),) + a.shape[1:], fill)]) if len(a) < gmax else a
        self.gate_position = np.stack([pad(t.position, 1e6) for t in env_tracks])  # (n, G, 3)
        self.gate_cos = np.stack([pad(t.cos, 1.0) for t in env_tracks])
        self.gate_sin = np.stack([pad(t.sin, 0.0) for t in env_tracks])
        self.gate_corners = np.stack([pad(t.corners, 1e6) for t in env_tracks])  # (n, G, 4, 3)
        self.arena_min = np.stack([t.arena_min for t in env_tracks])
        self.arena_max = np.stack([t.arena_max for t in env_tracks])
        self.start_position = np.stack([t.start_position for t in env_tracks])
        # The start attitude before the drawn roll, pitch and yaw; math's sin and cos as Rust's.
        self.start_attitude = np.array([[math.cos(t.start_yaw * 0.5), 0.0, 0.0, math.sin(t.start_yaw * 0.5)] for t in env_tracks])

        # Racing lines padded to the longest (the padding is never indexed) and flattened, so one
        # `take` gathers every environment's samples; the nearest-sample search reads the
        # coordinates one at a time (contiguous), the interpolation whole points.
        lmax = max(len(t.line) for t in self.tracks)
        self.line_stride = lmax
        self.line = np.concatenate([np.concatenate([t.line, np.zeros((lmax - len(t.line), 3))]) for t in self.tracks])
        self.line_xyz = np.ascontiguousarray(self.line.T)
        self.arc = np.concatenate([np.concatenate([t.arc, np.full(lmax - len(t.arc), np.inf)]) for t in self.tracks])
        self.line_length = np.array([t.length for t in self.tracks])
        self.line_count = np.array([len(t.line) for t in self.tracks])
        self.rows_of_track = [np.flatnonzero(self.track_index == t) for t in range(len(self.tracks))]

        self.seed = seed
        self.reset(seed)

    # ------------------------------------------------------------------ episodes
    def reset(self, seed=None):
        """Every environment starts afresh; with `seed`, the random streams restart from it (as
        a new environment of that seed), else the next draws of the streams. Returns observations."""
        if seed is not None:
            self.seed = seed
        if seed is not None or not hasattr(self, "rng"):
            self.rng = ChaCha8Streams(self.seed, np.arange(self.num_envs))
            n = self.num_envs
            self.state = np.zeros((n, 13))  # position, attitude (w, x, y, z), velocity, body rates
            self.motor_speeds = np.zeros((n, 4))
            self.mass, self.inertia, self.drag = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3))
            self.thrust_coefficient, self.delay = np.zeros(n), np.zeros(n, dtype=np.int64)
            self.previous_thrust, self.previous_rates = np.zeros(n), np.zeros((n, 3))
            self.previous_action, self.filtered = np.zeros((n, 4)), np.zeros((n, 4))
            self.target, self.steps, self.laps = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
            self.passed_gate0 = np.zeros(n, dtype=bool)
        self._start_episodes(np.arange(self.num_envs))
        self.pending_reset = np.zeros(self.num_envs, dtype=bool)
        return self._observe()

    def _start_episodes(self, rows):
        """randomization.rs `sample` then race.rs `reset` for `rows`, drawing in Rust's order; a
        zero range draws nothing."""
        r = self.randomization
        k = len(rows)
        symmetric = lambda x: self.rng.uniform(rows, -x, x) if x > 0 else np.zeros(k)
        scale = lambda x: 1.0 + symmetric(x)
        mass = MASS * scale(r["mass"])
        inertia = np.stack([INERTIA[i] * scale(r["inertia"]) for i in range(3)], axis=1)
        drag = DRAG * scale(r["drag"])[:, None]
        thrust_coefficient = THRUST_COEFFICIENT * scale(r["thrust_map"])
        delay = self.rng.uniform(rows, 0.0, r["command_delay"]) if r["command_delay"] > 0 else np.zeros(k)
        delay = delay / SUBSTEP
        whole = np.floor(delay)
        delay = (whole + (delay - whole >= 0.5)).astype(np.int64)  # Rust's round: halves away from zero
        offset = np.stack([symmetric(r["start_xy"]), symmetric(r["start_xy"]), symmetric(r["start_z"])], axis=1)
        velocity = np.stack([symmetric(r["start_velocity"]) for _ in range(3)], axis=1)
        roll, pitch, yaw = (symmetric(r["start_attitude"]) for _ in range(3))
        rates = np.stack([symmetric(r["start_body_rates"]) for _ in range(3)], axis=1)
        attitude = quat_mul(self.start_attitude[rows], quat_from_euler(roll, pitch, yaw))

        self.state[rows] = np.concatenate([self.start_position[rows] + offset, attitude, velocity, rates], axis=1)
        self.mass[rows], self.inertia[rows], self.drag[rows] = mass, inertia, drag
        self.thrust_coefficient[rows], self.delay[rows] = thrust_coefficient, delay
        self.motor_speeds[rows] = np.sqrt(mass * GRAVITY / 4.0 / thrust_coefficient)[:, None]  # the plant's hover
        # Before the first action arrives the flight controller holds a hover.
        self.previous_thrust[rows], self.previous_rates[rows] = GRAVITY, 0.0
        self.previous_action[rows], self.filtered[rows] = 0.0, 0.0
        self.target[rows], self.steps[rows], self.laps[rows], self.passed_gate0[rows] = 0, 0, 0, False

    def states(self):
        """Body states as `RaceVecEnv.states()`: position, velocity, (w, x, y, z), body rates."""
        s = self.state
        return np.concatenate([s[:, 0:3], s[:, 7:10], s[:, 3:7], s[:, 10:13]], axis=1)

    # ------------------------------------------------------------------ dynamics
    def _derivative(self, s, thrust, torque):
        """Rigid-body equations of motion on the plant with thrust and torque held."""
        qw, u = s[:, 3:4], s[:, 4:7]
        velocity, rates = s[:, 7:10], s[:, 10:13]
        v_body = rotate(qw, -u, velocity)  # the conjugate rotates world into body
        force = -self.drag * v_body
        force[:, 2] += thrust
        acceleration = rotate(qw, u, force) / self.mass[:, None]
        acceleration[:, 2] -= GRAVITY
        rates_dot = (torque - cross(rates, self.inertia * rates)) / self.inertia
        return np.concatenate([velocity, quat_times_rates(s[:, 3:7], rates) * 0.5, acceleration, rates_dot], axis=1)

    def _substep(self, state, motors, thrust_command, rates_command):
        """quadrotor.rs `substep`: controller on the substep's start state -> desired motor speeds
        -> motor lag -> forces held through RK4. Returns the new state and motor speeds."""
        w = state[:, 10:13]
        # Low-level controller on the nominal vehicle: F = m c, tau = J K (w_cmd - w) + w x J w.
        torque = INERTIA * (RATE_GAINS * (rates_command - w)) + cross(w, INERTIA * w)
        b = ALLOCATION_INVERSE
        thrusts = (((MASS * thrust_command)[:, None] * b[:, 0] + torque[:, 0:1] * b[:, 1]) + torque[:, 1:2] * b[:, 2]) + torque[:, 2:3] * b[:, 3]
        desired = np.clip(np.sqrt(np.clip(thrusts, MOTOR_THRUST_MIN, MOTOR_THRUST_MAX) / THRUST_COEFFICIENT), MOTOR_SPEED_MIN, MOTOR_SPEED_MAX)
        motors = motors + (desired - motors) * MOTOR_LAG
        t = self.thrust_coefficient[:, None] * motors * motors
        b = ALLOCATION
        wrench = ((t[:, 0:1] * b[:, 0] + t[:, 1:2] * b[:, 1]) + t[:, 2:3] * b[:, 2]) + t[:, 3:4] * b[:, 3]
        thrust, torque = wrench[:, 0], wrench[:, 1:4]
        h = SUBSTEP
        k1 = self._derivative(state, thrust, torque)
        k2 = self._derivative(state + k1 * (h / 2.0), thrust, torque)
        k3 = self._derivative(state + k2 * (h / 2.0), thrust, torque)
        k4 = self._derivative(state + k3 * h, thrust, torque)
        return state + ((k1 + (k2 + k3) * 2.0 + k4) / 6.0) * h, motors

    def _crashed(self, p):
        """race.rs `crash_cause`, whether any: ground, ceiling, walls, then gate frames."""
        out = (p < self.arena_min).any(axis=1) | (p > self.arena_max).any(axis=1) | (p[:, 2] < 0.0)
        local = to_gate_local(p[:, None, :], self.gate_position, self.gate_cos, self.gate_sin)
        return out | (frame_touches(local, self.collision_radius) & self.gate_valid).any(axis=1)

    # ------------------------------------------------------------------ one step
    def _approach_distance(self, gate_position, gcos, gsin, p):
        """reward.rs `ProgressDistance::Approach`: straight to the centre from behind the gate
        plane; from in front of it, by way of a point 1.5 m behind the centre."""
        o = p - gate_position
        front = (o[:, 0] * gcos + o[:, 1] * gsin) + o[:, 2] * 0.0 >= 0.0
        detour = np.stack([o[:, 0] + gcos * APPROACH_DEPTH, o[:, 1] + gsin * APPROACH_DEPTH, o[:, 2]], axis=1)
        return np.where(front, norm(detour) + APPROACH_DEPTH, norm(o))

    def step(self, actions):
        """Steps every environment with its row of `actions` (num_envs x 4, float32 in [-1, 1]):
        `(observations, rewards, terminated, truncated)`, float32 / bool arrays."""
        n = self.num_envs
        rows = np.arange(n)
        action = np.clip(np.asarray(actions, dtype=np.float32).astype(np.float64), -1.0, 1.0)
        target = self.target
        gpos, gcos, gsin = self.gate_position[rows, target], self.gate_cos[rows, target], self.gate_sin[rows, target]
        start = self.state[:, 0:3].copy()
        distance_before = self._approach_distance(gpos, gcos, gsin, start)

        thrust_command = (action[:, 0] + 1.0) / 2.0 * COLLECTIVE_THRUST_MAX
        rates_command = action[:, 1:4] * RATE_LIMITS
        state, motors = self.state, self.motor_speeds
        crashed = np.zeros(n, dtype=bool)
        for j in range(SUBSTEPS):
            # The command delay holds the previous command for the step's first substeps.
            late = j < self.delay
            c = np.where(late, self.previous_thrust, thrust_command)
            w = np.where(late[:, None], self.previous_rates, rates_command)
            new_state, new_motors = self._substep(state, motors, c, w)
            if crashed.any():  # an environment stops at its first crashing substep
                new_state = np.where(crashed[:, None], state, new_state)
                new_motors = np.where(crashed[:, None], motors, new_motors)
            state, motors = new_state, new_motors
            crashed |= self._crashed(state[:, 0:3])
            if crashed.all():
                break
        # Re-normalise the attitude once a policy step; nalgebra sums (x² + z²) + (y² + w²).
        q = state[:, 3:7]
        state[:, 3:7] = q / np.sqrt((q[:, 1] * q[:, 1] + q[:, 3] * q[:, 3]) + (q[:, 2] * q[:, 2] + q[:, 0] * q[:, 0]))[:, None]
        self.state, self.motor_speeds = state, motors
        self.previous_thrust, self.previous_rates = thrust_command, rates_command
        self.steps += 1

        # Passing the target gate: the step's segment through the opening, back to front.
        end = state[:, 0:3]
        a = to_gate_local(start, gpos, gcos, gsin)
        b = to_gate_local(end, gpos, gcos, gsin)
        crossing = (a[:, 0] < 0.0) & (b[:, 0] >= 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = -a[:, 0] / (b[:, 0] - a[:, 0])
            y = a[:, 1] + t * (b[:, 1] - a[:, 1])
            z = a[:, 2] + t * (b[:, 2] - a[:, 2])
        passed = crossing & (np.abs(y) < GATE_HALF_OPENING) & (np.abs(z) < GATE_HALF_OPENING)
        error = np.hypot(y, z)
        # A second pass of gate 0 closes a lap (targets advance strictly in order).
        self.laps += passed & (target == 0) & self.passed_gate0
        self.passed_gate0 |= passed & (target == 0)
        self.target = np.where(passed, (target + 1) % self.gate_count, target)

        # Reward: a pass leaves by the gate's front, so its last step is measured to the centre.
        distance_after = np.where(passed, norm(end - gpos), self._approach_distance(gpos, gcos, gsin, end))
        self.filtered = self.filtered + FILTER_ALPHA * (action - self.filtered)
        change = action - self.filtered
        command_terms = COMMAND_WEIGHTS * (COMMAND_LINEAR * np.abs(change) + change * change)
        wx, wy = state[:, 10] / RATE_LIMITS[0], state[:, 11] / RATE_LIMITS[1]
        reward = ((((REWARD_PROGRESS * (distance_before - distance_after)
                     + np.where(passed, REWARD_PASS * (1.0 - error / GATE_HALF_OPENING), 0.0))
                    + np.where(crashed, REWARD_CRASH, 0.0))
                   + REWARD_RATE * (wx * wx + wy * wy))
                  + (((command_terms[:, 0] + command_terms[:, 1]) + command_terms[:, 2]) + command_terms[:, 3]))
        self.previous_action = action
        terminated = crashed
        truncated = ~terminated & (self.steps >= self.max_episode_steps)

        # Next-step autoreset: an environment whose episode ended at its last step ignores this
        # step's action (its stepped values are thrown away) and starts a new episode.
        restarting = np.flatnonzero(self.pending_reset)
        if len(restarting):
            self._start_episodes(restarting)
            reward[restarting] = 0.0
            terminated[restarting] = truncated[restarting] = False
        self.pending_reset = terminated | truncated
        return self._observe(), reward.astype(np.float32), terminated, truncated

    # ------------------------------------------------------------------ observation
    def _observe(self):
        """observation.rs `write_state_observation` in the heading frame with the racing-line
        points: [R col 0, col 1, v, w, a_prev, target corners - p, next corners - target corners,
        4 line points - p], vectors rotated by R_z(-yaw), written as float32."""
        n = self.num_envs
        rows = np.arange(n)
        s = self.state
        p, v = s[:, 0:3], s[:, 7:10]
        qw, qi, qj, qk = s[:, 3], s[:, 4], s[:, 5], s[:, 6]
        # nalgebra's quaternion -> rotation matrix, the two columns and the heading it needs.
        ww, ii, jj, kk = qw * qw, qi * qi, qj * qj, qk * qk
        ij, wk, wj = qi * qj * 2.0, qw * qk * 2.0, qw * qj * 2.0
        ik, jk, wi = qi * qk * 2.0, qj * qk * 2.0, qw * qi * 2.0
        r00, r10, r20 = ((ww + ii) - jj) - kk, wk + ij, ik - wj
        r01, r11, r21 = ij - wk, ((ww - ii) + jj) - kk, wi + jk
        yaw = self.atan2(r10, r00).astype(np.float64)
        ch, sh = np.cos(-yaw), np.sin(-yaw)
        msh = -sh

        def heading(x, y):  # the first two rows of R_z(-yaw) applied to (x, y, ·)
            return ch * x + msh * y, sh * x + ch * y

        out = np.empty((n, OBS_DIM), dtype=np.float64)
        out[:, 0], out[:, 1] = heading(r00, r10)
        out[:, 2] = r20
        out[:, 3], out[:, 4] = heading(r01, r11)
        out[:, 5] = r21
        out[:, 6], out[:, 7] = heading(v[:, 0], v[:, 1])
        out[:, 8] = v[:, 2]
        out[:, 9:12] = s[:, 10:13]
        out[:, 12:16] = self.previous_action
        target_corners = self.gate_corners[rows, self.target]  # (n, 4, 3)
        next_corners = self.gate_corners[rows, (self.target + 1) % self.gate_count]
        to_target = target_corners - p[:, None, :]
        between = next_corners - target_corners
        hc, hs, hm = ch[:, None], sh[:, None], msh[:, None]
        out[:, 16:28] = np.stack([hc * to_target[..., 0] + hm * to_target[..., 1], hs * to_target[..., 0] + hc * to_target[..., 1],
                                  to_target[..., 2]], axis=2).reshape(n, 12)
        out[:, 28:40] = np.stack([hc * between[..., 0] + hm * between[..., 1], hs * between[..., 0] + hc * between[..., 1],
                                  between[..., 2]], axis=2).reshape(n, 12)
        ahead = self._line_ahead(p) - p[:, None, :]  # (n, 4, 3)
        out[:, 40:52] = np.stack([hc * ahead[..., 0] + hm * ahead[..., 1], hs * ahead[..., 0] + hc * ahead[..., 1],
                                  ahead[..., 2]], axis=2).reshape(n, 12)
        return out.astype(np.float32)

    def _line_ahead(self, p):
        """racing_line.rs: the sample nearest to p on the leg into the target gate, then the
        points 0, 2.5, 5 and 7.5 m of arc after it (interpolated between samples)."""
        track = self.track_index
        first = ((self.target + self.gate_count - 1) % self.gate_count) * SAMPLES_PER_SEGMENT
        base = track * self.line_stride  # where each environment's track starts in the flat arrays
        leg = (base + first)[:, None] + np.arange(SAMPLES_PER_SEGMENT)
        x, y, z = (c.take(leg) - p[:, i:i + 1] for i, c in enumerate(self.line_xyz))
        nearest = first + ((x * x + y * y) + z * z).argmin(axis=1)

        length = self.line_length[track][:, None]
        s = np.fmod(self.arc.take(base + nearest)[:, None] + np.arange(LINE_POINTS) * LINE_SPACING, length)  # (n, 4)
        # partition_point(arc <= s) - 1, saturating: one sorted search per track.
        k = np.empty(s.shape, dtype=np.int64)
        for t, rows in enumerate(self.rows_of_track):
            k[rows] = np.searchsorted(self.tracks[t].arc, s[rows], side="right")
        k = np.maximum(k - 1, 0)
        following = (k + 1) % self.line_count[track][:, None]
        k, following = base[:, None] + k, base[:, None] + following
        arc_k = self.arc.take(k)
        span = np.where(following == base[:, None], length - arc_k, self.arc.take(following) - arc_k)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(span > 0.0, (s - arc_k) / span, 0.0)[..., None]
        # nalgebra's lerp: t b + (1 - t) a.
        return t * self.line.take(following, axis=0) + (1.0 - t) * self.line.take(k, axis=0)


# ---------------------------------------------------------------------------- the check
def _chacha_known_answer():
    """ChaCha20 (10 double rounds), zero key, zero nonce, block 0: the published keystream
    starts 76 b8 e0 ad a0 f1 3d 90. Guards the block function independently of Rust."""
    streams = ChaCha8Streams(0, [0], double_rounds=10)
    streams.key[:] = 0
    first = streams._blocks(np.array([0]))[0, :2]
    return first.astype("<u4").tobytes().hex() == "76b8e0ada0f13d90"


def fly_both(names, num_envs, seed, steps, randomize, max_steps, source, libm_atan2, policy):
    """Steps dronerace.RaceVecEnv and the port side by side with the same actions (uniform
    random, or the generalist policy acting on Rust's observations); returns the differences."""
    import dronerace

    rust = dronerace.RaceVecEnv(num_envs, tracks=names, seed=seed, switching="none", randomize=randomize,
                                max_episode_steps=max_steps)
    port = NumpyRaceEnv(num_envs, names, seed=seed, randomize=randomize, max_episode_steps=max_steps or MAX_EPISODE_STEPS,
                        libm_atan2=libm_atan2)
    rng = np.random.default_rng(seed)
    obs_rust = rust.reset(seed=seed)[0].copy()
    obs_port = port.reset(seed)
    r = dict(start=np.abs(rust.states() - port.states()).max(), state=0.0, obs=np.abs(obs_rust - obs_port).max(), obs_rel=0.0,
             reward=0.0, not_identical=int((obs_rust != obs_port).sum()), entries=(steps + 1) * num_envs * OBS_DIM,
             ends_rust=[], ends_port=[], passes=0, infos_agree=True, outcomes={}, differing=set())
    for k in range(1, steps + 1):
        actions = rng.uniform(-1.0, 1.0, size=(num_envs, 4)).astype(np.float32) if source == "random" else policy.act(obs_rust)
        obs_rust, rew_rust, term_rust, trunc_rust, infos = rust.step(actions)
        obs_rust, rew_rust = obs_rust.copy(), rew_rust.copy()
        target_before = port.target.copy()
        obs_port, rew_port, term_port, trunc_port = port.step(actions)
        r["passes"] += int((port.target != target_before).sum())
        diff = np.abs(obs_rust.astype(np.float64) - obs_port)
        r["obs"] = max(r["obs"], diff.max())
        r["obs_rel"] = max(r["obs_rel"], (diff / np.maximum(np.abs(obs_rust), 1e-3)).max())
        r["not_identical"] += int((obs_rust != obs_port).sum())
        r["differing"].update(int(c) for c in np.flatnonzero((obs_rust != obs_port).any(axis=0)))
        r["reward"] = max(r["reward"], np.abs(rew_rust.astype(np.float64) - rew_port).max())
        r["state"] = max(r["state"], np.abs(rust.states() - port.states()).max())
        for ends, term, trunc in ((r["ends_rust"], term_rust, trunc_rust), (r["ends_port"], term_port, trunc_port)):
            ends += [(k, int(i), "terminated" if term[i] else "truncated") for i in np.flatnonzero(term | trunc)]
        r["infos_agree"] &= np.array_equal(infos["target_gate"], port.target) and np.array_equal(infos["laps"], port.laps)
        if "_episode" in infos:  # Rust's crash causes, which the port does not tell apart
            for i in np.flatnonzero(infos["_episode"]):
                outcome = str(infos["episode"]["outcome"][i])
                r["outcomes"][outcome] = r["outcomes"].get(outcome, 0) + 1
    r["laps"] = int(port.laps.sum())
    return r


def check(seed=7, steps=300, num_envs=18):
    """Flies the port and dronerace.RaceVecEnv from the same seed with the same actions and
    reports how far apart they are."""
    import dronerace

    assert _chacha_known_answer(), "the ChaCha block function does not reproduce the published keystream"
    names = dronerace.tracks.library_names()  # all nine, each flown by two environments
    policy = dronerace.Policy.load(str(pathlib.Path(__file__).resolve().parents[2] / "policies" / "generalist.bin"))
    scenarios = [
        # (what, randomize, max_episode_steps, actions)
        ("training env (state_agent), uniform random actions", True, None, "random"),
        ("training env (state_agent), the generalist policy's actions", True, None, "policy"),
        ("evaluation env (randomize=False), 60-step episodes, the policy's actions", False, 60, "policy"),
    ]
    print(f"ChaCha20 known-answer test (zero key and nonce): passed")
    all_ok = True
    for what, randomize, max_steps, source in scenarios:
        r = fly_both(names, num_envs, seed, steps, randomize, max_steps, source, False, policy)
        exact = fly_both(names, num_envs, seed, steps, randomize, max_steps, source, True, policy)
        same_ends = r["ends_rust"] == r["ends_port"]
        ok = same_ends and r["obs"] < 1e-4 and r["reward"] == 0.0 and r["infos_agree"]
        all_ok &= ok
        terminations = [(k, i) for k, i, kind in r["ends_rust"] if kind == "terminated"]
        truncations = [(k, i) for k, i, kind in r["ends_rust"] if kind == "truncated"]
        print(f"{what}: {num_envs} envs on {', '.join(names)} (round robin) x {steps} steps, seed {seed}")
        print(f"  start states after reset (RaceVecEnv.states()): max |diff| {r['start']:.3g}")
        print(f"  body states (float64) over all steps: max |diff| {r['state']:.3g}")
        print(f"  observations (float32): max |diff| {r['obs']:.3g}, max relative {r['obs_rel']:.3g}; "
              f"{r['not_identical']} of {r['entries']} numbers not bit-identical "
              f"(observation columns {sorted(r['differing'])}; {exact['not_identical']} with glibc's atan2 for the heading)")
        print(f"  rewards (float32): max |diff| {r['reward']:.3g}")
        print(f"  episode ends: Rust {len(terminations)} terminated + {len(truncations)} truncated, port "
              f"{len(r['ends_port'])}; the same (step, env, kind) for every one: {same_ends}; Rust's outcomes {r['outcomes']}")
        print(f"  target gates passed: {r['passes']}, laps: {r['laps']}; target gate and laps equal to RaceVecEnv's infos "
              f"at every step: {r['infos_agree']}")
        if terminations:
            print(f"  terminations (step, env): {terminations}")
        if truncations:
            print(f"  truncations (step, env): {truncations[:12]}{' ...' if len(truncations) > 12 else ''}")
    print("check:", "PASS" if all_ok else "FAIL")
    return all_ok


# ---------------------------------------------------------------------------- the benchmark
def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=96)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=1, help="timed rounds (each prints its figure)")
    parser.add_argument("--warmup", type=int, default=100, help="untimed steps first, as python_vecenv.py")
    parser.add_argument("--check", action="store_true", help="compare with dronerace.RaceVecEnv instead of timing")
    args = parser.parse_args()
    if args.check:
        raise SystemExit(0 if check() else 1)
    import dronerace

    # As docs/bench/python_vecenv.py: the library tracks round robin, the agents' training
    # environment, uniform random actions (64 batches drawn beforehand, cycled), only steps timed.
    names = dronerace.tracks.library_names()
    tracks = [names[i % len(names)] for i in range(args.envs)]
    envs = NumpyRaceEnv(args.envs, tracks, seed=0)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1.0, 1.0, size=(args.envs, 4)).astype(np.float32) for _ in range(64)]
    envs.reset(seed=0)
    for _ in range(args.warmup):
        envs.step(actions[0])
    for _ in range(args.rounds):
        episodes, seconds = 0, 0.0
        for k in range(args.steps):
            started = time.perf_counter()
            _, _, terminated, truncated = envs.step(actions[k % len(actions)])
            seconds += time.perf_counter() - started
            episodes += int((terminated | truncated).sum())
        rate = args.envs * args.steps / seconds
        print(f"numpy port: random actions, state observations, {args.envs} envs x {args.steps} steps: "
              f"{rate:.0f} env-steps/s, {episodes} episodes ended, {seconds:.2f} s")


if __name__ == "__main__":
    main()
