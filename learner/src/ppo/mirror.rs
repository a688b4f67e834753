//! A mirror-symmetry term in the PPO loss: the divergence between the policy's actions on the
//! mirrored observations and the mirror of its actions on the originals
//! (`sim::mirror`: the reflected scene is flown by the reflected action). It asks the policy to
//! take a left turn it has learned the way it takes the right turn it mirrors, so what it
//! learns on one side of a track serves the other (Yu, Turk & Liu 2018, "Learning symmetric
//! and low-energy locomotion", use the same loss for gaits).
//!
//! The policy reads normalised observations; the term mirrors them without leaving the device:
//! `x' = norm(S · denorm(x))` is, per number, `x[source] · scale + offset` with constants made
//! from the running statistics. It ignores the normaliser's ±clip, which only numbers more
//! than 10 standard deviations out reach.

use burn::tensor::{Device, Int, Tensor, TensorData};
use policy::ObsNormalizer;
use sim::{ACTION_MIRROR_SIGNS, ObservationMirror};

/// The term for one update: the mirror in normalised units on the device, and its weight.
#[derive(Debug)]
pub struct MirrorTerm {
    source: Tensor<1, Int>,
    scale: Tensor<2>,
    offset: Tensor<2>,
    action_signs: Tensor<2>,
    /// Weight of the divergence in the loss.
    pub weight: f64,
    /// Share of each minibatch's rows the divergence is taken on (its first rows, which the
    /// shuffle makes a uniform sample): an unbiased estimate of the whole minibatch's at a
    /// fraction of the extra actor pass's cost.
    pub fraction: f64,
}

impl MirrorTerm {
    /// The term for observations normalised by `normalizer`, mirrored by `mirror`.
    pub fn new(mirror: &ObservationMirror, normalizer: &ObsNormalizer, weight: f64, device: &Device) -> Self {
        let dim = mirror.source.len();
        let std = |d: usize| (normalizer.var[d] + normalizer.epsilon).sqrt();
        let (mut scale, mut offset) = (Vec::with_capacity(dim), Vec::with_capacity(dim));
        for (i, (&s, &sign)) in mirror.source.iter().zip(&mirror.sign).enumerate() {
            let sign = f64::from(sign);
            scale.push((sign * std(s) / std(i)) as f32);
            offset.push(((sign * normalizer.mean[s] - normalizer.mean[i]) / std(i)) as f32);
        }
        let source: Vec<i64> = mirror.source.iter().map(|&s| s as i64).collect();
        Self {
            source: Tensor::from_data(TensorData::new(source, [dim]), device),
            scale: Tensor::from_data(TensorData::new(scale, [1, dim]), device),
            offset: Tensor::from_data(TensorData::new(offset, [1, dim]), device),
            action_signs: Tensor::from_data(TensorData::new(ACTION_MIRROR_SIGNS.to_vec(), [1, ACTION_MIRROR_SIGNS.len()]), device),
            weight,
            fraction: 1.0,
        }
    }

    /// The term taken on `fraction` ∈ (0, 1] of each minibatch's rows.
    pub fn on_fraction(self, fraction: f64) -> Self {
        Self { fraction, ..self }
    }

    /// How many of a minibatch's `rows` the divergence is taken on: at least one.
    pub fn sampled_rows(&self, rows: usize) -> usize {
        ((rows as f64 * self.fraction).ceil() as usize).clamp(1, rows.max(1))
    }

    /// The mirrors of normalised observations `[b, dim]`, normalised.
    pub fn mirrored(&self, observations: Tensor<2>) -> Tensor<2> {
        observations.select(1, self.source.clone()) * self.scale.clone() + self.offset.clone()
    }

