//! The actor-critic (SPEC §10): separate actor and critic MLPs with LeakyReLU, a
//! state-independent log standard deviation, orthogonal initialisation.

use burn::module::{Module, Param, ParamId};
use burn::nn::Linear;
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use sim::nalgebra::DMatrix;

use kernels::dense::{Dense, dense_stack};
use policyfile::shapes::{ExportedParam, ShapeMismatch, check_shapes, parameter_shapes};
use policyfile::{Agent, Architecture};

/// A multilayer perceptron: LeakyReLU between layers, none after the last.
#[derive(Module, Debug)]
pub struct Mlp {
    layers: Vec<Linear>,
    negative_slope: f64,
}

/// A `rows × cols` matrix with orthonormal rows or columns times `gain` (as torch's
/// `orthogonal_`): QR of a Gaussian matrix, signs fixed by R's diagonal. Drawn from our own
/// seeded stream: burn's random tensors share one process-wide generator.
pub(crate) fn orthogonal(rows: usize, cols: usize, gain: f64, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let (tall, short) = (rows.max(cols), rows.min(cols));
    let gaussian = DMatrix::<f64>::from_fn(tall, short, |_, _| rng.sample(StandardNormal));
    let qr = gaussian.qr();
    let (mut q, r) = (qr.q(), qr.r());
    for j in 0..short {
        if r[(j, j)] < 0.0 {
            q.column_mut(j).neg_mut();
        }
    }
    let q = if rows >= cols { q } else { q.transpose() };
    // Row-major rows × cols.
    (0..rows).flat_map(|i| (0..cols).map(move |j| (i, j))).map(|(i, j)| (gain * q[(i, j)]) as f32).collect()
}

pub(crate) fn parameter<const D: usize>(values: Vec<f32>, shape: [usize; D], device: &Device) -> Param<Tensor<D>> {
    Param::from_tensor(Tensor::from_data(TensorData::new(values, shape), device))
}

impl Mlp {
    /// Orthogonal weights (gain √2 for hidden layers, `head_gain` for the last), zero biases.
    pub(crate) fn new(dims: &[usize], head_gain: f64, negative_slope: f64, rng: &mut ChaCha8Rng, device: &Device) -> Self {
        let count = dims.len() - 1;
        let layers = dims
            .windows(2)
            .enumerate()
            .map(|(i, w)| {
                let gain = if i + 1 == count { head_gain } else { std::f64::consts::SQRT_2 };
                Linear {
                    weight: parameter(orthogonal(w[0], w[1], gain, rng), [w[0], w[1]], device),
                    bias: Some(parameter(vec![0.0; w[1]], [w[1]], device)),
                }
            })
            .collect();
        Self { layers, negative_slope }
    }

    /// Each layer's weight (rank 2) and bias (rank 1) id, in order.
    pub fn param_ids(&self) -> Vec<(ParamId, usize)> {
        self.layers.iter().flat_map(|l| [(l.weight.id, 2)].into_iter().chain(l.bias.as_ref().map(|b| (b.id, 1)))).collect()
    }

    /// Each layer's weight and bias, in order.
    pub(crate) fn export(&self) -> Vec<ExportedParam> {
        let mut out = Vec::new();
        for layer in &self.layers {
            out.push(exported(&layer.weight));
            out.extend(layer.bias.as_ref().map(exported));
        }
        out
    }

    /// Rebuilds an MLP from (weight, bias) pairs, keeping parameter ids.
    pub(crate) fn import(pairs: &[ExportedParam], negative_slope: f64, device: &Device) -> Self {
        let layers = pairs.chunks(2).map(|wb| Linear { weight: loaded(&wb[0], device), bias: Some(loaded(&wb[1], device)) }).collect();
        Self { layers, negative_slope }
    }

    /// Width of the input the first layer reads.
    pub fn input_dim(&self) -> usize {
        self.layers.first().map_or(0, |l| l.weight.dims()[0])
    }

    /// `[batch, in] → [batch, out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        let layers: Vec<Dense> = self
            .layers
            .iter()
            .enumerate()
            .map(|(i, layer)| Dense {
                weight: layer.weight.val(),
                bias: layer_bias(layer),
                leaky_slope: (i != last).then_some(self.negative_slope),
            })
            .collect();
        dense_stack(x, &layers)
    }
}

/// One parameter's id, shape and values.
#[allow(clippy::expect_used, reason = "float parameters")]
pub(crate) fn exported<const D: usize>(p: &Param<Tensor<D>>) -> ExportedParam {
    let data = p.val().into_data();
    ExportedParam { id: p.id.val(), shape: data.shape().to_vec(), values: data.try_into_vec::<f32>().expect("float parameters") }
}

/// A trainable parameter from an exported one, keeping its id (shapes checked by the caller).
pub(crate) fn loaded<const D: usize>(p: &ExportedParam, device: &Device) -> Param<Tensor<D>> {
    let shape: [usize; D] = std::array::from_fn(|i| p.shape[i]);
    let t = Tensor::from_data(TensorData::new(p.values.clone(), shape), device);
    Param::initialized(ParamId::from(p.id), t).set_require_grad(true)
}

