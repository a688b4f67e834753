//! Blobs for the tests: the shapes of an architecture filled with a seeded pattern, as a
//! network would export them.

use crate::shapes::{ExportedParam, parameter_shapes};
use crate::{Architecture, ObsNormalizer, WeightsBlob};

/// A blob of `arch` whose every parameter holds small values drawn from `seed`.
pub(crate) fn pattern_blob(arch: &Architecture, normalizer: ObsNormalizer, version: u64, seed: u64) -> WeightsBlob {
    let params = parameter_shapes(arch)
        .into_iter()
        .enumerate()
        .map(|(i, shape)| {
            let n: usize = shape.iter().product();
            let values = (0..n).map(|k| (((k as u64 * 7 + i as u64 * 13 + seed * 31) % 23) as f32 - 11.0) * 0.01).collect();
            ExportedParam { id: 100 + i as u64, shape, values }
        })
        .collect();
    WeightsBlob { version, architecture: arch.clone(), normalizer, params }
}
