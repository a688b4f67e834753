//! The element-wise work of the dense layers' passes, one row at a time: bias and LeakyReLU
//! forward, the activation's derivative with the bias gradient backward, sums of partial
//! gradients, and a written buffer taken as values. Shared by the gemm layers
//! ([`crate::dense`]) and the row-by-row ones (`narrow`).

use std::mem::MaybeUninit;

/// `row = leaky(row + bias)` with slope `s`. Written without branches (max/min, and a select
/// between constants below) so that the compiler vectorises it: signs are random, and a branch
/// per element mispredicts half the time.
pub(crate) fn bias_and_activation(row: &mut [f32], bias: &[f32], s: f32) {
    let n = row.len().min(bias.len());
    let (row, bias) = (&mut row[..n], &bias[..n]);
    for j in 0..n {
        let z = row[j] + bias[j];
        row[j] = z.max(0.0) + s * z.min(0.0);
    }
}

/// `dz = dy ⊙ leaky'(y)` for one row, in place (`dz` holds `dy`), added into `sum` (the bias
/// gradient). Inlined, so that it takes the vector width of the function that calls it.
#[inline(always)]
pub(crate) fn activation_gradient(dz: &mut [f32], y: &[f32], sum: &mut [f32], s: f32) {
    let n = dz.len();
    assert!(y.len() == n && sum.len() == n, "one row of each");
    for j in 0..n {
        let d = dz[j] * if y[j] > 0.0 { 1.0 } else { s };
        dz[j] = d;
        sum[j] += d;
    }
}

/// `sum += part`, element by element.
pub(crate) fn add(sum: &mut [f32], part: &[f32]) {
    for (s, p) in sum.iter_mut().zip(part) {
        *s += p;
    }
}

/// The values of a slice every element of which has been written.
///
/// # Safety
/// Every element of `values` must be initialised.
pub(crate) unsafe fn assume_init(values: &mut [MaybeUninit<f32>]) -> &mut [f32] {
    // SAFETY: MaybeUninit<f32> has f32's layout, and the caller vouches for every element.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<f32>(), values.len()) }
}