/// A layer's bias (every layer here is built with one).
#[allow(clippy::expect_used, reason = "layers have biases")]
fn layer_bias(layer: &Linear) -> Tensor<1> {
    layer.bias.as_ref().expect("layers have biases").val()
}

/// Actor and critic networks plus the log standard deviation of the Gaussian policy.
#[derive(Module, Debug)]
pub struct ActorCritic {
    /// Observation → action mean.
    pub actor: Mlp,
    /// Observation → state value.
    pub critic: Mlp,
    /// Log standard deviation per action dimension (state-independent).
    pub log_std: Param<Tensor<1>>,
}

impl ActorCritic {
    /// A freshly initialised network (gains: √2 hidden, 0.01 policy head, 1 value head); the
    /// same seed gives the same weights.
    pub fn new(arch: &Architecture, initial_log_std: f64, seed: u64, device: &Device) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (actor, critic) = arch.mlp_dims();
        Self {
            actor: Mlp::new(&actor, 0.01, arch.negative_slope, &mut rng, device),
            critic: Mlp::new(&critic, 1.0, arch.negative_slope, &mut rng, device),
            log_std: parameter(vec![initial_log_std as f32; arch.action_dim], [arch.action_dim], device),
        }
    }

    /// Action means `[batch, action_dim]` and values `[batch]` of normalised observations.
    pub fn forward(&self, observations: Tensor<2>) -> (Tensor<2>, Tensor<1>) {
        let mean = self.action_means(observations.clone());
        let value = self.critic.forward(observations).squeeze_dim(1);
        (mean, value)
    }

    /// Action means `[batch, action_dim]` of normalised observations.
    pub fn action_means(&self, observations: Tensor<2>) -> Tensor<2> {
        self.actor.forward(observations)
    }

    /// Every parameter's id and rank, in [`ActorCritic::export`] order, without copying values.
    pub fn param_ids(&self) -> Vec<(ParamId, usize)> {
        let mut ids = self.actor.param_ids();
        ids.extend(self.critic.param_ids());
        ids.push((self.log_std.id, 1));
        ids
    }

    /// Every parameter's values, in a fixed order: actor layers (weight, bias), critic layers,
    /// log std.
    pub fn export(&self) -> Vec<ExportedParam> {
        let mut params = self.actor.export();
        params.extend(self.critic.export());
        params.push(exported(&self.log_std));
        params
    }

    /// Rebuilds a network of `arch` from [`ActorCritic::export`]'s output, keeping parameter ids.
    pub fn import(arch: &Architecture, params: &[ExportedParam], device: &Device) -> Result<Self, ShapeMismatch> {
        check_shapes(&parameter_shapes(&Architecture { agent: Agent::State, ..arch.clone() }), params)?;
        let (actor, rest) = params.split_at(2 * (arch.hidden.len() + 1));
        let (critic, log_std) = rest.split_at(actor.len());
        Ok(Self {
            actor: Mlp::import(actor, arch.negative_slope, device),
            critic: Mlp::import(critic, arch.negative_slope, device),
            log_std: loaded(&log_std[0], device),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orthogonal_init_has_orthonormal_columns_scaled_by_the_gain() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (rows, cols) = (40, 16);
        let w = orthogonal(rows, cols, 2.0, &mut rng);
        let m = DMatrix::from_row_slice(rows, cols, &w.iter().map(|&x| f64::from(x)).collect::<Vec<_>>());
        let gram = m.transpose() * &m / 4.0;
        assert!((gram - DMatrix::identity(cols, cols)).amax() < 1e-5);
        // Wide matrices get orthonormal rows instead.
        let w = orthogonal(4, 9, 1.0, &mut rng);
        let m = DMatrix::from_row_slice(4, 9, &w.iter().map(|&x| f64::from(x)).collect::<Vec<_>>());
        assert!((&m * m.transpose() - DMatrix::identity(4, 4)).amax() < 1e-5);
    }

    #[test]
    fn shapes_follow_the_export_order() {
        let arch = Architecture { hidden: vec![8, 6], ..Architecture::paper() };
        let exported: Vec<Vec<usize>> = ActorCritic::new(&arch, -0.5, 2, &Device::flex()).export().into_iter().map(|p| p.shape).collect();
        assert_eq!(parameter_shapes(&arch), exported);
    }

    #[test]
    fn same_seed_same_network() {
        let arch = Architecture { hidden: vec![8], ..Architecture::paper() };
        let a = ActorCritic::new(&arch, -0.5, 9, &Device::flex()).export();
        assert_eq!(
            a,
            ActorCritic::new(&arch, -0.5, 9, &Device::flex())
                .export()
                .into_iter()
                .zip(&a)
                .map(|(mut p, q)| {
                    p.id = q.id;
                    p
                })
                .collect::<Vec<_>>()
        );
        assert_ne!(a[0].values, ActorCritic::new(&arch, -0.5, 10, &Device::flex()).export()[0].values);
    }
}
