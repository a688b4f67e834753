//! The vision agent's camera (SPEC §5): an 84×84 greyscale image of the gate frames seen by a
//! pinhole camera at the centre of mass, tilted up 30°, with a 90° field of view both ways.
//!
//! Each pixel is the colour of the nearest gate-frame surface hit by the ray through its
//! centre: target gate 255, the gate after it 155, every other gate 55, background 0. Rather
//! than casting every ray against every frame, each gate's outer box is clipped at the
//! camera's near plane and projected to a pixel rectangle first, and only the rays inside it
//! are tested exactly against the frame's four bars (slab tests); a depth buffer keeps the
//! nearest hit. The culling only skips rays that cannot hit, so the image is the one a
//! brute-force ray caster gives.

use std::cell::RefCell;

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::track::{GATE_HALF_DEPTH, GATE_HALF_OPENING, GATE_HALF_OUTER, Gate, Track};

/// Camera tilt above the body x axis (rad): the forward camera of the vision profile (SPEC §5).
pub const CAMERA_TILT: f64 = 30.0 * std::f64::consts::PI / 180.0;
/// Image width and height (pixels).
pub const IMAGE_SIDE: usize = 84;
/// Pixels in one image.
pub const IMAGE_PIXELS: usize = IMAGE_SIDE * IMAGE_SIDE;
/// Colour of the target gate.
pub const TARGET_COLOUR: u8 = 255;
/// Colour of the gate after the target.
pub const NEXT_COLOUR: u8 = 155;
/// Colour of every other gate.
pub const OTHER_COLOUR: u8 = 55;

/// Where the camera was at one step and which gate was the target (its brightest): enough to
/// render the image seen again (the renderer is deterministic), in ~60 bytes instead of 7 kB.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// Target gate.
    pub target: u32,
    /// Position (m, world).
    pub position: [f64; 3],
    /// Body attitude quaternion (w, x, y, z).
    pub attitude: [f64; 4],
}

impl CameraPose {
    /// Renders the image seen from this pose on `track` into `out` (`IMAGE_PIXELS` bytes).
    pub fn render(&self, track: &Track, out: &mut [u8]) {
        let (position, rotation) = self.position_and_rotation();
        render(track, self.target as usize, &position, &rotation, out);
    }

    /// Position and `R_WB`.
    pub fn position_and_rotation(&self) -> (Vector3<f64>, Matrix3<f64>) {
        let [w, x, y, z] = self.attitude;
        let rotation = UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)).to_rotation_matrix().into_inner();
        (Vector3::from(self.position), rotation)
    }
}

/// Half the image side in pixels: `u = (c + 0.5 − 42) / 42` spans tan(±45°).
const HALF: f64 = IMAGE_SIDE as f64 / 2.0;

/// The camera axes in the world for a body attitude: columns x_c (forward, tilted up), y_c
/// (left), z_c (up) — the body frame rotated about body y by −30° (SPEC §5).
pub fn camera_axes(body_rotation: &Matrix3<f64>) -> Matrix3<f64> {
    let (s, c) = CAMERA_TILT.sin_cos();
    let tilt = Matrix3::new(c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c);
    body_rotation * tilt
}

/// The image column and row coordinates (not rounded) of a camera-frame point in front of
/// the camera (`p.x > 0`): the inverse of the pixel-ray convention.
fn project(p: &Vector3<f64>) -> (f64, f64) {
    let u = -p.y / p.x;
    let v = -p.z / p.x;
    (HALF * u + HALF - 0.5, HALF * v + HALF - 0.5)
}

/// Colour of gate `index` when `target` is the gate to fly through next.
pub fn gate_colour(index: usize, target: usize, gates: usize) -> u8 {
    if index == target {
        TARGET_COLOUR
    } else if index == (target + 1) % gates {
        NEXT_COLOUR
    } else {
        OTHER_COLOUR
    }
}

/// Per-thread scratch of one image: the nearest hit so far and its colour, both 32 bits wide
/// so the per-pixel loop runs on full SIMD lanes.
struct Scratch {
    depth: Vec<f32>,
    colour: Vec<u32>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch { depth: vec![0.0; IMAGE_PIXELS], colour: vec![0; IMAGE_PIXELS] });
}

