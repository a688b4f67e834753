//! Closed (periodic) smoothing spline curves, equal to
//! `scipy.interpolate.splprep(P_closed.T, s=s, per=1, k=3)`, i.e. FITPACK's `clocur`/`fpclos`
//! (P. Dierckx, *Curve and Surface Fitting with Splines*, 1993, ch. 5–6).
//!
//! The method, as FITPACK runs it:
//! 1. Knots. Start from a constant (a single point); while the least-squares closed spline
//!    with the current knots leaves a residual sum `fp > s`, add knots — each new one at the
//!    middle data point of the knot interval with the largest residual share — in batches
//!    sized from how fast `fp` fell last time. With `m + 2k` knots the spline interpolates.
//! 2. Smoothing. With those knots, minimise `Σ residual² + Σ (jump of the k-th derivative at
//!    each interior knot / p)²` and find p with `fp(p) = s` (within 0.1 %) by rational
//!    interpolation of `fp(p)`, starting from `p = n7 / trace(R)` of the observation matrix.
//!
//! FITPACK rotates rows into banded triangles with Givens rotations; the systems here have at
//! most a few dozen rows, so each least-squares stage is solved with a dense QR instead. Every
//! decision (knot positions, batch sizes, the p iteration) follows FITPACK's rules exactly, so
//! the results agree to rounding.

use sim::nalgebra::{DMatrix, Vector3};

use super::bspline::{BSplineCurve, basis};

/// Degree of the track splines (cubic).
pub const DEGREE: usize = 3;
/// Relative tolerance on `fp(p) = s` (FITPACK's `tol`).
const TOLERANCE: f64 = 0.001;
/// Most iterations of the smoothing-parameter search (FITPACK's `maxit`).
const MAX_ITERATIONS: usize = 20;

/// Why a closed curve could not be fitted.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SplineError {
    /// Fewer control points than a closed cubic needs.
    #[error("need at least {min} control points, got {got}")]
    TooFewPoints {
        /// Smallest count accepted.
        min: usize,
        /// Count given.
        got: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("control point {index} has a coordinate that is not a finite number")]
    NotFinite {
        /// 0-based point index.
        index: usize,
    },
    /// Two consecutive points (cyclically) coincide, so the chord parameter does not increase.
    #[error("control points {index} and {next} coincide")]
    RepeatedPoint {
        /// 0-based index of the first.
        index: usize,
        /// 0-based index of the second.
        next: usize,
    },
    /// The smoothing factor is negative or not finite.
    #[error("smoothing factor must be a finite number ≥ 0, got {0}")]
    BadSmoothing(f64),
}

/// A fitted closed curve with the parameter values of its data points.
#[derive(Clone, Debug, PartialEq)]
pub struct ClosedCurveFit {
    /// Normalised cumulative chord length of the closed polygon, one per point plus 1.0.
    pub u: Vec<f64>,
    /// The spline in FITPACK's representation.
    pub curve: BSplineCurve,
    /// Weighted sum of squared residuals at the data points.
    pub residual: f64,
}

/// A row of a control-point CSV that is not `x,y,z`.
#[derive(Debug, PartialEq, thiserror::Error)]
#[error("expected x,y,z (3 finite numbers), found {found:?}")]
pub struct ControlPointsError {
    /// 1-based line number.
    pub line: usize,
    /// The line as read.
    pub found: String,
}

/// Control points from CSV text, one `x,y,z` a row, no header; blank lines are skipped.
pub fn control_points_from_csv(text: &str) -> Result<Vec<Vector3<f64>>, ControlPointsError> {
    let mut points = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let values: Vec<Option<f64>> = line.split(',').map(|f| f.trim().parse::<f64>().ok().filter(|x| x.is_finite())).collect();
        let [Some(x), Some(y), Some(z)] = values[..] else {
            return Err(ControlPointsError { line: i + 1, found: line.to_string() });
        };
        points.push(Vector3::new(x, y, z));
    }
    Ok(points)
}

/// Fits a closed cubic smoothing spline through `points` (the closing point is added here).
pub fn fit_closed_curve(points: &[Vector3<f64>], s: f64) -> Result<ClosedCurveFit, SplineError> {
    let k = DEGREE;
    if points.len() < k + 1 {
        return Err(SplineError::TooFewPoints { min: k + 1, got: points.len() });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(SplineError::NotFinite { index });
    }
    if !(s.is_finite() && s >= 0.0) {
        return Err(SplineError::BadSmoothing(s));
    }
    let u = chord_parameters(points)?;
    let data = DMatrix::from_fn(points.len(), 3, |i, d| points[i][d]);
    let (curve, residual) = Fitter { u: &u, data: &data, s }.fit();
    Ok(ClosedCurveFit { u, curve, residual })
}

