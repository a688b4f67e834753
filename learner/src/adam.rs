//! Adam in one pass over each parameter: the arithmetic of burn's `Adam`, operation for
//! operation in the same order, so a step gives the same bits, without burn's one pass (and
//! one allocation) per tensor operation — about fifteen of them a parameter. Its state is
//! burn's `AdamState`, so checkpoints written with either optimiser load into the other.

use burn::optim::{AdamState, AdaptiveMomentumState, LearningRate, ModuleOptimizer, Optimizer};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

/// Elements per parallel piece of one parameter's step: below two of them the step stays on
/// one thread (handing off costs more than it saves on a small tensor).
const PIECE: usize = 32 * 1024;

/// Adam with L2 weight decay added to the gradient (torch's `Adam(weight_decay=…)`, burn's
/// `AdamConfig::with_weight_decay`), fused.
#[derive(Clone, Debug)]
pub struct FusedAdam {
    beta_1: f32,
    beta_2: f32,
    epsilon: f32,
    weight_decay: Option<f32>,
}

impl FusedAdam {
    /// burn's default betas (0.9, 0.999), `epsilon`, and L2 weight decay `weight_decay` if any.
    pub fn new(epsilon: f32, weight_decay: Option<f32>) -> Self {
        Self { beta_1: 0.9, beta_2: 0.999, epsilon, weight_decay }
    }

    /// As a module optimiser (what [`crate::Learner`] steps its networks with).
    pub fn init(self) -> ModuleOptimizer {
        ModuleOptimizer::from(self)
    }
}

/// One parameter's step coefficients, computed as burn's `AdaptiveMomentum` computes them.
#[derive(Clone, Copy)]
struct Coefficients {
    beta_1: f32,
    beta_2: f32,
    /// 1 − β₁ and 1 − β₂.
    rest_1: f32,
    rest_2: f32,
    /// √(1 − β₂ᵗ) / (1 − β₁ᵗ).
    combined: f32,
    /// ε √(1 − β₂ᵗ).
    epsilon: f32,
    learning_rate: f32,
    weight_decay: Option<f32>,
    /// The first step: the moments start from the gradient alone.
    first: bool,
}

