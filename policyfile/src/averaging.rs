//! The parameter-wise mean of several policies of one run (stochastic weight averaging).
//!
//! Checkpoints of one PPO run were trained against different normaliser statistics, so a
//! first-layer weight means something slightly different in each. Each policy's normaliser is
//! therefore folded into its first layers (so they act on raw observations), the folded
//! parameters are averaged, and the mean is expressed again under the newest policy's
//! normaliser. Apart from the normaliser's clip at ±10 standard deviations, the result is
//! exactly the average of the policies' first layers as functions of the raw observation.
//!
//! A vision policy's first layers are convolutions of the image, and only part of its actor
//! reads the normalised state, so there is no such fold: vision policies are averaged only when
//! they share one normaliser — as the checkpoints of one distillation do, whose student keeps
//! its teacher's, frozen.

use crate::architecture::Agent;
use crate::blob::{BlobError, WeightsBlob};

/// The parameter-wise mean of `blobs` (agents of one architecture; vision agents under one
/// normaliser); version, normaliser and parameter ids are the newest blob's (highest version).
pub fn average(blobs: &[WeightsBlob]) -> Result<WeightsBlob, BlobError> {
    let newest = blobs.iter().max_by_key(|b| b.version).ok_or_else(|| BlobError::Malformed("no policies to average".into()))?;
    for blob in blobs {
        blob.check_architecture(&newest.architecture)?;
        if newest.architecture.agent == Agent::Vision && blob.normalizer != newest.normalizer {
            return Err(BlobError::Malformed(format!(
                "vision policies v{} and v{} normalise their states differently: only those of one normaliser average",
                blob.version, newest.version
            )));
        }
    }
    let names = WeightsBlob::tensor_names(&newest.architecture);
    // Under one normaliser folding changes nothing, so a vision agent's layers average as they are.
    let first_layers: Vec<(usize, usize)> = match newest.architecture.agent {
        Agent::Vision => Vec::new(),
        Agent::State => ["actor", "critic"]
            .iter()
            .filter_map(|net| {
                let weight = names.iter().position(|n| *n == format!("{net}.0.weight"))?;
                let bias = names.iter().position(|n| *n == format!("{net}.0.bias"))?;
                Some((weight, bias))
            })
            .collect(),
    };
    let mut sums: Vec<Vec<f64>> = newest.params.iter().map(|p| vec![0.0; p.values.len()]).collect();
    for blob in blobs {
        let mut params: Vec<Vec<f64>> = blob.params.iter().map(|p| p.values.iter().map(|&v| f64::from(v)).collect()).collect();
        for &(weight, bias) in &first_layers {
            fold(blob, &mut params, weight, bias);
        }
        for (sum, values) in sums.iter_mut().zip(&params) {
            for (s, v) in sum.iter_mut().zip(values) {
                *s += v;
            }
        }
    }
    let n = blobs.len() as f64;
    for sum in &mut sums {
        sum.iter_mut().for_each(|s| *s /= n);
    }
    for &(weight, bias) in &first_layers {
        unfold(newest, &mut sums, weight, bias);
    }
    let mut mean = newest.clone();
    for (param, values) in mean.params.iter_mut().zip(sums) {
        param.values = values.into_iter().map(|v| v as f32).collect();
    }
    Ok(mean)
}

/// Per-input (mean, standard deviation) of a blob's normaliser.
fn statistics(blob: &WeightsBlob) -> impl Iterator<Item = (f64, f64)> + '_ {
    let n = &blob.normalizer;
    n.mean.iter().zip(&n.var).map(|(&m, &v)| (m, (v + n.epsilon).sqrt()))
}

/// Rewrites a first layer `W`, `b` (`W` is `[inputs, outputs]`, row-major) of normalised
/// inputs as the same affine map of raw inputs: `W'ᵢ = Wᵢ / sᵢ`, `b' = b − Σᵢ mᵢ W'ᵢ`.
fn fold(blob: &WeightsBlob, params: &mut [Vec<f64>], weight: usize, bias: usize) {
    let outputs = params[bias].len();
    let inputs = params[weight].len() / outputs;
    for (i, (mean, scale)) in statistics(blob).take(inputs).enumerate() {
        for o in 0..outputs {
            let w = params[weight][i * outputs + o] / scale;
            params[weight][i * outputs + o] = w;
            params[bias][o] -= mean * w;
        }
    }
}