/// `u_0 = 0`, `u_i` = cumulative chord length to point i (cyclically closed), divided by the total.
fn chord_parameters(points: &[Vector3<f64>]) -> Result<Vec<f64>, SplineError> {
    let m1 = points.len();
    let mut u = vec![0.0; m1 + 1];
    for i in 1..=m1 {
        let chord = (points[i % m1] - points[i - 1]).norm();
        if chord == 0.0 {
            return Err(SplineError::RepeatedPoint { index: i - 1, next: i % m1 });
        }
        u[i] = u[i - 1] + chord;
    }
    let total = u[m1];
    u.iter_mut().for_each(|x| *x /= total);
    u[m1] = 1.0;
    Ok(u)
}

/// One fit: parameters `u` (m values, the last the closing 1.0) and the m − 1 distinct points.
struct Fitter<'a> {
    u: &'a [f64],
    data: &'a DMatrix<f64>,
    s: f64,
}

/// A least-squares solution with the given knots.
struct Solution {
    /// Periodic coefficients, `n7 × 3`.
    coefficients: DMatrix<f64>,
    /// Sum of squared residuals.
    fp: f64,
}

impl Fitter<'_> {
    fn m1(&self) -> usize {
        self.data.nrows()
    }

    fn fit(&self) -> (BSplineCurve, f64) {
        let k = DEGREE;
        let (m1, s) = (self.m1(), self.s);
        let n_max = m1 + 1 + 2 * k;
        let acc = TOLERANCE * s;
        if s == 0.0 {
            let knots = self.knots(&self.u[1..m1]);
            let solution = self.least_squares(&knots).0;
            return (self.curve(knots, &solution), solution.fp);
        }

        // The least-squares constant: a single point.
        let mean = DMatrix::from_fn(1, 3, |_, d| self.data.column(d).mean());
        let fp0: f64 = (0..m1).map(|i| (self.data.row(i) - &mean).norm_squared()).sum();
        if fp0 - s < acc {
            return (self.constant_curve(&mean), fp0);
        }

        // Part 1: add knots until the least-squares spline's residual drops below s.
        let mid = (m1 + 2) / 2; // FITPACK's mm = (m+1)/2, 1-based
        let mut interior = vec![self.u[mid - 1]];
        let mut inside = vec![mid - 2, m1 - mid]; // data points strictly inside each interval
        let mut fp_old = fp0;
        let mut batch = 1usize;
        // FITPACK bounds the knot search by m rounds; each round adds at least one knot.
        let mut rounds = 0;
        let (knots, mut solution, trace) = loop {
            let knots = self.knots(&interior);
            let (solution, trace) = self.least_squares(&knots);
            let fpms = solution.fp - s;
            if fpms.abs() < acc || (fpms >= 0.0 && knots.len() == n_max) {
                return (self.curve(knots, &solution), solution.fp);
            }
            rounds += 1;
            if fpms < 0.0 || rounds > m1 {
                break (knots, solution, trace);
            }
            // How many knots to add: extrapolate the last decrease of fp, within [n/2, 2n].
            let mut proposal = batch * 2;
            if fp_old - solution.fp > acc {
                proposal = (batch as f64 * fpms / (fp_old - solution.fp)) as usize;
            }
            batch = (batch * 2).min(proposal.max(batch / 2).max(1));
            fp_old = solution.fp;
            let mut shares = self.interval_residuals(&knots, &solution, interior.len() + 1);
            for _ in 0..batch {
                add_knot(self.u, &mut interior, &mut inside, &mut shares);
                if interior.len() + 2 * k + 2 == n_max {
                    // As many knots as for interpolation: put them at the data points.
                    interior = self.u[1..m1].to_vec();
                    break;
                }
            }
        };

        // Part 2: the smoothing spline with fp(p) = s.
        let fpms = solution.fp - s;
        let jumps = self.periodic_jumps(&knots);
        let n7 = knots.len() - 2 * k - 1;
        let (mut p1, mut f1, mut p3, mut f3) = (0.0, fp0 - s, -1.0, fpms);
        let mut p = n7 as f64 / trace;
        let (mut found_above, mut found_below) = (false, false);
        for iteration in 1..=MAX_ITERATIONS {
            solution = self.smoothed(&knots, &jumps, p);
            let f2 = solution.fp - s;
            if f2.abs() < acc || iteration == MAX_ITERATIONS {
                break;
            }
            let p2 = p;
            if !found_below {
                if f2 - f3 <= acc {
                    // The initial p was too large.
                    (p3, f3) = (p2, f2);
                    p *= 0.04;
                    if p <= p1 {
                        p = p1 * 0.9 + p2 * 0.1;
                    }
                    continue;
                }
                found_below = f2 < 0.0;
            }
            if !found_above {
                if f1 - f2 <= acc {
                    // The initial p was too small.
                    (p1, f1) = (p2, f2);
                    p /= 0.04;
                    if p3 >= 0.0 && p >= p3 {
                        p = p2 * 0.1 + p3 * 0.9;
                    }
                    continue;
                }
                found_above = f2 > 0.0;
            }
            if f2 >= f1 || f2 <= f3 {
                // fp(p) is not behaving as theory says; FITPACK stops here too (ier = 2).
                break;
            }
            p = rational_root(&mut p1, &mut f1, p2, f2, &mut p3, &mut f3);
        }
        (self.curve(knots, &solution), solution.fp)
    }

    /// Full knot vector of a closed spline with these interior knots: `t[k] = u_0`,
    /// `t[n-k-1] = u_m`, and k knots on each side continued with the period.
    fn knots(&self, interior: &[f64]) -> Vec<f64> {
        let k = DEGREE;
        let (first, last) = (self.u[0], self.u[self.u.len() - 1]);
        let period = last - first;
        let n = interior.len() + 2 * k + 2;
        let mut t = vec![0.0; n];
        t[k] = first;
        t[n - k - 1] = last;
        t[k + 1..n - k - 1].copy_from_slice(interior);
        for j in 1..=k {
            t[n - k - 1 + j] = t[k + j] + period;
            t[k - j] = t[n - k - 1 - j] - period;
        }
        t
    }

    /// Observation matrix of the periodic basis: column `j` collects the B-splines whose
    /// coefficients are tied to coefficient `j` (index modulo n7).
    fn observation_matrix(&self, knots: &[f64]) -> DMatrix<f64> {
        let k = DEGREE;
        let n7 = knots.len() - 2 * k - 1;
        let mut a = DMatrix::zeros(self.m1(), n7);
        let mut l = k;
        for (row, &x) in self.u[..self.m1()].iter().enumerate() {
            while x >= knots[l + 1] {
                l += 1;
            }
            for (i, h) in basis(knots, k, l, x).into_iter().enumerate() {
                a[(row, (l - k + i) % n7)] += h;
            }
        }
        a
    }

    /// Least-squares closed spline with these knots, and the trace of its triangular factor.
    #[allow(clippy::expect_used, reason = "the knots interlace the data, so the observation matrix has full rank")]
    fn least_squares(&self, knots: &[f64]) -> (Solution, f64) {
        let a = self.observation_matrix(knots);
        let qr = a.clone().qr();
        let r = qr.r();
        let coefficients = r
            .solve_upper_triangular(&(qr.q().transpose() * self.data))
            .expect("the knots interlace the data, so the observation matrix has full rank");
        // FITPACK's Givens rotations leave a non-negative diagonal: |R_ii| is unique.
        let trace = r.diagonal().iter().map(|d| d.abs()).sum();
        let fp = (&a * &coefficients - self.data).norm_squared();
        (Solution { coefficients, fp }, trace)
    }

    /// The smoothing spline for weight p: least squares on the data rows plus the jump rows / p.
    #[allow(clippy::expect_used, reason = "the data rows alone have full rank")]
    fn smoothed(&self, knots: &[f64], jumps: &DMatrix<f64>, p: f64) -> Solution {
        let a = self.observation_matrix(knots);
        let (m1, n8, n7) = (a.nrows(), jumps.nrows(), a.ncols());
        let mut stacked = DMatrix::zeros(m1 + n8, n7);
        stacked.rows_mut(0, m1).copy_from(&a);
        stacked.rows_mut(m1, n8).copy_from(&(jumps / p));
        let mut rhs = DMatrix::zeros(m1 + n8, 3);
        rhs.rows_mut(0, m1).copy_from(self.data);
        let qr = stacked.qr();
        let coefficients = qr.r().solve_upper_triangular(&(qr.q().transpose() * rhs)).expect("the data rows alone have full rank");
        let fp = (&a * &coefficients - self.data).norm_squared();
        Solution { coefficients, fp }
    }

    /// Jumps of the k-th derivative of every B-spline at each interior knot (FITPACK's fpdisc,
    /// including its scaling), with columns tied modulo n7 like the observation matrix.
    fn periodic_jumps(&self, t: &[f64]) -> DMatrix<f64> {
        let k = DEGREE;
        let n = t.len();
        let (k1, nk1) = (k + 1, n - k - 1);
        let n7 = nk1 - k;
        let intervals = (nk1 - k) as f64;
        let fac = intervals / (t[nk1] - t[k]);
        let mut b = DMatrix::zeros(n - 2 * k - 2, n7);
        // Interior knot t[l], l = k+1 ..= nk1-1 (0-based), is row l - k - 1.
        for l in k + 1..nk1 {
            let row = l - k1;
            // Differences t[l] − t[r] for r = l−k−1 … l−1, l+1 … l+k+1.
            let h: Vec<f64> = (l - k1..l).chain(l + 1..=l + k1).map(|r| t[l] - t[r]).collect();
            for j in 0..k + 2 {
                let product = h[j] * (1..=k).map(|i| h[j + i] * fac).product::<f64>();
                let first = row + j; // B-spline on knots t[first] … t[first + k + 1]
                b[(row, first % n7)] += (t[first + k1] - t[first]) / product;
            }
        }
        b
    }

    /// Residual sums per knot interval (FITPACK's fpint): a data point on a knot is shared half
    /// and half, and the first point (on the periodic seam) counts for the last interval too.
    fn interval_residuals(&self, knots: &[f64], solution: &Solution, intervals: usize) -> Vec<f64> {
        let k = DEGREE;
        let residuals = &self.observation_matrix(knots) * &solution.coefficients - self.data;
        let mut shares = vec![0.0; intervals];
        let (mut running, mut i, mut l) = (0.0, 0, k);
        for (row, &x) in self.u[..self.m1()].iter().enumerate() {
            let term = residuals.row(row).norm_squared();
            let entered = x >= knots[l];
            if entered {
                l += 1;
            }
            running += term;
            if entered {
                if l <= k + 1 {
                    shares[intervals - 1] = term;
                } else {
                    let half = term / 2.0;
                    shares[i] = running - half;
                    i += 1;
                    running = half;
                }
            }
        }
        shares[intervals - 1] += running;
        shares
    }

    fn curve(&self, knots: Vec<f64>, solution: &Solution) -> BSplineCurve {
        let n7 = solution.coefficients.nrows();
        let count = knots.len() - DEGREE - 1;
        let coefficients = std::array::from_fn(|d| (0..count).map(|j| solution.coefficients[(j % n7, d)]).collect());
        BSplineCurve { knots, coefficients, degree: DEGREE }
    }

    /// A constant closed spline: `2k + 2` knots, every coefficient the mean point.
    fn constant_curve(&self, mean: &DMatrix<f64>) -> BSplineCurve {
        let k = DEGREE;
        let (first, last) = (self.u[0], self.u[self.u.len() - 1]);
        let period = last - first;
        let knots = (0..=k).map(|i| first - (k - i) as f64 * period).chain((0..=k).map(|i| last + i as f64 * period)).collect();
        BSplineCurve { knots, coefficients: std::array::from_fn(|d| vec![mean[(0, d)]; k + 1]), degree: k }
    }
}

