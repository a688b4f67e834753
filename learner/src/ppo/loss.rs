//! The PPO loss terms as tensor functions (SB3 semantics).

use burn::tensor::Tensor;
use policy::HALF_LN_2PI;

/// Log-density `[batch]` of `actions` `[batch, dim]` under N(mean, exp(log_std)²).
pub fn log_prob(actions: Tensor<2>, mean: Tensor<2>, log_std: Tensor<1>) -> Tensor<1> {
    let log_std = log_std.unsqueeze_dim::<2>(0); // [1, dim]
    let z = (actions - mean) / log_std.clone().exp(); // [batch, dim]
    (z.powf_scalar(2.0).mul_scalar(-0.5) - log_std).sub_scalar(HALF_LN_2PI).sum_dim(1).squeeze_dim(1)
}

/// The clipped surrogate, negated for minimisation: −mean(min(A r, A clip(r, 1−ε, 1+ε))).
pub fn clipped_surrogate(ratio: Tensor<1>, advantages: Tensor<1>, clip_range: f64) -> Tensor<1> {
    let unclipped = advantages.clone() * ratio.clone();
    let clipped = advantages * ratio.clamp(1.0 - clip_range, 1.0 + clip_range);
    unclipped.min_pair(clipped).mean().neg()
}

/// Entropy of the policy's Gaussian, `Σ_i (ln σ_i + ½ ln 2πe)`: the same for every state, since
/// the standard deviation is state-independent.
pub fn gaussian_entropy(log_std: Tensor<1>) -> Tensor<1> {
    log_std.add_scalar(HALF_LN_2PI + 0.5).sum()
}

/// Mean squared error between predicted values and returns (no value clipping).
pub fn value_loss(values: Tensor<1>, returns: Tensor<1>) -> Tensor<1> {
    (returns - values).powf_scalar(2.0).mean()
}

/// Per-minibatch advantage normalisation: (A − mean) / (unbiased std + 1e-8); a single sample
/// is left as is (SB3).
pub fn normalize_advantages(advantages: &mut [f32]) {
    let n = advantages.len();
    if n < 2 {
        return;
    }
    let mean = advantages.iter().map(|&a| f64::from(a)).sum::<f64>() / n as f64;
    let var = advantages.iter().map(|&a| (f64::from(a) - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let scale = var.sqrt() + 1e-8;
    for a in advantages {
        *a = ((f64::from(*a) - mean) / scale) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn t1(v: &[f32]) -> Tensor<1> {
        Tensor::from_data(TensorData::new(v.to_vec(), [v.len()]), &Device::flex())
    }

    fn scalar(t: Tensor<1>) -> f32 {
        t.into_data().try_into_vec::<f32>().unwrap()[0]
    }

    #[test]
    fn clipped_surrogate_matches_hand_computed_values() {
        // ratio 1.5 with A > 0 is clipped to 1.2; ratio 0.5 with A < 0 is clipped to 0.8;
        // ratio 0.9 with A > 0 and 1.1 with A < 0 stay inside the range.
        let ratio = [1.5, 0.5, 0.9, 1.1];
        let adv = [2.0, -1.0, 1.0, -3.0];
        // min(A r, A clip(r)) per sample: min(3.0, 2.4), min(-0.5, -0.8), 0.9, -3.3.
        let expected = -(2.4 + -0.8 + 0.9 + -3.3) / 4.0;
        let got = scalar(clipped_surrogate(t1(&ratio), t1(&adv), 0.2));
        assert!((got - expected).abs() < 1e-6, "{got} vs {expected}");
    }

    #[test]
    fn the_entropy_is_that_of_a_diagonal_gaussian() {
        // σ = 1 and σ = e^-1: ½ ln 2πe each, minus 1 for the narrower.
        let expected = (2.0 * std::f64::consts::PI * std::f64::consts::E).ln() - 1.0;
        assert!((f64::from(scalar(gaussian_entropy(t1(&[0.0, -1.0])))) - expected).abs() < 1e-6);
    }

    #[test]
    fn value_loss_is_the_mean_squared_error() {
        let got = scalar(value_loss(t1(&[1.0, 2.0, 4.0]), t1(&[1.5, 0.0, 4.0])));
        assert!((got - (0.25 + 4.0 + 0.0) / 3.0).abs() < 1e-6);
    }

    #[test]
    fn log_prob_matches_the_closed_form() {
        let device = Device::flex();
        let actions = Tensor::<2>::from_data(TensorData::new(vec![0.3f32, -1.0], [1, 2]), &device);
        let mean = Tensor::<2>::from_data(TensorData::new(vec![0.1f32, 0.0], [1, 2]), &device);
        let got = scalar(log_prob(actions, mean, t1(&[-0.5, 0.2])));
        let expected = policy::gaussian_log_prob(&[0.3, -1.0], &[0.1, 0.0], &[-0.5, 0.2]);
        assert!((got - expected).abs() < 1e-5, "{got} vs {expected}");
    }

    #[test]
    fn advantages_are_normalised_with_the_unbiased_std() {
        let mut a = [1.0f32, 2.0, 3.0, 4.0];
        normalize_advantages(&mut a);
        // mean 2.5, unbiased std √(5/3).
        let s = (5.0f64 / 3.0).sqrt() as f32;
        assert!((a[0] + 1.5 / s).abs() < 1e-5 && (a[3] - 1.5 / s).abs() < 1e-5);
        let mut one = [7.0f32];
        normalize_advantages(&mut one);
        assert_eq!(one, [7.0]);
    }
}
