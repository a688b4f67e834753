//! Running observation normaliser (Stable-Baselines3 `VecNormalize` semantics): the learner
//! updates it from raw rollout observations; actors and evaluation only apply it.

use serde::{Deserialize, Serialize};

/// Per-dimension running mean and variance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObsNormalizer {
    /// Running mean.
    pub mean: Vec<f64>,
    /// Running (population) variance.
    pub var: Vec<f64>,
    /// Samples seen (starts at a tiny epsilon, as SB3's `RunningMeanStd`).
    pub count: f64,
    /// Normalised values are clipped to ±clip.
    pub clip: f64,
    /// Added to the variance before the square root.
    pub epsilon: f64,
}

impl ObsNormalizer {
    /// Identity statistics for `dim`-long observations.
    pub fn new(dim: usize) -> Self {
        Self { mean: vec![0.0; dim], var: vec![1.0; dim], count: 1e-4, clip: 10.0, epsilon: 1e-8 }
    }

    /// Observation length.
    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// Merges the statistics of a batch of rows (Chan et al.'s parallel update).
    pub fn update(&mut self, batch: &[f32]) {
        let dim = self.dim();
        assert_eq!(batch.len() % dim, 0, "batch length is not a multiple of the observation length");
        let n = (batch.len() / dim) as f64;
        if n == 0.0 {
            return;
        }
        for d in 0..dim {
            let column = batch.iter().skip(d).step_by(dim).map(|&x| f64::from(x));
            let batch_mean = column.clone().sum::<f64>() / n;
            let batch_var = column.map(|x| (x - batch_mean).powi(2)).sum::<f64>() / n;
            let delta = batch_mean - self.mean[d];
            let total = self.count + n;
            let m2 = self.var[d] * self.count + batch_var * n + delta * delta * self.count * n / total;
            self.mean[d] += delta * n / total;
            self.var[d] = m2 / total;
        }
        self.count += n;
    }

    /// Normalises rows of raw observations into `out`.
    pub fn normalize(&self, raw: &[f32], out: &mut [f32]) {
        let dim = self.dim();
        for (i, (o, &x)) in out.iter_mut().zip(raw).enumerate() {
            let d = i % dim;
            let z = (f64::from(x) - self.mean[d]) / (self.var[d] + self.epsilon).sqrt();
            *o = z.clamp(-self.clip, self.clip) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batched_updates_equal_the_statistics_of_all_data() {
        let data: Vec<f32> = (0..200).map(|i| ((i * 37) % 23) as f32 * 0.5 - 3.0).collect();
        let mut n = ObsNormalizer::new(2);
        n.count = 0.0;
        for chunk in data.chunks(26) {
            n.update(chunk);
        }
        for d in 0..2 {
            let col: Vec<f64> = data.iter().skip(d).step_by(2).map(|&x| f64::from(x)).collect();
            let mean = col.iter().sum::<f64>() / col.len() as f64;
            let var = col.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / col.len() as f64;
            assert!((n.mean[d] - mean).abs() < 1e-12 && (n.var[d] - var).abs() < 1e-12);
        }
        let mut out = vec![0.0; 2];
        n.normalize(&[1e6, n.mean[1] as f32], &mut out);
        assert_eq!(out[0], 10.0, "clipped");
        assert!(out[1].abs() < 1e-6);
    }
}
