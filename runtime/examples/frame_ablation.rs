//! Whether a stacked-frame student uses its earlier frames: writes the student with the first
//! convolution's kernels for every earlier frame set to zero, so that it acts on the current
//! frame alone. Evaluating both (`dronerace eval --controller policy --policy …`) tells how
//! much of its racing the earlier frames carry.
//!
//! `cargo run --release -p runtime --example frame_ablation -- STUDENT OUT`

#![allow(clippy::print_stdout, reason = "the summary on stdout is what this analysis is for")]

use std::path::Path;

use anyhow::{Context, bail, ensure};
use learner::checkpoint::read_policy;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [student, out] = args.as_slice() else {
        bail!("usage: frame_ablation STUDENT OUT");
    };
    let mut blob = read_policy(Path::new(student)).with_context(|| format!("student {student}"))?;
    blob.check_agent(policy::Agent::Vision)?;
    let frames = blob.architecture.frame_stack.frames;
    ensure!(frames > 1, "{student} sees one camera frame: nothing to ablate");
    // The first parameter is the first convolution's weight, `[out, frames, k, k]` row-major.
    let weight = blob.params.first_mut().context("a vision blob has parameters")?;
    let kernel = weight.shape.iter().skip(2).product::<usize>();
    let rms = |w: &[f32]| (w.iter().map(|v| f64::from(v * v)).sum::<f64>() / w.len() as f64).sqrt();
    for (frame, name) in (0..frames).zip(std::iter::once("current").chain(std::iter::repeat("earlier"))) {
        let values: Vec<f32> = weight.values.chunks_exact(kernel).skip(frame).step_by(frames).flatten().copied().collect();
        println!("frame {frame} ({name}): kernel RMS {:.4}", rms(&values));
    }
    for (i, chunk) in weight.values.chunks_exact_mut(kernel).enumerate() {
        if i % frames != 0 {
            chunk.fill(0.0);
        }
    }
    std::fs::write(out, blob.to_bytes()).with_context(|| format!("writing {out}"))?;
    println!("wrote {out}: the earlier frames' kernels are zero");
    Ok(())
}
