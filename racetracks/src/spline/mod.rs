//! Splines for track generation: B-spline curves and the closed smoothing fit of FITPACK.

mod bspline;
mod closed_fit;

pub use bspline::{BSplineCurve, basis};
pub use closed_fit::{ClosedCurveFit, ControlPointsError, DEGREE, SplineError, control_points_from_csv, fit_closed_curve};