/// FITPACK's fpknot: splits the interval with the largest residual share (among those holding
/// data) at its middle data point; shares and data counts are divided in proportion.
#[allow(clippy::expect_used, reason = "an interval with data and a positive residual")]
fn add_knot(u: &[f64], interior: &mut Vec<f64>, inside: &mut Vec<usize>, shares: &mut Vec<f64>) {
    let mut best: Option<(usize, usize, usize, f64)> = None;
    let mut start = 1; // 1-based index of the data point on the interval's left knot
    let mut largest = 0.0;
    for (j, (&count, &share)) in inside.iter().zip(shares.iter()).enumerate() {
        if share > largest && count != 0 {
            largest = share;
            best = Some((j, count, start, share));
        }
        start += count + 1;
    }
    // Part 1 only adds knots while fp > s > 0, so some interval with data has a positive share.
    let (j, count, start, share) = best.expect("an interval with data and a positive residual");
    let half = count / 2 + 1;
    interior.insert(j, u[start + half - 1]);
    inside[j] = half - 1;
    inside.insert(j + 1, count - half);
    shares[j] = share * (half - 1) as f64 / count as f64;
    shares.insert(j + 1, share * (count - half) as f64 / count as f64);
}

/// FITPACK's fprati: the p where the rational function through (p1,f1), (p2,f2), (p3,f3)
/// crosses zero (p3 < 0 meaning infinity); keeps f1 > 0 and f3 < 0 around the root.
fn rational_root(p1: &mut f64, f1: &mut f64, p2: f64, f2: f64, p3: &mut f64, f3: &mut f64) -> f64 {
    let p = if *p3 > 0.0 {
        let h1 = *f1 * (f2 - *f3);
        let h2 = f2 * (*f3 - *f1);
        let h3 = *f3 * (*f1 - f2);
        -(*p1 * p2 * h3 + p2 * *p3 * h1 + *p3 * *p1 * h2) / (*p1 * h1 + p2 * h2 + *p3 * h3)
    } else {
        (*p1 * (*f1 - *f3) * f2 - p2 * (f2 - *f3) * *f1) / ((*f1 - f2) * *f3)
    };
    if f2 < 0.0 {
        (*p3, *f3) = (p2, f2);
    } else {
        (*p1, *f1) = (p2, f2);
    }
    p
}
