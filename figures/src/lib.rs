//! The figures and images dronerace draws: track layouts, experiments' validation curves and
//! runs' learning curves (`plot`), and what the vision agent sees, frame by frame and over a
//! whole flight (`flight`).

pub mod flight;
pub mod plot;
pub mod robustness;

/// Why a figure could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    /// Nothing to draw, or a bad setting.
    #[error("{0}")]
    Nothing(&'static str),
    /// Drawing or encoding failed.
    #[error("{0}")]
    Draw(String),
    /// A file could not be read or a directory made.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// A metrics file that is not what a run writes.
    #[error("{0}")]
    Csv(String),
}

impl<E: std::error::Error + Send + Sync> From<plotters::drawing::DrawingAreaErrorKind<E>> for FigureError {
    fn from(e: plotters::drawing::DrawingAreaErrorKind<E>) -> Self {
        FigureError::Draw(e.to_string())
    }
}
