//! A dense layer — matrix product, bias and optional LeakyReLU — as one autodiff node on the flex
//! backend. Through burn's ops the same layer is a matrix product plus five element-wise ops
//! forward and as many backward, each a full pass over a `batch × width` activation; here it is one
//! product and one pass forward, and two products and one pass backward
//! (docs/notebook/throughput.md, "The fused dense layer"). Other devices take burn's ops, which
//! compute the same function.

use std::mem::MaybeUninit;

use burn::backend::Autodiff;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::NoCheckpointing;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::{Flex, FlexTensor};
use burn::backend::tensor::FloatTensor;
use burn::tensor::activation::relu;
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

/// The autodiff flex backend that training runs on.
type Tracked = Autodiff<Flex, NoCheckpointing>;

/// Rows per part of a layer's pass. Each pass is one parallel region over parts of this many
/// rows, a part's products and element-wise work on one thread: per product and pass, waking
/// the other thread cost more than its share of a product at 4,000 rows
/// (docs/notebook/throughput.md). Fixed, so that the weight and bias gradients' partial sums are
/// added in the same order whatever the thread count (exact resume relies on it).
const PART_ROWS: usize = 1024;

/// Rows per part of a training pass over `rows` rows: [`PART_ROWS`], but a pass of 257 to
/// 1,024 rows is cut in two, so that both cores work on it (the mirror term's share of a
/// minibatch is such a pass). A function of `rows` alone, for the same reason as `PART_ROWS`.
/// Inference keeps `PART_ROWS`: an evaluation's actions stay what they were, bit for bit.
fn training_part_rows(rows: usize) -> usize {
    if rows <= PART_ROWS { rows.div_ceil(2).max(PART_ROWS / 4) } else { PART_ROWS }
}

/// `activation(x · weight + bias)` for `x: [batch, in]`, `weight: [in, out]`, `bias: [out]`;
/// `leaky_slope` `Some(s)` applies LeakyReLU with negative slope `s`, `None` none.
pub fn dense(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>, leaky_slope: Option<f64>) -> Tensor<2> {
    let slope = leaky_slope.map(|s| s as f32);
    if let (Ok(x), Ok(w), Ok(b)) = (
        x.clone().try_into_primitive::<Tracked>(),
        weight.clone().try_into_primitive::<Tracked>(),
        bias.clone().try_into_primitive::<Tracked>(),
    ) {
        return Tensor::from_primitive::<Tracked>(tracked_dense(x, w, b, slope));
    }
    if let (Ok(x), Ok(w), Ok(b)) =
        (x.clone().try_into_primitive::<Flex>(), weight.clone().try_into_primitive::<Flex>(), bias.clone().try_into_primitive::<Flex>())
    {
        return Tensor::from_primitive::<Flex>(forward(&x, &w, &b, slope, PART_ROWS));
    }
    dense_by_burn_ops(x, weight, bias, leaky_slope)
}

/// LeakyReLU with negative slope `s` as `s·z + (1 − s)·relu(z)`: burn's own `leaky_relu` is a
/// branchy mask under autodiff.
pub fn leaky_relu<const D: usize>(z: Tensor<D>, s: f64) -> Tensor<D> {
    z.clone().mul_scalar(s) + relu(z).mul_scalar(1.0 - s)
}

/// The same layer through burn's ops (devices other than flex, and the tests' reference).
pub fn dense_by_burn_ops(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>, leaky_slope: Option<f64>) -> Tensor<2> {
    let z = x.matmul(weight) + bias.unsqueeze_dim(0);
    match leaky_slope {
        Some(s) => leaky_relu(z, s),
        None => z,
    }
}

/// What the backward pass needs: the layer's input, weight and output (the output's sign is the
/// pre-activation's, as the slope is positive).
#[derive(Clone, Debug)]
struct Saved {
    x: FlexTensor,
    weight: FlexTensor,
    y: FlexTensor,
    slope: Option<f32>,
}

/// The layer's node in burn's autodiff graph; parents are input, weight and bias.
#[derive(Debug)]
struct DenseBackward;

impl Backward<Flex, 3> for DenseBackward {
    type State = Saved;