/// The inverse of [`fold`] under `blob`'s normaliser.
fn unfold(blob: &WeightsBlob, params: &mut [Vec<f64>], weight: usize, bias: usize) {
    let outputs = params[bias].len();
    let inputs = params[weight].len() / outputs;
    for (i, (mean, scale)) in statistics(blob).take(inputs).enumerate() {
        for o in 0..outputs {
            let w = params[weight][i * outputs + o];
            params[bias][o] += mean * w;
            params[weight][i * outputs + o] = w * scale;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_blobs::pattern_blob;
    use crate::{Architecture, ObsNormalizer};

    fn small(hidden: Vec<usize>) -> Architecture {
        Architecture { hidden, ..Architecture::paper() }
    }

    fn blob(seed: u64, version: u64, normalizer: ObsNormalizer) -> WeightsBlob {
        pattern_blob(&small(vec![16, 16]), normalizer, version, seed)
    }

    fn skewed_normalizer(dim: usize, shift: f64) -> ObsNormalizer {
        let mut n = ObsNormalizer::new(dim);
        n.mean = (0..dim).map(|i| shift + 0.1 * i as f64).collect();
        n.var = (0..dim).map(|i| 0.5 + shift * 0.3 + 0.05 * i as f64).collect();
        n
    }

    fn observations(dim: usize) -> Vec<f32> {
        (0..dim * 8).map(|i| ((i * 29) % 17) as f32 * 0.2 - 1.5).collect()
    }

    /// The first layer's outputs `normalise(x)·W + b` for every observation row: the only
    /// layer averaging re-expresses, so equal outputs here are an equal policy.
    fn first_layer(blob: &WeightsBlob, weight: usize, raw: &[f32]) -> Vec<f32> {
        let dim = blob.normalizer.dim();
        let (w, b) = (&blob.params[weight].values, &blob.params[weight + 1].values);
        let outputs = b.len();
        let mut out = Vec::new();
        for row in raw.chunks(dim) {
            let mut x = vec![0.0; dim];
            blob.normalizer.normalize(row, &mut x);
            out.extend((0..outputs).map(|o| b[o] + x.iter().enumerate().map(|(i, xi)| xi * w[i * outputs + o]).sum::<f32>()));
        }
        out
    }

    fn max_difference(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    #[test]
    fn the_mean_of_two_policies_under_one_normaliser_is_the_elementwise_mean() {
        let dim = small(vec![16, 16]).observation_dim;
        let (a, b) = (blob(1, 10, skewed_normalizer(dim, 0.4)), blob(2, 20, skewed_normalizer(dim, 0.4)));
        let mean = average(&[a.clone(), b.clone()]).unwrap();
        assert_eq!(mean.version, 20);
        for ((m, x), y) in mean.params.iter().zip(&a.params).zip(&b.params) {
            for ((&m, &x), &y) in m.values.iter().zip(&x.values).zip(&y.values) {
                assert!((m - (x + y) / 2.0).abs() < 1e-5, "{m} against {}", (x + y) / 2.0);
            }
        }
    }

    /// The same policy re-expressed under other statistics (fold under the old, unfold under
    /// the new) computes the same first layers, and its mean with the original is the original.
    #[test]
    fn one_function_under_two_normalisers_averages_to_itself() {
        let arch = small(vec![16, 16]);
        let dim = arch.observation_dim;
        let original = pattern_blob(&arch, skewed_normalizer(dim, 0.2), 5, 3);
        let mut restated = original.clone();
        restated.version = 6;
        restated.normalizer = skewed_normalizer(dim, 1.3);
        let mut params: Vec<Vec<f64>> = original.params.iter().map(|p| p.values.iter().map(|&v| f64::from(v)).collect()).collect();
        let critic_first = 2 * (arch.hidden.len() + 1);
        for (weight, bias) in [(0, 1), (critic_first, critic_first + 1)] {
            fold(&original, &mut params, weight, bias);
            unfold(&restated, &mut params, weight, bias);
        }
        for (p, values) in restated.params.iter_mut().zip(params) {
            p.values = values.into_iter().map(|v| v as f32).collect();
        }
        let raw = observations(dim);
        let mean = average(&[original.clone(), restated.clone()]).unwrap();
        for layer in [0, critic_first] {
            let expected = first_layer(&original, layer, &raw);
            assert!(max_difference(&expected, &first_layer(&restated, layer, &raw)) < 1e-4);
            assert!(max_difference(&expected, &first_layer(&mean, layer, &raw)) < 1e-4);
        }
        assert_eq!(mean.params[2..critic_first], original.params[2..critic_first], "deeper layers are the same");
    }

    #[test]
    fn vision_policies_under_one_normaliser_average_elementwise_and_under_two_are_refused() {
        let arch = Architecture { hidden: vec![8], agent: Agent::Vision, ..Architecture::paper() };
        let vision = |seed: u64, version: u64, normalizer: ObsNormalizer| pattern_blob(&arch, normalizer, version, seed);
        let dim = arch.observation_dim;
        let (a, b) = (vision(1, 10, skewed_normalizer(dim, 0.4)), vision(2, 20, skewed_normalizer(dim, 0.4)));
        let mean = average(&[a.clone(), b.clone()]).unwrap();
        assert_eq!((mean.version, mean.architecture.agent), (20, Agent::Vision));
        for ((m, x), y) in mean.params.iter().zip(&a.params).zip(&b.params) {
            for ((&m, &x), &y) in m.values.iter().zip(&x.values).zip(&y.values) {
                assert!((m - (x + y) / 2.0).abs() < 1e-6, "{m} against {}", (x + y) / 2.0);
            }
        }
        let other = vision(3, 30, skewed_normalizer(dim, 1.0));
        assert!(matches!(average(&[a, other]), Err(BlobError::Malformed(m)) if m.contains("normalise")));
        // Nor does a vision policy average with a state-based one.
        assert!(matches!(average(&[b, blob(4, 5, skewed_normalizer(dim, 0.4))]), Err(BlobError::Architecture { .. })));
    }

    #[test]
    fn policies_of_different_shapes_or_none_are_refused() {
        let dim = small(vec![16, 16]).observation_dim;
        let narrow = blob(1, 1, skewed_normalizer(dim, 0.0));
        let wide = pattern_blob(&small(vec![32, 16]), skewed_normalizer(dim, 0.0), 2, 1);
        assert!(matches!(average(&[narrow, wide]), Err(BlobError::Architecture { .. })));
        assert!(matches!(average(&[]), Err(BlobError::Malformed(_))));
    }
}
