//! Policy-file surgery: a trained policy rewritten into another that acts exactly as it did
//! until trained further — a vision actor that also reads its previous action, wider hidden
//! layers — or with a chosen exploration noise. Each checks the shapes it produces against the
//! architecture it declares.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::architecture::Agent;
use crate::blob::{BlobError, WeightsBlob};
use crate::shapes::{CONVOLUTION_COUNT, check_shapes, parameter_shapes};

impl WeightsBlob {
    /// This vision policy with an actor that also reads its previous action
    /// ([`Architecture::vision_previous_action`]): the actor's first layer gains zero weights
    /// for the new inputs, so it acts exactly as before until it is trained further.
    pub fn with_vision_previous_action(&self) -> Result<Self, BlobError> {
        self.check_agent(Agent::Vision)?;
        let mut widened = self.clone();
        if widened.architecture.vision_previous_action {
            return Ok(widened);
        }
        widened.architecture.vision_previous_action = true;
        // Convolutions and the embedding (weight and bias each), then the actor's first weight,
        // `[inputs, outputs]` row-major: the new inputs are rows appended at the end.
        let first_actor_weight = 2 * CONVOLUTION_COUNT + 2;
        let weight = widened
            .params
            .get_mut(first_actor_weight)
            .ok_or_else(|| BlobError::Malformed(format!("{} parameters; the actor's first weight is missing", self.params.len())))?;
        let &[inputs, outputs] = weight.shape.as_slice() else {
            return Err(BlobError::Malformed(format!("actor's first weight has shape {:?}", weight.shape)));
        };
        weight.values.resize((inputs + sim::ACTION_DIM) * outputs, 0.0);
        weight.shape = vec![inputs + sim::ACTION_DIM, outputs];
        check_shapes(&parameter_shapes(&widened.architecture), &widened.params)?;
        Ok(widened)
    }

    /// This policy with its log standard deviation (the last parameter, one per action
    /// dimension) set to `log_std` everywhere: a distilled student's exploration noise is not
    /// what regression trained, so PPO from it chooses the noise it starts with.
    pub fn with_log_std(&self, log_std: f32) -> Result<Self, BlobError> {
        let mut changed = self.clone();
        let last = changed.params.last_mut().ok_or_else(|| BlobError::Malformed("no parameters".into()))?;
        if last.shape != [self.architecture.action_dim] {
            return Err(BlobError::Malformed(format!("the last parameter has shape {:?}, not a log std's", last.shape)));
        }
        last.values.fill(log_std);
        Ok(changed)
    }

    /// This policy with wider hidden layers (`hidden`: as many layers as it has, none
    /// narrower), acting and valuing exactly as before: each new unit gets fresh random
    /// incoming weights (He's scale √(2 / inputs), seeded) and zero outgoing ones, and no old
    /// unit reads a new one. PPO from it keeps the policy and gains capacity: gradients reach
    /// the new units' outgoing weights at once, and their incoming ones once those move.
    pub fn with_hidden(&self, hidden: &[usize], seed: u64) -> Result<Self, BlobError> {
        let old = &self.architecture.hidden;
        if hidden.len() != old.len() || hidden.iter().zip(old).any(|(new, old)| new < old) {
            return Err(BlobError::Malformed(format!("hidden layers {old:?} cannot widen to {hidden:?} (same depth, none narrower)")));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut widened = self.clone();
        widened.architecture.hidden = hidden.to_vec();
        // The actor's and the critic's layers (weight `[in, out]`, bias) sit before the log std.
        let layers = old.len() + 1;
        let mlps_start = self.params.len().checked_sub(4 * layers + 1).ok_or_else(|| BlobError::Malformed("too few parameters".into()))?;
        for mlp in 0..2 {
            for layer in 0..layers {
                let weight = mlps_start + 2 * (mlp * layers + layer);
                let bias = weight + 1;
                let [old_in, old_out] = self.params[weight].shape[..] else {
                    return Err(BlobError::Malformed(format!("parameter {weight} is not a dense layer's weight")));
                };
                let new_in = if layer == 0 { old_in } else { hidden[layer - 1] };
                let new_out = if layer == old.len() { old_out } else { hidden[layer] };
                let scale = (2.0 / new_in as f64).sqrt();
                let mut values = vec![0f32; new_in * new_out];
                for (i, row) in values.chunks_exact_mut(new_out).enumerate() {
                    for (j, value) in row.iter_mut().enumerate() {
                        *value = match (i < old_in, j < old_out) {
                            (true, true) => self.params[weight].values[i * old_out + j],
                            // An old unit never reads a new one.
                            (false, true) => 0.0,
                            _ => (scale * rng.sample::<f64, _>(rand_distr::StandardNormal)) as f32,
                        };
                    }
                }
                widened.params[weight].shape = vec![new_in, new_out];
                widened.params[weight].values = values;
                widened.params[bias].shape = vec![new_out];
                widened.params[bias].values.resize(new_out, 0.0);
            }
        }
        check_shapes(&parameter_shapes(&widened.architecture), &widened.params)?;
        Ok(widened)
    }
}