    /// The KL divergence between the policy's action distribution at the mirrored observations
    /// and the mirror of its distribution at the originals, averaged over the minibatch: with
    /// one state-independent standard deviation σ (its own mirror), `Σ_i Δ_i² / (2σ_i²)` for
    /// the difference Δ of the means. Measured in σ, a mismatch weighs as much as PPO's own
    /// step does, however narrow the policy has become; σ is held fixed here, so the term
    /// moves the means only.
    pub fn divergence(&self, means: Tensor<2>, mirrored_means: Tensor<2>, log_std: Tensor<1>) -> Tensor<1> {
        let twice_variance = log_std.detach().mul_scalar(2.0).exp().mul_scalar(2.0).unsqueeze::<2>();
        ((mirrored_means - means * self.action_signs.clone()).powf_scalar(2.0) / twice_variance).sum_dim(1).mean()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim::{ObservationFrame, ObservationLayout};

    /// Normalised, mirrored on the device = mirrored raw on the CPU, then normalised.
    #[test]
    fn mirroring_normalised_rows_equals_normalising_mirrored_rows() {
        let device = Device::flex();
        let layout = ObservationLayout { line_points: 2, ..ObservationLayout::spec(ObservationFrame::Heading) };
        let mirror = layout.mirror().unwrap();
        let dim = layout.dim();
        let raw: Vec<f32> = (0..3 * dim).map(|i| ((i * 29) % 17) as f32 * 0.4 - 3.0).collect();
        let mut normalizer = ObsNormalizer::new(dim);
        normalizer.update(&raw);
        let mut normalized = vec![0f32; raw.len()];
        normalizer.normalize(&raw, &mut normalized);
        let term = MirrorTerm::new(&mirror, &normalizer, 1.0, &device);
        let on_device = term.mirrored(Tensor::from_data(TensorData::new(normalized, [3, dim]), &device));
        let on_device = on_device.into_data().try_into_vec::<f32>().unwrap();
        let mut expected = vec![0f32; raw.len()];
        for (row, out) in raw.chunks(dim).zip(expected.chunks_mut(dim)) {
            let mut m = vec![0f32; dim];
            mirror.apply(row, &mut m);
            normalizer.normalize(&m, out);
        }
        for (i, (a, b)) in on_device.iter().zip(&expected).enumerate() {
            assert!((a - b).abs() < 1e-4, "number {i}: {a} vs {b}");
        }
    }

    /// A fraction of a minibatch rounds up to whole rows, never none and never more than it has.
    #[test]
    fn the_sampled_rows_are_the_fraction_rounded_up() {
        let device = Device::flex();
        let term =
            MirrorTerm::new(&ObservationLayout::spec(ObservationFrame::Heading).mirror().unwrap(), &ObsNormalizer::new(40), 1.0, &device);
        assert_eq!(term.sampled_rows(4000), 4000);
        let quarter = term.on_fraction(0.25);
        assert_eq!((quarter.sampled_rows(4000), quarter.sampled_rows(4001), quarter.sampled_rows(3)), (1000, 1001, 1));
        assert_eq!(quarter.on_fraction(1e-6).sampled_rows(10), 1);
    }

    /// A policy that commutes with the mirror has no divergence; one that does not, has, in units
    /// of its standard deviation.
    #[test]
    fn the_divergence_is_zero_exactly_for_mirrored_means() {
        let device = Device::flex();
        let term =
            MirrorTerm::new(&ObservationLayout::spec(ObservationFrame::Heading).mirror().unwrap(), &ObsNormalizer::new(40), 1.0, &device);
        let means = Tensor::<2>::from_data(TensorData::new(vec![0.2f32, 0.5, -0.3, 0.7], [1, 4]), &device);
        let symmetric = Tensor::<2>::from_data(TensorData::new(vec![0.2f32, -0.5, -0.3, -0.7], [1, 4]), &device);
        let log_std = |x: f32| Tensor::<1>::from_data(TensorData::new(vec![x; 4], [4]), &device);
        let scalar = |t: Tensor<1>| t.into_data().try_into_vec::<f32>().unwrap()[0];
        assert!(scalar(term.divergence(means.clone(), symmetric, log_std(0.0))) < 1e-12);
        // Δ = 1.0 and 1.4 on the two mirrored rates: (1 + 1.96) / 2 at σ = 1, four times that at σ = 1/2.
        assert!((scalar(term.divergence(means.clone(), means.clone(), log_std(0.0))) - 1.48).abs() < 1e-5);
        assert!((scalar(term.divergence(means.clone(), means, log_std(-std::f32::consts::LN_2))) - 4.0 * 1.48).abs() < 1e-4);
    }
}