    fn backward(self, ops: Ops<Saved, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<Flex>(&ops.node);
        let [x_node, weight_node, bias_node] = ops.parents;
        let (dx, dw, db) = backward(&ops.state, &dy, x_node.is_some());
        for (node, grad) in [(x_node, dx), (weight_node, Some(dw)), (bias_node, Some(db))] {
            if let (Some(node), Some(grad)) = (node, grad) {
                grads.register::<Flex>(node.id, grad);
            }
        }
    }
}

fn tracked_dense(
    x: FloatTensor<Tracked>,
    weight: FloatTensor<Tracked>,
    bias: FloatTensor<Tracked>,
    slope: Option<f32>,
) -> FloatTensor<Tracked> {
    let part_rows = training_part_rows(x.primitive().layout().shape()[0]);
    let y = forward(x.primitive(), weight.primitive(), bias.primitive(), slope, part_rows);
    match DenseBackward.prepare::<NoCheckpointing>([x.node(), weight.node(), bias.node()]).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let saved = Saved { x: x.into_primitive(), weight: weight.into_primitive(), y: y.clone(), slope };
            prep.finish(saved, y)
        }
        OpsKind::UnTracked(prep) => prep.finish(y),
    }
}

/// Row-major values of a 2-D (or 1-D) tensor and its shape, copied only if it is a strided view.
fn values(t: &FlexTensor) -> (std::borrow::Cow<'_, [f32]>, Vec<usize>) {
    let shape = t.layout().shape().to_vec();
    match t.as_slice::<f32>() {
        Some(s) => (std::borrow::Cow::Borrowed(s), shape),
        None => (std::borrow::Cow::Owned(t.to_contiguous().as_slice::<f32>().map(<[f32]>::to_vec).unwrap_or_default()), shape),
    }
}

fn tensor(values: Vec<f32>, shape: &[usize]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(values, shape.to_vec()))
}

/// The layer's output, computed in parts of `part_rows` rows, one parallel region.
fn forward(x: &FlexTensor, weight: &FlexTensor, bias: &FlexTensor, slope: Option<f32>, part_rows: usize) -> FlexTensor {
    let ((x, xs), (w, ws), (b, _)) = (values(x), values(weight), values(bias));
    let (rows, inputs, outputs) = (xs[0], xs[1], ws[1]);
    // Slope 1 is the identity: one branch-free loop (a vector blend) serves both kinds of layer.
    let s = slope.unwrap_or(1.0);
    let mut y = Vec::with_capacity(rows * outputs);
    if outputs > 0 {
        y.spare_capacity_mut()[..rows * outputs].par_chunks_mut(part_rows * outputs).enumerate().for_each(|(p, y)| {
            let part = y.len() / outputs;
            let x = &x[p * part_rows * inputs..][..part * inputs];
            // y = x · w: all row-major (column stride 1, row stride the width).
            let y = product_into(y, part, outputs, inputs, (x, 1, inputs as isize), (&w, 1, outputs as isize));
            for row in y.chunks_exact_mut(outputs) {
                bias_and_activation(row, &b, s);
            }
        });
    }
    // SAFETY: the parts cover all rows × outputs values and `product_into` wrote each of them.
    unsafe { y.set_len(rows * outputs) };
    tensor(y, &[rows, outputs])
}

/// `row = leaky(row + bias)` with slope `s`. Written without branches (max/min, and a select
/// between constants below) so that the compiler vectorises it: signs are random, and a branch
/// per element mispredicts half the time.
fn bias_and_activation(row: &mut [f32], bias: &[f32], s: f32) {
    let n = row.len().min(bias.len());
    let (row, bias) = (&mut row[..n], &bias[..n]);
    for j in 0..n {
        let z = row[j] + bias[j];
        row[j] = z.max(0.0) + s * z.min(0.0);
    }
}

/// `dz = dy ⊙ leaky'(y)` for one row, added into `sum` (the bias gradient).
fn activation_gradient(dz: &mut [MaybeUninit<f32>], dy: &[f32], y: &[f32], sum: &mut [f32], s: f32) {
    let n = dz.len();
    assert!(dy.len() == n && y.len() == n && sum.len() == n, "one row of each");
    for j in 0..n {
        let d = dy[j] * if y[j] > 0.0 { 1.0 } else { s };
        dz[j].write(d);
        sum[j] += d;
    }
}