/// `u` (and `v`) of the ray through pixel column (row) `i`: `(i + 0.5 − 42) / 42`.
fn pixel_coordinate(i: usize) -> f64 {
    (i as f64 + 0.5 - HALF) / HALF
}

/// Renders what the camera of a drone at `position` with attitude `body_rotation` sees of
/// `track` when gate `target` is next, into `out` (`IMAGE_PIXELS` bytes, row-major, row 0 at
/// the top, column 0 at the left).
pub fn render(track: &Track, target: usize, position: &Vector3<f64>, body_rotation: &Matrix3<f64>, out: &mut [u8]) {
    assert_eq!(out.len(), IMAGE_PIXELS, "one 84×84 image");
    let axes = camera_axes(body_rotation);
    SCRATCH.with(|scratch| {
        let scratch = &mut *scratch.borrow_mut();
        scratch.depth.fill(f32::INFINITY);
        scratch.colour.fill(0);
        for (index, gate) in track.gates.iter().enumerate() {
            let colour = gate_colour(index, target, track.gates.len());
            draw_gate(gate, colour, position, &axes, scratch);
        }
        for (pixel, colour) in out.iter_mut().zip(&scratch.colour) {
            *pixel = *colour as u8;
        }
    });
}

/// The ray origin and the camera axes in one gate's frame, in f32 for the per-pixel work.
#[derive(Clone, Copy)]
struct GateView {
    origin: [f32; 3],
    x_c: [f32; 3],
    y_c: [f32; 3],
    z_c: [f32; 3],
}

impl GateView {
    /// Direction of the ray through pixel coordinates (u, v): `x_c − u·y_c − v·z_c`. Its x_c
    /// component is 1, so the ray parameter is the depth along the optical axis.
    #[inline(always)]
    fn ray(&self, u: f32, v: f32) -> [f32; 3] {
        std::array::from_fn(|k| self.x_c[k] - u * self.y_c[k] - v * self.z_c[k])
    }
}

/// True when gate `gate`'s outer box projects into the image of a drone at `position` with
/// attitude `body_rotation`: the gate may be in view (the box's pixel rectangle, not its bars,
/// and nearer gates are not taken to hide it). What a camera-limited observation shows.
pub fn gate_in_view(gate: &Gate, position: &Vector3<f64>, body_rotation: &Matrix3<f64>) -> bool {
    gate_on_image(gate, position, &camera_axes(body_rotation)).is_some()
}

/// The pixel rectangle gate `gate`'s outer box covers seen from `position` along camera
/// `axes`, and the camera in the gate's frame; `None` when the box is off the image.
fn gate_on_image(gate: &Gate, position: &Vector3<f64>, axes: &Matrix3<f64>) -> Option<(PixelBox, GateView)> {
    // Everything in the gate's frame: the ray origin, and the camera axes as directions.
    let origin = gate.to_local(position);
    let local_dir = |w: Vector3<f64>| gate.to_local(&(gate.position + w));
    let (ax, ay, az) = (local_dir(axes.column(0).into()), local_dir(axes.column(1).into()), local_dir(axes.column(2).into()));
    // Camera coordinates of a gate-local point q: ((q − origin)·ax, (q − origin)·ay, (q − origin)·az).
    let to_camera = |q: Vector3<f64>| {
        let d = q - origin;
        Vector3::new(d.dot(&ax), d.dot(&ay), d.dot(&az))
    };
    let pixels = pixel_box(&OUTER_BOX.0, &OUTER_BOX.1, &to_camera)?;
    let f = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
    Some((pixels, GateView { origin: f(origin), x_c: f(ax), y_c: f(ay), z_c: f(az) }))
}

/// Draws one gate's frame wherever it is nearer than what is drawn already.
fn draw_gate(gate: &Gate, colour: u8, position: &Vector3<f64>, axes: &Matrix3<f64>, scratch: &mut Scratch) {
    let Some((pixels, view)) = gate_on_image(gate, position, axes) else { return };
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2, checked just above.
        unsafe { draw_pixels_avx2(&view, u32::from(colour), pixels, scratch) };
        return;
    }
    draw_pixels(&view, u32::from(colour), pixels, scratch);
}

