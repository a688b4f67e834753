//! A training pass through a layer with few outputs — the actor's action means, the critic's
//! value — one row at a time. gemm tiles its output in blocks of 64 × 6 (AVX-512), so a
//! product with four outputs or one ran at 15–50 GFLOP/s, a few per cent of the step for under
//! half a per cent of its arithmetic; here each output is a dot product vectorised over the input's
//! width. Backward, one pass over a row makes the layer's weight gradient, the gradient of the
//! layer below and that layer's activation derivative and bias gradient together, while the
//! row is in cache (gemm's products and a separate pass read it three times).
//!
//! The arithmetic is written out lane by lane ([`LANES`] partial sums, added in a fixed order;
//! fused multiply-adds, which LLVM never splits or reorders), so the AVX-512, AVX2 and plain
//! builds of these loops give the same values, bit for bit. The plain build serves x86-64 CPUs
//! without FMA (and other architectures); there each fused multiply-add is a call to libm's
//! `fmaf`, slower than gemm, but such CPUs predate AVX2.

use std::mem::MaybeUninit;

use crate::rows::{activation_gradient, assume_init};

/// The most outputs a layer may have to take this path; wider layers go through gemm.
pub const NARROW: usize = 8;

/// Partial sums per dot product: four AVX-512 registers (eight AVX2 ones), so that several
/// fused multiply-adds are in flight at once (one register's chain waited on each add's
/// latency and ran no faster than gemm).
const LANES: usize = 64;

/// `out[c] = Σ_j row[j] · weights[c][j]` for each output `c`; `weights` holds the layer's
/// weights transposed (`out.len()` rows as wide as `row`).
pub fn dots(row: &[f32], weights: &[f32], out: &mut [f32]) {
    assert!(weights.len() == out.len() * row.len(), "{} outputs of a {}-wide row", out.len(), row.len());
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has AVX-512F and FMA, checked just above.
        return unsafe { dots_avx512(row, weights, out) };
    } else if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has AVX2 and FMA, checked just above.
        return unsafe { dots_avx2(row, weights, out) };
    }
    dots_lanes(row, weights, out);
}

/// One row of the backward pass of a layer `y = x · w + b` with few outputs: given the row's
/// input `x` and output gradient `dz`, adds `dz[c] · x` to the weight gradient's row `c`
/// (`weight_gradient` holds it transposed, like `weights`) and writes `dx = Σ_c dz[c] ·
/// weights[c]`, the input's gradient, into `dx` if asked. `below` is the layer below's
/// LeakyReLU slope when `x` is its output: `dx` is then multiplied by its derivative at `x`
/// (1 where `x > 0`, the slope elsewhere) and added into the bias gradient it carries; it asks
/// for `dx`.
pub fn backward_row(
    x: &[f32],
    dz: &[f32],
    weights: &[f32],
    weight_gradient: &mut [f32],
    dx: Option<&mut [MaybeUninit<f32>]>,
    below: Option<(f32, &mut [f32])>,
) {
    let (k, n) = (x.len(), dz.len());
    assert!(weights.len() == n * k && weight_gradient.len() == n * k, "{n} outputs of a {k}-wide row");
    assert!(dx.as_ref().is_none_or(|dx| dx.len() == k) && below.as_ref().is_none_or(|(_, db)| db.len() == k), "{k}-wide");
    assert!(below.is_none() || dx.is_some(), "the layer below's gradient is made from dx");
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has AVX-512F and FMA, checked just above.
        return unsafe { backward_row_avx512(x, dz, weights, weight_gradient, dx, below) };
    } else if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has AVX2 and FMA, checked just above.
        return unsafe { backward_row_avx2(x, dz, weights, weight_gradient, dx, below) };
    }
    backward_row_lanes(x, dz, weights, weight_gradient, dx, below);
}

/// [`dots_lanes`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,fma")]
fn dots_avx512(row: &[f32], weights: &[f32], out: &mut [f32]) {
    dots_lanes(row, weights, out);
}

/// [`dots_lanes`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dots_avx2(row: &[f32], weights: &[f32], out: &mut [f32]) {
    dots_lanes(row, weights, out);
}

/// [`backward_row_lanes`] compiled for AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,fma")]
fn backward_row_avx512(
    x: &[f32],
    dz: &[f32],
    weights: &[f32],
    weight_gradient: &mut [f32],
    dx: Option<&mut [MaybeUninit<f32>]>,
    below: Option<(f32, &mut [f32])>,
) {
    backward_row_lanes(x, dz, weights, weight_gradient, dx, below);
}