/// Gradients of input (if asked), weight and bias from the output's gradient `dy`.
fn backward(saved: &Saved, dy: &FlexTensor, input_gradient: bool) -> (Option<FlexTensor>, FlexTensor, FlexTensor) {
    let ((x, xs), (w, ws), (y, _), (dy, _)) = (values(&saved.x), values(&saved.weight), values(&saved.y), values(dy));
    let (rows, inputs, outputs) = (xs[0], xs[1], ws[1]);
    assert!(dy.len() == rows * outputs && y.len() == rows * outputs, "output and its gradient are {rows}×{outputs}");
    if outputs == 0 {
        // Nothing flows back through a layer without outputs.
        let dx = input_gradient.then(|| tensor(vec![0.0; rows * inputs], &[rows, inputs]));
        return (dx, tensor(vec![0.0; inputs * outputs], &[inputs, outputs]), tensor(Vec::new(), &[0]));
    }
    let s = saved.slope.unwrap_or(1.0);
    let part_rows = training_part_rows(rows);
    let (mut dz, mut dx) = (Vec::with_capacity(rows * outputs), Vec::with_capacity(if input_gradient { rows * inputs } else { 0 }));
    let mut dx_parts: Vec<Option<&mut [MaybeUninit<f32>]>> = Vec::new();
    if input_gradient && inputs > 0 {
        dx_parts.extend(dx.spare_capacity_mut()[..rows * inputs].chunks_mut(part_rows * inputs).map(Some));
    }
    // One input-gradient part per part of dz (the zip below would silently drop a mismatch).
    debug_assert!(dx_parts.is_empty() || dx_parts.len() == rows.div_ceil(part_rows));
    dx_parts.resize_with(rows.div_ceil(part_rows), || None);
    // Per part of the rows, on one thread: dz = dy ⊙ activation'(z), the part's bias and weight
    // gradients (Σ_rows dz, xᵀ·dz) and its rows of the input gradient (dz · wᵀ).
    let partials: Vec<(Vec<f32>, Vec<f32>)> = dz.spare_capacity_mut()[..rows * outputs]
        .par_chunks_mut(part_rows * outputs)
        .zip(dx_parts)
        .enumerate()
        .map(|(p, (dz, dx))| {
            let part = dz.len() / outputs;
            let (start, end) = (p * part_rows, p * part_rows + part);
            let mut db = vec![0.0f32; outputs];
            for ((dz, dy), y) in dz
                .chunks_exact_mut(outputs)
                .zip(dy[start * outputs..end * outputs].chunks_exact(outputs))
                .zip(y[start * outputs..end * outputs].chunks_exact(outputs))
            {
                activation_gradient(dz, dy, y, &mut db, s);
            }
            // SAFETY: `activation_gradient` wrote every element of every row of the part.
            let dz = unsafe { assume_init(dz) };
            let x = &x[start * inputs..end * inputs];
            // xᵀ read from x's storage with its strides swapped.
            let dw = product(inputs, outputs, part, (x, inputs as isize, 1), (dz, 1, outputs as isize));
            if let Some(dx) = dx {
                product_into(dx, part, inputs, outputs, (dz, 1, outputs as isize), (&w, outputs as isize, 1));
            }
            (db, dw)
        })
        .collect();
    // SAFETY: the parts cover all rows and wrote every value of dz, and of dx when it is asked.
    unsafe {
        dz.set_len(rows * outputs);
        if input_gradient && inputs > 0 {
            dx.set_len(rows * inputs);
        }
    }
    // Partial sums added in part order.
    let (mut db, mut dw) = (vec![0.0f32; outputs], vec![0.0f32; inputs * outputs]);
    for (pdb, pdw) in &partials {
        add(&mut db, pdb);
        add(&mut dw, pdw);
    }
    let dx = input_gradient.then(|| tensor(dx, &[rows, inputs]));
    (dx, tensor(dw, &[inputs, outputs]), tensor(db, &[outputs]))
}

/// `sum += part`, element by element.
fn add(sum: &mut [f32], part: &[f32]) {
    for (s, p) in sum.iter_mut().zip(part) {
        *s += p;
    }
}

