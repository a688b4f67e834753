//! How closely a distilled vision student fits the states it was trained on: the mean squared
//! difference between its action means and the teacher's labels on a uniform sample of its own
//! distillation's data set, split by whether the image shows the target gate. Read against
//! `label_gap`'s figure for the same student on fresh flights: a much lower figure here is a
//! generalisation gap (the CNN fits its data set better than new states of the same kind).
//!
//! `cargo run --release -p runtime --example dataset_fit -- CHECKPOINT [SAMPLES]`
//!
//! CHECKPOINT is a periodic checkpoint of a distillation (it holds the student and the data
//! set); SAMPLES defaults to 20,000.

#![allow(clippy::print_stdout, reason = "the table on stdout is what this analysis is for")]

use std::path::Path;

use anyhow::{Context, bail};
use learner::checkpoint::Checkpoint;
use learner::distill::DistillDataset;
use policy::{VisionPolicy, WeightsBlob};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sim::ACTION_DIM;
use sim::camera::{IMAGE_PIXELS, TARGET_COLOUR};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (checkpoint, samples) = match args.as_slice() {
        [c] => (c, 20_000),
        [c, n] => (c, n.parse().with_context(|| format!("samples {n:?}"))?),
        _ => bail!("usage: dataset_fit CHECKPOINT [SAMPLES]"),
    };
    let checkpoint = Checkpoint::read(Path::new(checkpoint))?;
    let student = VisionPolicy::from_blob(&WeightsBlob::from_bytes(checkpoint.get("weights")?)?)?;
    let data = DistillDataset::from_bytes(checkpoint.get("dataset")?)?;
    let rows = rand::seq::index::sample(&mut ChaCha8Rng::seed_from_u64(0), data.len(), samples.min(data.len())).into_vec();
    // Summed squared errors and counts: target gate in view (0) or not (1).
    let mut sums = [[0f64; 2]; 2];
    for chunk in rows.chunks(512) {
        let images = data.images(chunk);
        let means = student.mean_actions(&images, &data.states(chunk));
        for ((image, mean), label) in images
            .chunks_exact(data.frame_stack().image_len())
            .zip(means.chunks_exact(ACTION_DIM))
            .zip(data.labels(chunk).chunks_exact(ACTION_DIM))
        {
            let error = mean.iter().zip(label).map(|(m, l)| f64::from(m - l).powi(2)).sum::<f64>() / ACTION_DIM as f64;
            // Whether the current frame (each observation's first) shows the target gate.
            let row = usize::from(!image[..IMAGE_PIXELS].contains(&TARGET_COLOUR));
            sums[row][0] += error;
            sums[row][1] += 1.0;
        }
    }
    println!("{} of {} data-set states; mean squared difference from the teacher's label", rows.len(), data.len());
    for (name, s) in ["in view", "unseen"].iter().zip(&sums) {
        println!("{name:>8} {:>7} {:>9.4}", s[1], s[0] / s[1]);
    }
    println!("{:>8} {:>7} {:>9.4}", "all", sums[0][1] + sums[1][1], (sums[0][0] + sums[1][0]) / (sums[0][1] + sums[1][1]));
    Ok(())
}