/// [`backward_row_lanes`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn backward_row_avx2(
    x: &[f32],
    dz: &[f32],
    weights: &[f32],
    weight_gradient: &mut [f32],
    dx: Option<&mut [MaybeUninit<f32>]>,
    below: Option<(f32, &mut [f32])>,
) {
    backward_row_lanes(x, dz, weights, weight_gradient, dx, below);
}

/// [`dots`] for each number of outputs up to [`NARROW`]: with the number known, the loops over
/// outputs and lanes unroll (on AVX-512 the sums of up to four outputs stay in registers).
#[inline(always)]
fn dots_lanes(row: &[f32], weights: &[f32], out: &mut [f32]) {
    match out.len() {
        0 => {}
        1 => dots_of::<1>(row, weights, out),
        2 => dots_of::<2>(row, weights, out),
        3 => dots_of::<3>(row, weights, out),
        4 => dots_of::<4>(row, weights, out),
        5 => dots_of::<5>(row, weights, out),
        6 => dots_of::<6>(row, weights, out),
        7 => dots_of::<7>(row, weights, out),
        8 => dots_of::<8>(row, weights, out),
        n => unreachable!("at most NARROW = {NARROW} outputs, not {n}"),
    }
}

/// [`dots`] of `N` outputs as [`LANES`] partial sums each, a fused multiply-add per element (a
/// tail shorter than the lanes goes into the first ones), the lanes then added pairwise. The row
/// is read once for all outputs.
#[inline(always)]
fn dots_of<const N: usize>(row: &[f32], weights: &[f32], out: &mut [f32]) {
    let k = row.len();
    let w: [(&[[f32; LANES]], &[f32]); N] = std::array::from_fn(|c| weights[c * k..][..k].as_chunks::<LANES>());
    let (chunks, tail) = row.as_chunks::<LANES>();
    let mut sums = [[0.0f32; LANES]; N];
    for (i, r) in chunks.iter().enumerate() {
        for (sums, (w, _)) in sums.iter_mut().zip(&w) {
            let w = &w[i];
            for l in 0..LANES {
                sums[l] = r[l].mul_add(w[l], sums[l]);
            }
        }
    }
    for (sums, (_, w_tail)) in sums.iter_mut().zip(&w) {
        for (l, (r, w)) in tail.iter().zip(*w_tail).enumerate() {
            sums[l] = r.mul_add(*w, sums[l]);
        }
    }
    for (out, sums) in out.iter_mut().zip(sums) {
        *out = pairwise_sum(sums);
    }
}

/// The sum of the lanes, halving their number each step (lane `l` takes lane `l + width`),
/// the same on every build.
#[inline(always)]
fn pairwise_sum(mut sums: [f32; LANES]) -> f32 {
    let mut width = LANES;
    while width > 1 {
        width /= 2;
        for l in 0..width {
            sums[l] += sums[l + width];
        }
    }
    sums[0]
}

/// [`backward_row`], element by element: nothing is added across elements, so however a build
/// vectorises the loops, each element gets the same operations.
#[inline(always)]
fn backward_row_lanes(
    x: &[f32],
    dz: &[f32],
    weights: &[f32],
    weight_gradient: &mut [f32],
    dx: Option<&mut [MaybeUninit<f32>]>,
    below: Option<(f32, &mut [f32])>,
) {
    let k = x.len();
    for (c, d) in dz.iter().enumerate() {
        for (g, x) in weight_gradient[c * k..][..k].iter_mut().zip(x) {
            *g = d.mul_add(*x, *g);
        }
    }
    let Some(dx) = dx else { return };
    // dx = dz[0]·w[0] + dz[1]·w[1] + …, one output at a time over the whole row.
    let first = &weights[..k];
    for (j, dx) in dx.iter_mut().enumerate() {
        dx.write(dz[0] * first[j]);
    }
    // SAFETY: every element was just written.
    let dx = unsafe { assume_init(dx) };
    for (c, d) in dz.iter().enumerate().skip(1) {
        for (dx, w) in dx.iter_mut().zip(&weights[c * k..][..k]) {
            *dx = d.mul_add(*w, *dx);
        }
    }
    if let Some((slope, bias_gradient)) = below {
        activation_gradient(dx, x, bias_gradient, slope);
    }
}

