//! Dense layers — matrix product, bias and optional LeakyReLU — as one autodiff node on the flex
//! backend, a whole stack of them (an MLP) at once. Through burn's ops each layer is a matrix
//! product plus five element-wise ops forward and as many backward, each a full pass over a
//! `batch × width` activation; here a layer is one product and one pass forward, two products and
//! one pass backward (docs/notebook/throughput.md, "The fused dense layer"). A stack runs a part
//! of the rows through every layer on one thread, so a layer's output, and backward its input
//! gradient, is still in cache when the next layer reads it, and a node (up to four layers) is
//! one parallel region each way. In training, a layer of a few outputs (the actor's and the
//! critic's last) goes row by row instead of through gemm (`policy::narrow`). Other devices take
//! burn's ops, which compute the same function.

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

use crate::narrow::{self, NARROW};
use crate::rows::{activation_gradient, add, assume_init, bias_and_activation};

/// The autodiff flex backend that training runs on.
type Tracked = Autodiff<Flex, NoCheckpointing>;

/// Rows per part of a stack's pass. Each pass is one parallel region over parts of this many
/// rows, a part's products and element-wise work on one thread: per product and pass, waking
/// the other thread cost more than its share of a product at 4,000 rows
/// (docs/notebook/throughput.md). Fixed, so that the weight and bias gradients' partial sums are
/// added in the same order whatever the thread count (exact resume relies on it).
const PART_ROWS: usize = 1024;

/// Values per chunk of a weight gradient's sum over parts; a gradient of more than two chunks
/// is summed on the pool's threads, a chunk each.
const SUM_CHUNK: usize = 16 * 1024;

/// Layers per autodiff node: the node's parents (input, then each layer's weight and bias) are
/// a fixed-size array, so a stack is cut into nodes of up to this many layers.
const NODE_LAYERS: usize = 4;

/// Rows per part of a training pass over `rows` rows: [`PART_ROWS`], but a pass of 257 to
/// 1,024 rows is cut in two, so that both cores work on it (the mirror term's share of a
/// minibatch is such a pass). A function of `rows` alone, for the same reason as `PART_ROWS`.
/// Inference keeps `PART_ROWS`: an evaluation's actions stay what they were, bit for bit.
fn training_part_rows(rows: usize) -> usize {
    if rows <= PART_ROWS { rows.div_ceil(2).max(PART_ROWS / 4) } else { PART_ROWS }
}

/// One layer of a [`dense_stack`]: `weight: [in, out]`, `bias: [out]`, and LeakyReLU with
/// negative slope `leaky_slope` after it (`None`: no activation).
#[derive(Clone, Debug)]
pub struct Dense {
    /// `[in, out]`.
    pub weight: Tensor<2>,
    /// `[out]`.
    pub bias: Tensor<1>,
    /// The LeakyReLU's negative slope, or none.
    pub leaky_slope: Option<f64>,
}

/// `activation(x · weight + bias)` for `x: [batch, in]`, `weight: [in, out]`, `bias: [out]`;
/// `leaky_slope` `Some(s)` applies LeakyReLU with negative slope `s`, `None` none.
pub fn dense(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>, leaky_slope: Option<f64>) -> Tensor<2> {
    dense_stack(x, &[Dense { weight, bias, leaky_slope }])
}

/// `x` through each layer in turn. The same values as [`dense`] layer by layer, bit for bit
/// (a stack with an empty layer — no inputs or outputs — goes through burn's ops instead).
pub fn dense_stack(mut x: Tensor<2>, layers: &[Dense]) -> Tensor<2> {
    // A layer without outputs or inputs has nothing to cut into parts.
    if layers.iter().any(|l| l.weight.dims().contains(&0)) {
        return stack_by_burn_ops(x, layers);
    }
    for node in layers.chunks(NODE_LAYERS) {
        x = stack_node(x, node);
    }
    x
}