impl Coefficients {
    /// Steps every element of `p` (gradients `g`, moments `m` and `v`, the same length).
    fn step_all(&self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
        for (((p, g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
            self.step(p, *g, m, v);
        }
    }

    /// Steps one element: `p` the parameter, `g` its gradient, `m` and `v` its moments.
    #[inline(always)]
    fn step(&self, p: &mut f32, g: f32, m: &mut f32, v: &mut f32) {
        let g = match self.weight_decay {
            Some(penalty) => *p * penalty + g,
            None => g,
        };
        if self.first {
            *m = g * self.rest_1;
            *v = (g * g) * self.rest_2;
        } else {
            *m = *m * self.beta_1 + g * self.rest_1;
            *v = *v * self.beta_2 + (g * g) * self.rest_2;
        }
        let update = (*m * self.combined) / (v.sqrt() + self.epsilon);
        *p -= update * self.learning_rate;
    }
}

#[allow(clippy::expect_used, reason = "a float parameter's values")]
fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().expect("float values")
}

fn tensor<const D: usize>(values: Vec<f32>, dims: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, dims), device)
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        param: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let (device, dims) = (param.device(), param.dims());
        let mut params = values(param);
        let grads = values(grad);
        let (time, mut m, mut v) = match state {
            Some(s) => (s.momentum.time + 1, values(s.momentum.moment_1), values(s.momentum.moment_2)),
            None => (1, vec![0.0; params.len()], vec![0.0; params.len()]),
        };
        // As burn: f32 powers of the betas at the step count, the square root taken once.
        let t = time as i32;
        let bias_correction_2 = (1.0 - self.beta_2.powi(t)).sqrt();
        let c = Coefficients {
            beta_1: self.beta_1,
            beta_2: self.beta_2,
            rest_1: 1.0 - self.beta_1,
            rest_2: 1.0 - self.beta_2,
            combined: bias_correction_2 / (1.0 - self.beta_1.powi(t)),
            epsilon: self.epsilon * bias_correction_2,
            learning_rate: lr as f32,
            weight_decay: self.weight_decay,
            first: time == 1,
        };
        if params.len() >= 2 * PIECE {
            params
                .par_chunks_mut(PIECE)
                .zip(grads.par_chunks(PIECE))
                .zip(m.par_chunks_mut(PIECE))
                .zip(v.par_chunks_mut(PIECE))
                .for_each(|(((p, g), m), v)| c.step_all(p, g, m, v));
        } else {
            c.step_all(&mut params, &grads, &mut m, &mut v);
        }
        let momentum = AdaptiveMomentumState::new(time, tensor(m, dims, &device), tensor(v, dims, &device));
        (tensor(params, dims, &device), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        AdamState::new(state.momentum.to_device(device))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Module, Param};
    use burn::optim::decay::WeightDecayConfig;
    use burn::optim::{AdamConfig, GradientsParams};

    /// burn's unfused `Adam` with `fused`'s settings: what it must equal.
    fn unfused(fused: &FusedAdam) -> ModuleOptimizer {
        AdamConfig::new()
            .with_beta_1(fused.beta_1)
            .with_beta_2(fused.beta_2)
            .with_epsilon(fused.epsilon)
            .with_weight_decay(fused.weight_decay.map(WeightDecayConfig::new))
            .init()
    }

    /// A module of two parameters: one above the parallel size, one below it.
    #[derive(Module, Debug)]
    struct Two {
        big: Param<Tensor<2>>,
        small: Param<Tensor<1>>,
    }

    fn values_of(two: &Two) -> Vec<u32> {
        let (big, small) = (two.big.val().into_data(), two.small.val().into_data());
        let floats = big.try_into_vec::<f32>().unwrap().into_iter().chain(small.try_into_vec::<f32>().unwrap());
        floats.map(f32::to_bits).collect()
    }

    /// Several steps of the fused and of burn's Adam, with and without weight decay, from the
    /// same weights on the same gradients, give the same weights to the last bit.
    #[test]
    fn fused_adam_steps_as_burns_adam_bit_for_bit() {
        let device = Device::flex().autodiff();
        let init = |seed: usize, rows: usize, cols: usize| -> Vec<f32> {
            (0..rows * cols).map(|i| (((i * 7919 + seed * 104_729) % 2003) as f32 - 1001.0) * 1e-3).collect()
        };
        let (rows, cols) = (3 * PIECE / 256 + 5, 256);
        let new = || Two {
            big: Param::from_tensor(tensor(init(1, rows, cols), [rows, cols], &device)),
            small: Param::from_tensor(tensor(init(2, 1, 37), [37], &device)),
        };
        for weight_decay in [None, Some(1e-5)] {
            let fused = FusedAdam::new(1e-5, weight_decay);
            let (mut a, mut b) = (new(), new());
            let (mut fused_opt, mut burn_opt) = (fused.clone().init(), unfused(&fused));
            for step in 0..4 {
                // A loss whose gradient differs per element and per step: sum of w² · k.
                let loss = |m: &Two| {
                    let k = 1.0 + step as f32 * 0.37;
                    m.big.val().powi_scalar(2).sum().mul_scalar(k) + m.small.val().sin().sum()
                };
                let grads_a = GradientsParams::from_grads(loss(&a).backward(), &a);
                let grads_b = GradientsParams::from_grads(loss(&b).backward(), &b);
                a = fused_opt.step(3e-4, a, grads_a);
                b = burn_opt.step(3e-4, b, grads_b);
                assert_eq!(values_of(&a), values_of(&b), "step {step}, weight decay {weight_decay:?}");
            }
            assert_ne!(values_of(&a), values_of(&new()), "the steps moved the weights");
        }
    }
}