/// `weights` (`rows × cols`, row-major) transposed.
pub fn transpose(weights: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    assert_eq!(weights.len(), rows * cols, "{rows} × {cols}");
    (0..cols).flat_map(|c| (0..rows).map(move |r| weights[r * cols + c])).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    fn random(n: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
        (0..n).map(|_| rng.sample(StandardNormal)).collect()
    }

    fn close(a: f32, b: f64, what: &str) {
        assert!((f64::from(a) - b).abs() <= 1e-5 * b.abs().max(1.0), "{what}: {a} against {b}");
    }

    /// The dot products and every gradient of one row agree with the same sums in f64, for
    /// widths around the lanes' (tails included) and one to [`NARROW`] outputs; the derivative
    /// of the layer below takes the slope where its output is not positive.
    #[test]
    fn a_row_forward_and_backward_agree_with_f64_sums() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for (k, n) in [(1, 1), (15, 4), (16, 1), (17, 8), (52, 3), (512, 4)] {
            let (x, w, dz) = (random(k, &mut rng), random(n * k, &mut rng), random(n, &mut rng));
            let mut out = vec![0.0; n];
            dots(&x, &w, &mut out);
            let mut gradient = random(n * k, &mut rng);
            let before = gradient.clone();
            let mut dx = vec![MaybeUninit::uninit(); k];
            let mut bias_gradient = vec![0.5f32; k];
            backward_row(&x, &dz, &w, &mut gradient, Some(&mut dx), Some((0.01, &mut bias_gradient)));
            for c in 0..n {
                let want: f64 = (0..k).map(|j| f64::from(x[j]) * f64::from(w[c * k + j])).sum();
                close(out[c], want, "dot");
                for j in 0..k {
                    close(gradient[c * k + j], f64::from(before[c * k + j]) + f64::from(dz[c]) * f64::from(x[j]), "dw");
                }
            }
            for j in 0..k {
                let slope = if x[j] > 0.0 { 1.0 } else { 0.01 };
                let want = slope * (0..n).map(|c| f64::from(dz[c]) * f64::from(w[c * k + j])).sum::<f64>();
                // SAFETY: backward_row writes every element of dx it is given.
                close(unsafe { dx[j].assume_init() }, want, "dx");
                close(bias_gradient[j], 0.5 + want, "bias gradient");
            }
        }
    }

    type BackwardRow = fn(&[f32], &[f32], &[f32], &mut [f32], Option<&mut [MaybeUninit<f32>]>, Option<(f32, &mut [f32])>);

    /// The plain build of the loops gives the CPU's vectorised one bit for bit.
    #[test]
    fn the_plain_loops_give_the_vectorised_ones_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let (k, n) = (77, 5);
        let (x, w, dz) = (random(k, &mut rng), random(n * k, &mut rng), random(n, &mut rng));
        let (mut fast, mut plain) = (vec![0.0; n], vec![0.0; n]);
        dots(&x, &w, &mut fast);
        dots_lanes(&x, &w, &mut plain);
        assert!(fast == plain, "dots: {fast:?} against {plain:?}");
        let run = |backward: BackwardRow| {
            let (mut gradient, mut dx, mut db) = (vec![0.25; n * k], vec![MaybeUninit::uninit(); k], vec![0.0; k]);
            backward(&x, &dz, &w, &mut gradient, Some(&mut dx), Some((0.01, &mut db)));
            // SAFETY: backward_row writes every element of dx it is given.
            (gradient, dx.into_iter().map(|v| unsafe { v.assume_init() }).collect::<Vec<f32>>(), db)
        };
        let plain = run(backward_row_lanes);
        assert!(run(backward_row) == plain, "the backward row differs between builds");
        // The AVX2 build too, where the CPU has it (with AVX-512, `dots` took the AVX-512 one).
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            let mut avx2 = vec![0.0; n];
            // SAFETY: the CPU has AVX2 and FMA, checked just above.
            unsafe { dots_avx2(&x, &w, &mut avx2) };
            assert!(avx2 == fast, "dots: AVX2 {avx2:?} against {fast:?}");
            // SAFETY: as above.
            assert!(run(|x, dz, w, g, dx, below| unsafe { backward_row_avx2(x, dz, w, g, dx, below) }) == plain, "AVX2 backward row");
        }
    }

    #[test]
    fn transpose_swaps_rows_and_columns() {
        assert_eq!(transpose(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 2, 3), [1.0, 4.0, 2.0, 5.0, 3.0, 6.0]);
    }
}
