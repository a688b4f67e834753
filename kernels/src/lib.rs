//! The dense layers' kernels: a stack of `x·W + b` with LeakyReLU as one burn autodiff op whose
//! forward and backward call gemm's matrix kernels directly (`dense`), row-by-row kernels for
//! layers too narrow for them (`narrow`), and the per-row helpers both share (`rows`). Kept
//! apart from the networks because they are measured, not designed: BENCHMARKS.md has the
//! figures that justify each.

pub mod dense;
mod narrow;
mod rows;
