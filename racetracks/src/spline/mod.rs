//! Splines for track generation: B-spline curves and the closed smoothing fit of FITPACK.

mod bspline;
mod closed_fit;

pub use bspline::{BSplineCurve, basis};
pub use closed_fit::{ClosedCurveFit, DEGREE, SplineError, fit_closed_curve};
