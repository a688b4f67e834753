//! The three matrix products of a dense layer's PPO step (forward y = x·w, weight gradient
//! xᵀ·dz, input gradient dz·wᵀ) through the gemm crate, strided the way `kernels::dense` calls it,
//! on two threads: median GFLOP/s of 15 calls per product and shape.

use std::time::Instant;

/// dst[m × n] = lhs[m × k] · rhs[k × n], operands as (values, column stride, row stride).
fn mm(m: usize, n: usize, k: usize, dst: &mut [f32], lhs: &[f32], lcs: isize, lrs: isize, rhs: &[f32], rcs: isize, rrs: isize) {
    // SAFETY: every caller passes operands holding the m×k and k×n values its strides reach and
    // a destination of m×n values.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.as_ptr(),
            lcs,
            lrs,
            rhs.as_ptr(),
            rcs,
            rrs,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::Rayon(0),
        );
    }
}
fn med(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}
fn main() {
    for &(rows, inp, out) in &[(4096, 40, 512), (4096, 512, 512), (4000, 40, 256), (4000, 256, 256), (24000, 512, 512)] {
        let x: Vec<f32> = (0..rows * inp).map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5).collect();
        let w: Vec<f32> = (0..inp * out).map(|i| ((i * 104729) % 1000) as f32 / 1000.0 - 0.5).collect();
        let dz: Vec<f32> = (0..rows * out).map(|i| ((i * 31) % 1000) as f32 / 1000.0 - 0.5).collect();
        let (mut y, mut dw, mut dx) = (vec![0f32; rows * out], vec![0f32; inp * out], vec![0f32; rows * inp]);
        let (mut tf, mut tw, mut tx) = (vec![], vec![], vec![]);
        for _ in 0..15 {
            let t = Instant::now();
            mm(rows, out, inp, &mut y, &x, 1, inp as isize, &w, 1, out as isize);
            tf.push(t.elapsed().as_secs_f64());
            // xᵀ·dz reads x transposed in place: column stride inp, row stride 1.
            let t = Instant::now();
            mm(inp, out, rows, &mut dw, &x, inp as isize, 1, &dz, 1, out as isize);
            tw.push(t.elapsed().as_secs_f64());
            // dz·wᵀ reads w transposed in place: column stride out, row stride 1.
            let t = Instant::now();
            mm(rows, inp, out, &mut dx, &dz, 1, out as isize, &w, out as isize, 1);
            tx.push(t.elapsed().as_secs_f64());
        }
        let g = 2.0 * (rows * inp * out) as f64 / 1e9;
        println!(
            "{rows:5} x {inp:3} -> {out:3}: y=x.w {:6.1}  dw=xT.dz {:6.1}  dx=dz.wT {:6.1} GFLOP/s",
            g / med(tf),
            g / med(tw),
            g / med(tx)
        );
    }
}