/// Up to [`NODE_LAYERS`] layers as one node on flex (with autodiff or without), burn's ops
/// elsewhere.
fn stack_node(x: Tensor<2>, layers: &[Dense]) -> Tensor<2> {
    let slopes: Vec<Option<f32>> = layers.iter().map(|l| l.leaky_slope.map(|s| s as f32)).collect();
    let tracked: Option<Vec<_>> = layers
        .iter()
        .map(|l| Some((l.weight.clone().try_into_primitive::<Tracked>().ok()?, l.bias.clone().try_into_primitive::<Tracked>().ok()?)))
        .collect();
    if let (Ok(x), Some(params)) = (x.clone().try_into_primitive::<Tracked>(), tracked) {
        let y = match params.len() {
            1 => tracked_stack::<3>(x, params, slopes),
            2 => tracked_stack::<5>(x, params, slopes),
            3 => tracked_stack::<7>(x, params, slopes),
            4 => tracked_stack::<9>(x, params, slopes),
            n => unreachable!("a node has 1 to NODE_LAYERS = 4 layers, not {n}"),
        };
        return Tensor::from_primitive::<Tracked>(y);
    }
    let untracked: Option<Vec<_>> = layers
        .iter()
        .map(|l| Some((l.weight.clone().try_into_primitive::<Flex>().ok()?, l.bias.clone().try_into_primitive::<Flex>().ok()?)))
        .collect();
    if let (Ok(x), Some(params)) = (x.clone().try_into_primitive::<Flex>(), untracked) {
        let outputs = forward(&x, &params, &slopes, PART_ROWS, false);
        return Tensor::from_primitive::<Flex>(outputs[outputs.len() - 1].clone());
    }
    stack_by_burn_ops(x, layers)
}