/// [`draw_pixels`] compiled for AVX2 (8 pixels per instruction; no FMA, so the arithmetic and
/// the image are the same as on any other x86-64).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn draw_pixels_avx2(view: &GateView, colour: u32, pixels: PixelBox, scratch: &mut Scratch) {
    draw_pixels(view, colour, pixels, scratch);
}

/// Tests every ray of the pixel box against the gate's frame and keeps the nearer hits.
#[inline(always)]
fn draw_pixels(view: &GateView, colour: u32, (c0, c1, r0, r1): PixelBox, scratch: &mut Scratch) {
    let us: [f32; IMAGE_SIDE] = std::array::from_fn(|c| pixel_coordinate(c) as f32);
    for r in r0..=r1 {
        let v = pixel_coordinate(r) as f32;
        let row = r * IMAGE_SIDE + c0..=r * IMAGE_SIDE + c1;
        // Branch-free per pixel, so the loop runs on SIMD lanes.
        for ((u, pixel), nearest) in us[c0..=c1].iter().zip(&mut scratch.colour[row.clone()]).zip(&mut scratch.depth[row]) {
            let t = frame_hit(&view.origin, &view.ray(*u, v));
            let closer = t < *nearest;
            *pixel = if closer { colour } else { *pixel };
            *nearest = if closer { t } else { *nearest };
        }
    }
}

/// Inclusive pixel ranges: first and last column, first and last row.
type PixelBox = (usize, usize, usize, usize);

/// Gate-local box around the whole frame: every ray that hits a bar passes through it.
const OUTER_BOX: ([f64; 3], [f64; 3]) =
    ([-GATE_HALF_DEPTH, -GATE_HALF_OUTER, -GATE_HALF_OUTER], [GATE_HALF_DEPTH, GATE_HALF_OUTER, GATE_HALF_OUTER]);

/// Depth at which the ray `origin + t·dir` (t ≥ 0, gate-local) first meets the gate frame —
/// the four bars of `track::FRAME_BARS` as closed boxes — or infinity. One slab test per bar,
/// sharing the reciprocals and the plane crossings the bars have in common.
#[inline(always)]
fn frame_hit(origin: &[f32; 3], dir: &[f32; 3]) -> f32 {
    const DEPTH_HALF: f32 = GATE_HALF_DEPTH as f32;
    const OUTER: f32 = GATE_HALF_OUTER as f32;
    const INNER: f32 = GATE_HALF_OPENING as f32;
    // Plain comparisons rather than f32::min/max: no NaN bookkeeping, so the loop stays a few
    // SIMD instructions (a NaN needs a ray exactly in a bar's face plane, parallel to it).
    let min = |a: f32, b: f32| if a < b { a } else { b };
    let max = |a: f32, b: f32| if a > b { a } else { b };
    let inv = [1.0 / dir[0], 1.0 / dir[1], 1.0 / dir[2]];
    // Entry and exit of the slab lo ≤ q_k ≤ hi (a ray parallel to it gets ±∞ or no interval).
    let slab = |k: usize, lo: f32, hi: f32| {
        let (a, b) = ((lo - origin[k]) * inv[k], (hi - origin[k]) * inv[k]);
        (min(a, b), max(a, b))
    };
    let (x_in, x_out) = slab(0, -DEPTH_HALF, DEPTH_HALF);
    let near = max(x_in, 0.0);
    let (y_all, y_left, y_right) = (slab(1, -OUTER, OUTER), slab(1, INNER, OUTER), slab(1, -OUTER, -INNER));
    let (z_all, z_top, z_bottom) = (slab(2, -OUTER, OUTER), slab(2, INNER, OUTER), slab(2, -OUTER, -INNER));
    let bar = |(y_in, y_out): (f32, f32), (z_in, z_out): (f32, f32)| {
        let enter = max(max(near, y_in), z_in);
        if enter <= min(min(x_out, y_out), z_out) { enter } else { f32::INFINITY }
    };
    min(min(bar(y_all, z_top), bar(y_all, z_bottom)), min(bar(y_left, z_all), bar(y_right, z_all)))
}

/// Depth of the near plane the boxes are clipped at: rays have a unit x_c component, so a
/// point nearer than this is seen only within ±`NEAR` of the optical axis.
const NEAR: f64 = 1e-6;

