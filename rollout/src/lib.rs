//! What an actor sends the learner: a [`RolloutChunk`] of transitions with its episodes'
//! records, checked against the limits the learner admits (`chunk`), framed for the wire, with
//! camera images run-length coded (`run_length`). No transport: `proto` carries the bytes.

pub mod chunk;
pub mod run_length;

pub use chunk::{ChunkLimits, EpisodeRecord, RolloutCheckError, RolloutChunk, RolloutWireError};