/// `x` through each layer by burn's ops.
fn stack_by_burn_ops(x: Tensor<2>, layers: &[Dense]) -> Tensor<2> {
    layers.iter().fold(x, |x, l| dense_by_burn_ops(x, l.weight.clone(), l.bias.clone(), l.leaky_slope))
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

/// What the backward pass needs: the stack's input, each layer's weight and output (an
/// output's sign is its pre-activation's, as the slope is positive) and slope.
#[derive(Clone, Debug)]
struct Saved {
    x: FlexTensor,
    weights: Vec<FlexTensor>,
    outputs: Vec<FlexTensor>,
    slopes: Vec<Option<f32>>,
}

/// The stack's node in burn's autodiff graph; its `N` parents are the input, then each layer's
/// weight and bias.
#[derive(Debug)]
struct StackBackward;

impl<const N: usize> Backward<Flex, N> for StackBackward {
    type State = Saved;

    fn backward(self, ops: Ops<Saved, N>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<Flex>(&ops.node);
        let x_node = ops.parents[0].clone();
        let (dx, params) = backward(&ops.state, &dy, x_node.is_some());
        if let (Some(node), Some(dx)) = (x_node, dx) {
            grads.register::<Flex>(node.id, dx);
        }
        for (l, (dw, db)) in params.into_iter().enumerate() {
            for (parent, grad) in [(1 + 2 * l, dw), (2 + 2 * l, db)] {
                if let Some(node) = &ops.parents[parent] {
                    grads.register::<Flex>(node.id, grad);
                }
            }
        }
    }
}

/// `N = 1 + 2 × layers` parents: the input, then each layer's weight and bias.
fn tracked_stack<const N: usize>(
    x: FloatTensor<Tracked>,
    params: Vec<(FloatTensor<Tracked>, FloatTensor<Tracked>)>,
    slopes: Vec<Option<f32>>,
) -> FloatTensor<Tracked> {
    assert_eq!(N, 1 + 2 * params.len(), "one parent for the input and two a layer");
    let flex: Vec<(FlexTensor, FlexTensor)> = params.iter().map(|(w, b)| (w.primitive().clone(), b.primitive().clone())).collect();
    let part_rows = training_part_rows(x.primitive().layout().shape()[0]);
    let outputs = forward(x.primitive(), &flex, &slopes, part_rows, true);
    let nodes: [_; N] = std::array::from_fn(|i| match i {
        0 => x.node(),
        i if i % 2 == 1 => params[(i - 1) / 2].0.node(),
        i => params[(i - 2) / 2].1.node(),
    });
    let y = outputs[outputs.len() - 1].clone();
    match <StackBackward as Backward<Flex, N>>::prepare::<NoCheckpointing>(StackBackward, nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let weights = flex.into_iter().map(|(w, _)| w).collect();
            prep.finish(Saved { x: x.into_primitive(), weights, outputs, slopes }, y)
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

/// Each layer's output, computed in parts of `part_rows` rows, every layer of a part on one
/// thread: one parallel region. `params` are (weight, bias) pairs; every width is ≥ 1. With
/// `training`, a layer of at most [`NARROW`] outputs goes row by row ([`narrow`]); when the
/// layer below is a gemm layer, the narrow one applies that layer's bias and activation to each
/// row just before reading it (not in a pass of its own). Inference keeps
/// gemm's products, so that an evaluation's actions stay what they were, bit for bit.
fn forward(
    x: &FlexTensor,
    params: &[(FlexTensor, FlexTensor)],
    slopes: &[Option<f32>],
    part_rows: usize,
    training: bool,
) -> Vec<FlexTensor> {
    let (x, xs) = values(x);
    let weights: Vec<_> = params.iter().map(|(w, _)| values(w)).collect();
    let biases: Vec<_> = params.iter().map(|(_, b)| values(b).0).collect();
    let rows = xs[0];
    let inputs: Vec<usize> = weights.iter().map(|(_, shape)| shape[0]).collect();
    let widths: Vec<usize> = weights.iter().map(|(_, shape)| shape[1]).collect();
    // Each layer reads what the one before writes; a mismatch would read rows misaligned.
    let fed: Vec<usize> = std::iter::once(xs[1]).chain(widths.iter().copied()).collect();
    assert!(inputs == fed[..inputs.len()], "the input is {rows}×{}, the layers take {inputs:?} and give {widths:?}", xs[1]);
    assert!(biases.iter().zip(&widths).all(|(b, w)| b.len() == *w), "one bias per output");
    let transposed = narrow_weights(&weights, training);
    // A gemm layer's bias and activation are left to the layer above when that one goes row by row.
    let deferred = |l: usize| transposed[l].is_none() && transposed.get(l + 1).is_some_and(Option::is_some);
    let mut ys: Vec<Vec<f32>> = widths.iter().map(|w| Vec::with_capacity(rows * w)).collect();
    let mut parts: Vec<Vec<&mut [MaybeUninit<f32>]>> = (0..rows.div_ceil(part_rows)).map(|_| Vec::new()).collect();
    for (y, width) in ys.iter_mut().zip(&widths) {
        for (part, chunk) in parts.iter_mut().zip(y.spare_capacity_mut()[..rows * width].chunks_mut(part_rows * width)) {
            part.push(chunk);
        }
    }
    // Slope 1 is the identity: one branch-free loop (a vector blend) serves both kinds of layer.
    let slope = |l: usize| slopes[l].unwrap_or(1.0);
    parts.into_par_iter().enumerate().for_each(|(p, outputs)| {
        let part = outputs[0].len() / widths[0];
        let x = &x[p * part_rows * inputs[0]..][..part * inputs[0]];
        // The layer below's output (none below the first layer).
        let mut below: Option<&mut [f32]> = None;
        for (l, y) in outputs.into_iter().enumerate() {
            let (k, n) = (inputs[l], widths[l]);
            let y = if let Some(weights_t) = &transposed[l] {
                for (i, y) in y.chunks_exact_mut(n).enumerate() {
                    let row: &[f32] = match below.as_deref_mut() {
                        Some(below) if deferred(l - 1) => {
                            let row = &mut below[i * k..][..k];
                            bias_and_activation(row, &biases[l - 1], slope(l - 1));
                            row
                        }
                        Some(below) => &below[i * k..][..k],
                        None => &x[i * k..][..k],
                    };
                    let mut z = [0.0f32; NARROW];
                    narrow::dots(row, weights_t, &mut z[..n]);
                    bias_and_activation(&mut z[..n], &biases[l], slope(l));
                    for (y, z) in y.iter_mut().zip(z) {
                        y.write(z);
                    }
                }
                // SAFETY: every row of y was just written.
                unsafe { assume_init(y) }
            } else {
                let input = below.as_deref().unwrap_or(x);
                // y = input · w: all row-major (column stride 1, row stride the width).
                let y = product_into(y, part, n, k, (input, 1, k as isize), (&weights[l].0, 1, n as isize));
                if !deferred(l) {
                    for row in y.chunks_exact_mut(n) {
                        bias_and_activation(row, &biases[l], slope(l));
                    }
                }
                y
            };
            below = Some(y);
        }
    });
    ys.into_iter()
        .zip(&widths)
        .map(|(mut y, width)| {
            // SAFETY: the parts cover all rows × width values, and `product_into` or the row loop wrote each.
            unsafe { y.set_len(rows * width) };
            tensor(y, &[rows, *width])
        })
        .collect()
}

/// The weights of each layer of at most [`NARROW`] outputs, transposed for the row kernels, when
/// `training`; `None` for the other layers (and every layer otherwise).
fn narrow_weights(weights: &[(std::borrow::Cow<'_, [f32]>, Vec<usize>)], training: bool) -> Vec<Option<Vec<f32>>> {
    weights.iter().map(|(w, shape)| (training && shape[1] <= NARROW).then(|| narrow::transpose(w, shape[0], shape[1]))).collect()
}

/// Gradients of the input (if asked) and of each layer's weight and bias from the output's
/// gradient `dy`. Per part of the rows, on one thread, from the top layer down: the layer's
/// `dz = dy ⊙ activation'(z)` and bias gradient (Σ_rows dz), its weight gradient (xᵀ·dz), and
/// `dz · wᵀ`, the layer below's `dy`, whose `dz` is then made in place while it is in cache.
fn backward(saved: &Saved, dy: &FlexTensor, input_gradient: bool) -> (Option<FlexTensor>, Vec<(FlexTensor, FlexTensor)>) {
    let ((x, xs), (dy, _)) = (values(&saved.x), values(dy));
    let weights: Vec<_> = saved.weights.iter().map(values).collect();
    let transposed = narrow_weights(&weights, true);
    let outputs: Vec<_> = saved.outputs.iter().map(|y| values(y).0).collect();
    let slopes: Vec<f32> = saved.slopes.iter().map(|s| s.unwrap_or(1.0)).collect();
    let rows = xs[0];
    let inputs: Vec<usize> = weights.iter().map(|(_, shape)| shape[0]).collect();
    let widths: Vec<usize> = weights.iter().map(|(_, shape)| shape[1]).collect();
    let (top, last) = (widths.len() - 1, widths[widths.len() - 1]);
    assert!(dy.len() == rows * last && outputs[top].len() == rows * last, "output and its gradient are {rows}×{last}");
    let part_rows = training_part_rows(rows);
    let mut dx = Vec::with_capacity(if input_gradient { rows * inputs[0] } else { 0 });
    let mut dx_parts: Vec<Option<&mut [MaybeUninit<f32>]>> = Vec::new();
    if input_gradient {
        dx_parts.extend(dx.spare_capacity_mut()[..rows * inputs[0]].chunks_mut(part_rows * inputs[0]).map(Some));
    }
    // One input-gradient part per part of the rows: they drive the parallel loop.
    debug_assert!(dx_parts.is_empty() || dx_parts.len() == rows.div_ceil(part_rows));
    dx_parts.resize_with(rows.div_ceil(part_rows), || None);
    // Per part: each layer's (bias, weight) gradient partial sums, top layer first.
    let partials: Vec<Vec<(Vec<f32>, Vec<f32>)>> = dx_parts
        .into_par_iter()
        .enumerate()
        .map(|(p, mut dx)| {
            let (start, end) = (p * part_rows, (p * part_rows + part_rows).min(rows));
            let part = end - start;
            let rows_of = |values, width| row_range(values, start..end, width);
            let mut dz = rows_of(&dy, last).to_vec();
            let mut db = vec![0.0f32; last];
            for (dz, y) in dz.chunks_exact_mut(last).zip(rows_of(&outputs[top], last).chunks_exact(last)) {
                activation_gradient(dz, y, &mut db, slopes[top]);
            }
            let mut layers = Vec::with_capacity(widths.len());
            for l in (0..widths.len()).rev() {
                let (k, n) = (inputs[l], widths[l]);
                let input = if l == 0 { rows_of(&x, k) } else { rows_of(&outputs[l - 1], k) };
                if let Some(weights_t) = &transposed[l] {
                    // One pass over the rows: the weight gradient (transposed), and the input's
                    // gradient with the layer below's activation derivative and bias gradient.
                    let mut dw_t = vec![0.0f32; n * k];
                    let rows = input.chunks_exact(k).zip(dz.chunks_exact(n));
                    if l == 0 {
                        for (i, (x, dz)) in rows.enumerate() {
                            narrow::backward_row(x, dz, weights_t, &mut dw_t, dx.as_deref_mut().map(|dx| &mut dx[i * k..][..k]), None);
                        }
                        layers.push((db, narrow::transpose(&dw_t, n, k)));
                        break;
                    }
                    let (mut below, mut db_below) = (Vec::with_capacity(part * k), vec![0.0f32; k]);
                    for ((x, dz), dx) in rows.zip(below.spare_capacity_mut()[..part * k].chunks_exact_mut(k)) {
                        narrow::backward_row(x, dz, weights_t, &mut dw_t, Some(dx), Some((slopes[l - 1], &mut db_below)));
                    }
                    // SAFETY: backward_row wrote every row of `below`.
                    unsafe { below.set_len(part * k) };
                    layers.push((std::mem::replace(&mut db, db_below), narrow::transpose(&dw_t, n, k)));
                    dz = below;
                    continue;
                }
                // The layer's input transposed: read from its storage with the strides swapped.
                let dw = product(k, n, part, (input, k as isize, 1), (&dz, 1, n as isize));
                if l == 0 {
                    if let Some(dx) = dx {
                        product_into(dx, part, k, n, (&dz, 1, n as isize), (&weights[l].0, n as isize, 1));
                    }
                    layers.push((db, dw));
                    break;
                }
                let mut below = product(part, k, n, (&dz, 1, n as isize), (&weights[l].0, n as isize, 1));
                layers.push((std::mem::replace(&mut db, vec![0.0f32; k]), dw));
                for (dz, y) in below.chunks_exact_mut(k).zip(input.chunks_exact(k)) {
                    activation_gradient(dz, y, &mut db, slopes[l - 1]);
                }
                dz = below;
            }
            layers
        })
        .collect();
    // SAFETY: the parts cover all rows and wrote every value of dx when it is asked.
    if input_gradient {
        unsafe { dx.set_len(rows * inputs[0]) };
    }
    // Partial sums added in part order, element by element; a large weight gradient in chunks on
    // both threads (on one, the sums were ~2.5 % of the paper profile's step).
    let params = (0..widths.len())
        .map(|l| {
            let (mut db, mut dw) = (vec![0.0f32; widths[l]], vec![0.0f32; inputs[l] * widths[l]]);
            let parts: Vec<&(Vec<f32>, Vec<f32>)> = partials.iter().map(|part| &part[top - l]).collect();
            for (pdb, _) in &parts {
                add(&mut db, pdb);
            }
            let add_chunk = |(c, chunk): (usize, &mut [f32])| {
                for (_, pdw) in &parts {
                    add(chunk, &pdw[c * SUM_CHUNK..]);
                }
            };
            if dw.len() > 2 * SUM_CHUNK {
                dw.par_chunks_mut(SUM_CHUNK).enumerate().for_each(add_chunk);
            } else {
                dw.chunks_mut(SUM_CHUNK).enumerate().for_each(add_chunk);
            }
            (tensor(dw, &[inputs[l], widths[l]]), tensor(db, &[widths[l]]))
        })
        .collect();
    let dx = input_gradient.then(|| tensor(dx, &[rows, inputs[0]]));
    (dx, params)
}

/// Rows `range` of a row-major matrix `width` values wide.
fn row_range(values: &[f32], range: std::ops::Range<usize>, width: usize) -> &[f32] {
    &values[range.start * width..range.end * width]
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

    /// A stack gives its layers' values and every gradient bit for bit as the layers one node
    /// each: the same products over the same parts, the same sums in the same order. Three
    /// layers (one node) and six (two nodes), passes of three parts, two, and one; the input
    /// tracked and not.
    #[test]
    fn a_stack_is_its_layers_one_by_one_bit_for_bit() {
        for (widths, rows, track_input) in
            [(&[7, 33, 29, 5][..], 2 * PART_ROWS + 203, true), (&[7, 33, 29, 5], 701, false), (&[4, 9, 8, 7, 6, 5, 3], 40, true)]
        {
            let device = Device::flex().autodiff();
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let x = Tensor::<2>::from_data(TensorData::new(random(rows, widths[0], &mut rng), [rows, widths[0]]), &device);
            let x = if track_input { x.require_grad() } else { x };
            let last = widths.len() - 2;
            let layers: Vec<Dense> = widths
                .windows(2)
                .enumerate()
                .map(|(i, w)| Dense {
                    weight: Tensor::from_data(TensorData::new(random(w[0], w[1], &mut rng), [w[0], w[1]]), &device).require_grad(),
                    bias: Tensor::from_data(TensorData::new(random(1, w[1], &mut rng), [w[1]]), &device).require_grad(),
                    leaky_slope: (i != last).then_some(0.01),
                })
                .collect();
            let scale = Tensor::<2>::from_data(
                TensorData::new(random(rows, widths[widths.len() - 1], &mut rng), [rows, widths[widths.len() - 1]]),
                &device,
            );
            let run = |y: Tensor<2>| {
                let grads = (y.clone() * scale.clone()).sum().backward();
                let mut all = vec![values_of(y)];
                all.extend(x.grad(&grads).map(values_of));
                for l in &layers {
                    all.push(values_of(l.weight.grad(&grads).unwrap()));
                    all.push(values_of(l.bias.grad(&grads).unwrap()));
                }
                all
            };
            let stacked = run(dense_stack(x.clone(), &layers));
            let one_by_one = run(layers.iter().fold(x.clone(), |x, l| dense(x, l.weight.clone(), l.bias.clone(), l.leaky_slope)));
            assert_eq!(stacked.len(), 1 + usize::from(track_input) + 2 * layers.len());
            assert!(stacked == one_by_one, "{widths:?}, {rows} rows: the stack differs from its layers one by one");
            // Without autodiff, the inference path.
            let inference = |t: Tensor<2>| Tensor::<2>::from_data(t.into_data(), &Device::flex());
            let plain: Vec<Dense> = layers
                .iter()
                .map(|l| Dense {
                    weight: inference(l.weight.clone()),
                    bias: Tensor::from_data(l.bias.clone().into_data(), &Device::flex()),
                    leaky_slope: l.leaky_slope,
                })
                .collect();
            let x = inference(x.clone());
            let stacked = values_of(dense_stack(x.clone(), &plain));
            let one_by_one = values_of(plain.iter().fold(x, |x, l| dense(x, l.weight.clone(), l.bias.clone(), l.leaky_slope)));
            assert!(stacked == one_by_one, "{widths:?}, {rows} rows: inference differs");
        }
    }

    /// A layer that does not take what the one before gives is refused, not read misaligned.
    #[test]
    #[should_panic(expected = "the layers take")]
    fn a_stack_whose_widths_do_not_chain_is_refused() {
        let device = Device::flex();
        let layer = |inputs: usize, outputs: usize| Dense {
            weight: Tensor::zeros([inputs, outputs], &device),
            bias: Tensor::zeros([outputs], &device),
            leaky_slope: None,
        };
        dense_stack(Tensor::zeros([3, 4], &device), &[layer(4, 6), layer(5, 2)]);
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