/// The inclusive pixel ranges (columns, rows) that a gate-local box can cover, or `None`
/// when it is entirely behind the near plane or off the image. The box is clipped at the near
/// plane first, so a bar beside the camera costs the rays on its side, not the whole image.
fn pixel_box(lo: &[f64; 3], hi: &[f64; 3], to_camera: &impl Fn(Vector3<f64>) -> Vector3<f64>) -> Option<PixelBox> {
    let corners: [Vector3<f64>; 8] = std::array::from_fn(|i| {
        let pick = |axis: usize| if i >> axis & 1 == 0 { lo[axis] } else { hi[axis] };
        to_camera(Vector3::new(pick(0), pick(1), pick(2)))
    });
    let (mut cmin, mut cmax, mut rmin, mut rmax) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    let mut include = |p: &Vector3<f64>| {
        let (c, r) = project(p);
        (cmin, cmax, rmin, rmax) = (cmin.min(c), cmax.max(c), rmin.min(r), rmax.max(r));
    };
    for (i, p) in corners.iter().enumerate() {
        if p.x >= NEAR {
            include(p);
        }
        // Where an edge (corners differing in one index bit) crosses the near plane.
        for bit in [1, 2, 4] {
            let q = &corners[i ^ bit];
            if i & bit == 0 && (p.x < NEAR) != (q.x < NEAR) {
                let s = (NEAR - p.x) / (q.x - p.x);
                include(&(p + (q - p) * s));
            }
        }
    }
    if cmin > cmax {
        return None; // the whole box is behind the near plane
    }
    let last = (IMAGE_SIDE - 1) as f64;
    // A hair of slack so that rounding in the projection never culls a ray the exact test hits.
    let (c0, c1) = ((cmin - 1e-6).ceil().max(0.0), (cmax + 1e-6).floor().min(last));
    let (r0, r1) = ((rmin - 1e-6).ceil().max(0.0), (rmax + 1e-6).floor().min(last));
    (c0 <= c1 && r0 <= r1).then_some((c0 as usize, c1 as usize, r0 as usize, r1 as usize))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Arena, FRAME_BARS};
    use nalgebra::Rotation3;

    fn track(gates: &[([f64; 3], f64)]) -> Track {
        let gates = gates.iter().map(|(p, yaw)| Gate::new(Vector3::from(*p), *yaw)).collect();
        Track::new("t", gates, None, Arena::default()).unwrap()
    }

    /// Body attitude whose camera looks horizontally along +x (the body pitched nose-down by
    /// the tilt).
    fn level_camera() -> Matrix3<f64> {
        Rotation3::from_axis_angle(&Vector3::y_axis(), CAMERA_TILT).into_inner()
    }

    fn painted(image: &[u8]) -> usize {
        image.iter().filter(|&&p| p != 0).count()
    }

    #[test]
    fn a_gate_straight_ahead_covers_the_analytic_pixel_box() {
        // Gate facing the camera 4 m ahead: the outer edge of its near face at depth 3.95
        // bounds the frame; the inner edge of its far face at depth 4.05 bounds the hole.
        let distance = 4.0;
        let t = track(&[([distance, 0.0, 3.0], 0.0), ([distance, 6.0, 3.0], 0.0)]);
        let mut image = vec![0u8; IMAGE_PIXELS];
        render(&t, 0, &Vector3::new(0.0, 0.0, 3.0), &level_camera(), &mut image);
        let outer = GATE_HALF_OUTER / (distance - GATE_HALF_DEPTH);
        let hole = GATE_HALF_OPENING / (distance + GATE_HALF_DEPTH);
        for r in 0..IMAGE_SIDE {
            for c in 0..IMAGE_SIDE {
                let (u, v) = (pixel_coordinate(c), pixel_coordinate(r));
                let in_frame = u.abs() <= outer && v.abs() <= outer && !(u.abs() < hole && v.abs() < hole);
                let expected = if in_frame { TARGET_COLOUR } else { 0 };
                assert_eq!(image[r * IMAGE_SIDE + c], expected, "row {r} column {c} (u {u:.4}, v {v:.4})");
            }
        }
        assert!(painted(&image) > 150, "the frame is drawn: {}", painted(&image));
    }

    #[test]
    fn brightness_follows_gate_order() {
        // Three gates side by side 5 m ahead, each well inside the image.
        let t = track(&[([5.0, 2.5, 3.0], 0.0), ([5.0, 0.0, 3.0], 0.0), ([5.0, -2.5, 3.0], 0.0)]);
        let mut image = vec![0u8; IMAGE_PIXELS];
        let colour_at = |image: &[u8], y: f64| {
            // Column of the left bar's centre line of the gate centred at lateral offset y.
            let u = -(y + 0.875) / (5.0 - GATE_HALF_DEPTH);
            let c = (HALF * u + HALF - 0.5).round() as usize;
            image[(IMAGE_SIDE / 2) * IMAGE_SIDE + c]
        };
        let position = Vector3::new(0.0, 0.0, 3.0);
        render(&t, 0, &position, &level_camera(), &mut image);
        assert_eq!([2.5, 0.0, -2.5].map(|y| colour_at(&image, y)), [TARGET_COLOUR, NEXT_COLOUR, OTHER_COLOUR]);
        render(&t, 1, &position, &level_camera(), &mut image);
        assert_eq!([2.5, 0.0, -2.5].map(|y| colour_at(&image, y)), [OTHER_COLOUR, TARGET_COLOUR, NEXT_COLOUR]);
        render(&t, 2, &position, &level_camera(), &mut image);
        assert_eq!([2.5, 0.0, -2.5].map(|y| colour_at(&image, y)), [NEXT_COLOUR, OTHER_COLOUR, TARGET_COLOUR]);
    }

    #[test]
    fn a_nearer_gate_hides_a_farther_one() {
        // Gate 1 (next, 155) 3 m ahead in front of gate 0 (target, 255) 8 m ahead, same line
        // of sight: wherever both could be seen, the near one's colour wins.
        let t = track(&[([8.0, 0.0, 3.0], 0.0), ([3.0, 0.0, 3.0], 0.0)]);
        let mut image = vec![0u8; IMAGE_PIXELS];
        render(&t, 0, &Vector3::new(0.0, 0.0, 3.0), &level_camera(), &mut image);
        let far_only = track(&[([8.0, 0.0, 3.0], 0.0), ([3.0, 10.0, 3.0], 0.0)]);
        let mut far_image = vec![0u8; IMAGE_PIXELS];
        render(&far_only, 0, &Vector3::new(0.0, 0.0, 3.0), &level_camera(), &mut far_image);
        let (mut hidden, mut seen_through) = (0, 0);
        for p in 0..IMAGE_PIXELS {
            if far_image[p] == TARGET_COLOUR {
                match image[p] {
                    NEXT_COLOUR => hidden += 1,
                    TARGET_COLOUR => seen_through += 1,
                    other => panic!("pixel {p}: {other}"),
                }
            }
        }
        // The far gate (outer 1 m at 8 m) lies inside the near gate's opening (0.75 m at 3 m),
        // so nothing of it is hidden; move the near gate so its bar crosses the line of sight.
        assert!(seen_through > 0 && hidden == 0);
        let crossing = track(&[([8.0, 0.0, 3.0], 0.0), ([3.0, 0.0, 3.0 + 0.875], 0.0)]);
        render(&crossing, 0, &Vector3::new(0.0, 0.0, 3.0), &level_camera(), &mut image);
        // The near gate's bottom bar now crosses the centre row where the far gate's side
        // bars are: there the near colour wins.
        let centre_row = IMAGE_SIDE / 2 * IMAGE_SIDE;
        let behind_bar: Vec<usize> = (0..IMAGE_SIDE).filter(|&c| far_image[centre_row + c] == TARGET_COLOUR).collect();
        assert!(!behind_bar.is_empty(), "the far gate's bars cross the centre row on their own");
        for c in behind_bar {
            assert_eq!(image[centre_row + c], NEXT_COLOUR, "column {c}: the near bar hides the far gate");
        }
    }

    /// Every ray against every gate, without culling; with `exact_bars` each bar of
    /// `FRAME_BARS` is tested on its own in f64 (an independent statement of the geometry),
    /// otherwise with the renderer's own f32 kernel.
    fn brute_force(track: &Track, target: usize, position: &Vector3<f64>, body_rotation: &Matrix3<f64>, exact_bars: bool) -> Vec<u8> {
        let axes = camera_axes(body_rotation);
        let mut image = vec![0u8; IMAGE_PIXELS];
        for (p, pixel) in image.iter_mut().enumerate() {
            let (u, v) = (pixel_coordinate(p % IMAGE_SIDE), pixel_coordinate(p / IMAGE_SIDE));
            let world_dir: Vector3<f64> = axes.column(0) - u * axes.column(1) - v * axes.column(2);
            let mut nearest = f64::INFINITY;
            for (index, gate) in track.gates.iter().enumerate() {
                let dir = gate.to_local(&(gate.position + world_dir));
                let origin = gate.to_local(position);
                let t = if exact_bars {
                    FRAME_BARS.iter().filter_map(|(lo, hi)| ray_box(&origin, &dir, lo, hi)).fold(f64::INFINITY, f64::min)
                } else {
                    let f = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
                    let view = GateView {
                        origin: f(origin),
                        x_c: f(gate.to_local(&(gate.position + axes.column(0)))),
                        y_c: f(gate.to_local(&(gate.position + axes.column(1)))),
                        z_c: f(gate.to_local(&(gate.position + axes.column(2)))),
                    };
                    f64::from(frame_hit(&view.origin, &view.ray(u as f32, v as f32)))
                };
                if t < nearest {
                    nearest = t;
                    *pixel = gate_colour(index, target, track.gates.len());
                }
            }
        }
        image
    }

    /// Where the ray `origin + t·dir` (t ≥ 0) first meets the closed box `[lo, hi]`, if it does.
    fn ray_box(origin: &Vector3<f64>, dir: &Vector3<f64>, lo: &[f64; 3], hi: &[f64; 3]) -> Option<f64> {
        let (mut near, mut far) = (0.0f64, f64::INFINITY);
        for axis in 0..3 {
            let (o, d) = (origin[axis], dir[axis]);
            if d == 0.0 {
                if o < lo[axis] || o > hi[axis] {
                    return None;
                }
                continue;
            }
            let (t1, t2) = ((lo[axis] - o) / d, (hi[axis] - o) / d);
            near = near.max(t1.min(t2));
            far = far.min(t1.max(t2));
        }
        (near <= far).then_some(near)
    }

    #[test]
    fn culled_rendering_equals_brute_force_ray_casting() {
        use rand::{Rng, SeedableRng};
        let t = track(&[([4.0, 0.0, 2.0], 0.3), ([0.0, 5.0, 3.0], 2.0), ([-4.0, 0.5, 1.5], -2.8), ([0.5, -5.0, 2.5], -0.9)]);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut image = vec![0u8; IMAGE_PIXELS];
        let (mut drawn, mut differ_from_f64_bars) = (0, 0);
        for _ in 0..200 {
            let position = Vector3::new(rng.random_range(-6.0..6.0), rng.random_range(-6.0..6.0), rng.random_range(0.5..4.5));
            let axis = nalgebra::Unit::new_normalize(Vector3::new(rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3), 1.0));
            let rotation = Rotation3::from_axis_angle(&axis, rng.random_range(-3.2..3.2)).into_inner();
            let target = rng.random_range(0..4);
            render(&t, target, &position, &rotation, &mut image);
            // Culling never changes a pixel ...
            assert_eq!(image, brute_force(&t, target, &position, &rotation, false), "pose {position:?}");
            // ... and the f32 kernel agrees with the bars in f64 but for rays grazing an edge.
            let exact = brute_force(&t, target, &position, &rotation, true);
            differ_from_f64_bars += image.iter().zip(&exact).filter(|(a, b)| a != b).count();
            drawn += painted(&image);
        }
        assert!(drawn > 10_000, "the poses see gates ({drawn} pixels)");
        assert!(differ_from_f64_bars <= 2, "{differ_from_f64_bars} of {drawn} drawn pixels differ from the f64 bars");
    }

    #[test]
    fn the_brightest_gate_moves_on_when_the_target_is_passed() {
        use crate::race::{EnvConfig, RaceEnv};
        use crate::reference_pilot::{Controller, PilotParams, ReferencePilot};
        let t = std::sync::Arc::new(track(&[
            ([4.0, 0.0, 2.0], 0.0),
            ([10.0, 4.0, 2.0], 1.2),
            ([4.0, 8.0, 2.0], 3.0),
            ([-3.0, 4.0, 2.0], -1.6),
        ]));
        let mut env = RaceEnv::new(t, EnvConfig::evaluation(), 0, 0);
        let mut pilot = ReferencePilot::new(PilotParams::default());
        pilot.reset(&env);
        let mut image = vec![0u8; IMAGE_PIXELS];
        env.render_camera(&mut image);
        let gate0_target = image.iter().filter(|&&p| p == TARGET_COLOUR).count();
        assert!(gate0_target > 0, "gate 0, straight ahead of the start, is the target");
        while env.target_gate() == 0 {
            let outcome = env.step(&pilot.act(&env));
            assert!(!outcome.done(), "the pilot passes gate 0");
        }
        env.render_camera(&mut image);
        // Just past gate 0 the drone faces away from it; what it sees in target colour is gate 1.
        let expected = brute_force(env.track(), 1, &env.body().position, &env.body().rotation(), false);
        assert_eq!(image, expected);
        let colours: std::collections::BTreeSet<u8> = image.iter().copied().collect();
        assert!(colours.contains(&TARGET_COLOUR), "gate 1 is in view as the target: {colours:?}");
        // A saved pose renders the same image again, here and after the drone has moved on.
        let pose = env.camera_pose();
        let mut again = vec![0u8; IMAGE_PIXELS];
        pose.render(env.track(), &mut again);
        assert_eq!(again, image);
        env.step(&pilot.act(&env));
        pose.render(env.track(), &mut again);
        assert_eq!(again, image, "the pose, not the environment, says what is rendered");
    }

    #[test]
    fn a_gate_behind_the_camera_draws_nothing() {
        let t = track(&[([-4.0, 0.0, 3.0], 0.0), ([-4.0, 5.0, 3.0], 0.0)]);
        let mut image = vec![7u8; IMAGE_PIXELS];
        render(&t, 0, &Vector3::new(0.0, 0.0, 3.0), &level_camera(), &mut image);
        assert_eq!(painted(&image), 0);
    }

    #[test]
    fn the_tilt_puts_a_gate_at_camera_height_below_the_centre() {
        // Level drone: the camera looks 30° up, so a gate straight ahead at its height appears
        // tan(30°)·42 ≈ 24.2 rows below the centre. Along the centre column the frame's rows
        // are those whose rays hit the top or bottom bar, computed here in the world.
        let distance = 6.0;
        let t = track(&[([distance, 0.0, 3.0], 0.0), ([distance, 8.0, 3.0], 0.0)]);
        let mut image = vec![0u8; IMAGE_PIXELS];
        render(&t, 0, &Vector3::new(0.0, 0.0, 3.0), &Matrix3::identity(), &mut image);
        let (s, c) = CAMERA_TILT.sin_cos();
        let painted_rows: Vec<usize> = (0..IMAGE_SIDE).filter(|r| image[r * IMAGE_SIDE + IMAGE_SIDE / 2 - 1] != 0).collect();
        let expected: Vec<usize> = (0..IMAGE_SIDE)
            .filter(|&r| {
                let v = pixel_coordinate(r);
                let u = pixel_coordinate(IMAGE_SIDE / 2 - 1);
                // World ray: x_c − u·y_c − v·z_c with x_c = (c, 0, s), z_c = (−s, 0, c).
                let dir = Vector3::new(c + v * s, -u, s - v * c);
                [GATE_HALF_OPENING, -GATE_HALF_OUTER].iter().any(|&bottom| {
                    let top = if bottom > 0.0 { GATE_HALF_OUTER } else { -GATE_HALF_OPENING };
                    // Hits the bar if the height at some depth in [d − 0.05, d + 0.05] is in it.
                    let heights = [distance - GATE_HALF_DEPTH, distance + GATE_HALF_DEPTH].map(|x| x / dir.x * dir.z);
                    heights[0].max(heights[1]) >= bottom && heights[0].min(heights[1]) <= top
                })
            })
            .collect();
        assert_eq!(painted_rows, expected);
        let middle = (painted_rows[0] + painted_rows[painted_rows.len() - 1]) as f64 / 2.0 + 0.5;
        let below = middle - HALF;
        assert!((below - HALF * (CAMERA_TILT.tan())).abs() < 1.5, "gate centre {below:.2} rows below the image centre");
    }
}
