//! Racetracks: track files, the hand-designed library, generation and task switching.