/// The values of a slice every element of which has been written.
///
/// # Safety
/// Every element of `values` must be initialised.
unsafe fn assume_init(values: &mut [MaybeUninit<f32>]) -> &mut [f32] {
    // SAFETY: MaybeUninit<f32> has f32's layout, and the caller vouches for every element.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<f32>(), values.len()) }
}

/// `lhs[m × k] · rhs[k × n]`, row-major, each operand given as (values, column stride, row
/// stride), on the calling thread.
fn product(m: usize, n: usize, k: usize, lhs: (&[f32], isize, isize), rhs: (&[f32], isize, isize)) -> Vec<f32> {
    let mut dst = Vec::with_capacity(m * n);
    product_into(&mut dst.spare_capacity_mut()[..m * n], m, n, k, lhs, rhs);
    // SAFETY: `product_into` wrote all m × n values.
    unsafe { dst.set_len(m * n) };
    dst
}

/// [`product`] written into `dst` (m × n values at row stride n), which it returns initialised.
/// `dst` is not zeroed first: gemm writes every element (a memset of every activation and
/// gradient was 3–5 % of the step).
fn product_into<'a>(
    dst: &'a mut [MaybeUninit<f32>],
    m: usize,
    n: usize,
    k: usize,
    lhs: (&[f32], isize, isize),
    rhs: (&[f32], isize, isize),
) -> &'a mut [f32] {
    let reach = |(values, cs, rs): (&[f32], isize, isize), rows: usize, cols: usize| {
        rows == 0 || cols == 0 || (rows - 1) * (rs as usize) + (cols - 1) * (cs as usize) < values.len()
    };
    assert!(reach(lhs, m, k) && reach(rhs, k, n) && dst.len() == m * n, "operands hold {m}×{k} and {k}×{n} values, the result {m}×{n}");
    if k == 0 {
        for v in dst.iter_mut() {
            v.write(0.0);
        }
        // SAFETY: every element was just written.
        return unsafe { assume_init(dst) };
    }
    // SAFETY: the assertion keeps every index the strides reach inside the operands; `dst` holds
    // m × n values at row stride n and aliases nothing; with `read_dst` false and k ≥ 1 gemm
    // writes every element of it.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr().cast::<f32>(),
            1,
            n as isize,
            false,
            lhs.0.as_ptr(),
            lhs.1,
            lhs.2,
            rhs.0.as_ptr(),
            rhs.1,
            rhs.2,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
        assume_init(dst)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    fn random(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
        (0..rows * cols).map(|_| rng.sample(StandardNormal)).collect()
    }

    type Layer = fn(Tensor<2>, Tensor<2>, Tensor<1>, Option<f64>) -> Tensor<2>;

    fn values_of<const D: usize>(t: Tensor<D>) -> Vec<f32> {
        t.into_data().try_into_vec::<f32>().unwrap()
    }

    /// Value and every gradient of a two-layer stack (the input tracked too) agree with burn's
    /// own ops, for shapes that are not multiples of the part or kernel sizes (three parts, the
    /// last short, so the partial gradients are summed; and a short pass cut in two).
    #[test]
    fn fused_layers_match_burns_ops_in_value_and_gradients() {
        for rows in [2 * PART_ROWS + 203, 701] {
            fused_layers_match_burns_ops_at(rows);
        }
    }

    fn fused_layers_match_burns_ops_at(rows: usize) {
        let device = Device::flex().autodiff();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (inputs, hidden, outputs) = (7, 33, 5);
        let leaf = |v: Vec<f32>, shape: [usize; 2]| Tensor::<2>::from_data(TensorData::new(v, shape), &device).require_grad();
        let x = leaf(random(rows, inputs, &mut rng), [rows, inputs]);
        let w1 = leaf(random(inputs, hidden, &mut rng), [inputs, hidden]);
        let w2 = leaf(random(hidden, outputs, &mut rng), [hidden, outputs]);
        let b1 = Tensor::<1>::from_data(TensorData::new(random(1, hidden, &mut rng), [hidden]), &device).require_grad();
        let b2 = Tensor::<1>::from_data(TensorData::new(random(1, outputs, &mut rng), [outputs]), &device).require_grad();
        let weights = Tensor::<2>::from_data(TensorData::new(random(rows, outputs, &mut rng), [rows, outputs]), &device);
        let run = |layer: Layer| {
            let h = layer(x.clone(), w1.clone(), b1.clone(), Some(0.01));
            let y = layer(h, w2.clone(), b2.clone(), None);
            let grads = (y.clone() * weights.clone()).sum().backward();
            let grad = |t: &Tensor<2>| values_of(t.grad(&grads).unwrap());
            let bias_grad = |t: &Tensor<1>| values_of(t.grad(&grads).unwrap());
            [values_of(y), grad(&x), grad(&w1), grad(&w2), bias_grad(&b1), bias_grad(&b2)]
        };
        let (fused, reference) = (run(dense), run(dense_by_burn_ops));
        for (name, (a, b)) in ["output", "dx", "dw1", "dw2", "db1", "db2"].iter().zip(fused.iter().zip(&reference)) {
            assert_eq!(a.len(), b.len(), "{name}");
            let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            let worst = a.iter().zip(b).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst <= 1e-5 * scale, "{rows} rows, {name}: fused and burn's ops differ by {worst} (scale {scale})");
        }
    }

    /// A training pass is cut into parts by its row count alone: short passes in two, long
    /// ones in parts of `PART_ROWS`, the smallest in one.
    #[test]
    fn training_passes_are_cut_by_their_row_count() {
        let parts = |rows: usize| rows.div_ceil(training_part_rows(rows));
        assert_eq!([parts(32), parts(256), parts(257), parts(701), parts(1000), parts(1024)], [1, 1, 2, 2, 2, 2]);
        assert_eq!([parts(1025), parts(4000), parts(24_000)], [2, 4, 24]);
        assert_eq!(training_part_rows(1000), 500);
    }

    /// LeakyReLU's value and gradient per element, through an identity layer, on both paths:
    /// torch's convention, including the negative slope as the gradient at 0.
    #[test]
    fn leaky_relu_has_torchs_value_and_gradient() {
        let device = Device::flex().autodiff();
        let xs = [-3.0f32, -0.25, 0.0, 0.5, 7.0];
        let n = xs.len();
        let identity: Vec<f32> = (0..n * n).map(|i| if i % (n + 1) == 0 { 1.0 } else { 0.0 }).collect();
        for layer in [dense as Layer, dense_by_burn_ops] {
            let x = Tensor::<2>::from_data(TensorData::new(xs.to_vec(), [1, n]), &device).require_grad();
            let w = Tensor::<2>::from_data(TensorData::new(identity.clone(), [n, n]), &device);
            let y = layer(x.clone(), w, Tensor::zeros([n], &device), Some(0.01));
            let grad = values_of(x.grad(&y.clone().sum().backward()).expect("x takes part"));
            for ((x, y), g) in xs.iter().zip(values_of(y)).zip(grad) {
                let (value, slope) = if *x > 0.0 { (*x, 1.0) } else { (0.01 * x, 0.01) };
                assert!((y - value).abs() <= 1e-6 * value.abs(), "f({x}) = {y}, want {value}");
                assert!((g - slope).abs() < 1e-7, "f'({x}) = {g}, want {slope}");
            }
        }
    }

    /// Without autodiff (inference) the layer takes the fused forward and gives the same values.
    #[test]
    fn inference_device_gives_the_same_values() {
        let device = Device::flex();
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let x = Tensor::<2>::from_data(TensorData::new(random(9, 4, &mut rng), [9, 4]), &device);
        let w = Tensor::<2>::from_data(TensorData::new(random(4, 6, &mut rng), [4, 6]), &device);
        let b = Tensor::<1>::from_data(TensorData::new(random(1, 6, &mut rng), [6]), &device);
        let fused = values_of(dense(x.clone(), w.clone(), b.clone(), Some(0.2)));
        let reference = values_of(dense_by_burn_ops(x, w, b, Some(0.2)));
        for (a, b) in fused.iter().zip(&reference) {
            assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{a} vs {b}");
        }
        assert!(reference.iter().any(|v| *v < 0.0), "the slope is exercised");
    }
}
