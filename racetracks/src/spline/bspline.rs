//! B-spline curves in 3-D: evaluation (de Boor), derivatives and arc length.

use sim::nalgebra::Vector3;

/// A B-spline curve: knots, one coefficient vector per coordinate, degree.
///
/// Coefficients follow FITPACK's layout (`len(knots) - degree - 1` per coordinate); a closed
/// curve repeats its first `degree` coefficients at the end.
#[derive(Clone, Debug, PartialEq)]
pub struct BSplineCurve {
    /// Knot vector, non-decreasing.
    pub knots: Vec<f64>,
    /// Coefficients per coordinate x, y, z.
    pub coefficients: [Vec<f64>; 3],
    /// Polynomial degree.
    pub degree: usize,
}

/// Values of the `k + 1` B-splines of degree `k` that are non-zero on `[t[l], t[l+1])` at `x`
/// (Cox–de Boor recurrence).
pub fn basis(t: &[f64], k: usize, l: usize, x: f64) -> Vec<f64> {
    let mut h = vec![0.0; k + 1];
    h[0] = 1.0;
    for j in 1..=k {
        let previous = h[..j].to_vec();
        h[0] = 0.0;
        for i in 0..j {
            let (right, left) = (t[l + i + 1], t[l + i + 1 - j]);
            let f = previous[i] / (right - left);
            h[i] += f * (right - x);
            h[i + 1] = f * (x - left);
        }
    }
    h
}

impl BSplineCurve {
    /// Lower end of the parameter domain, `t[k]`.
    pub fn start(&self) -> f64 {
        self.knots[self.degree]
    }

    /// Upper end of the parameter domain, `t[n - k - 1]`.
    pub fn end(&self) -> f64 {
        self.knots[self.knots.len() - self.degree - 1]
    }

    /// Index `l` of the knot interval `[t[l], t[l+1])` holding `x`, clamped to the domain.
    pub fn interval(&self, x: f64) -> usize {
        let (k, n) = (self.degree, self.knots.len());
        let mut l = k;
        while l + 1 < n - k - 1 && x >= self.knots[l + 1] {
            l += 1;
        }
        l
    }

    /// Point on the curve at `x` (as `scipy.interpolate.splev`).
    pub fn point(&self, x: f64) -> Vector3<f64> {
        let k = self.degree;
        let l = self.interval(x);
        let h = basis(&self.knots, k, l, x);
        Vector3::from_fn(|d, _| (0..=k).map(|i| self.coefficients[d][l - k + i] * h[i]).sum())
    }

    /// The derivative curve, of degree `k - 1` on the knots without their first and last.
    pub fn derivative(&self) -> BSplineCurve {
        let k = self.degree;
        assert!(k > 0, "a degree-0 spline has no derivative curve");
        let t = &self.knots;
        let count = t.len() - k - 2;
        let coefficients = std::array::from_fn(|d| {
            let c = &self.coefficients[d];
            (0..count).map(|i| k as f64 * (c[i + 1] - c[i]) / (t[i + k + 1] - t[i + 1])).collect()
        });
        BSplineCurve { knots: t[1..t.len() - 1].to_vec(), coefficients, degree: k - 1 }
    }

    /// Length of the curve between parameters `a` and `b`.
    pub fn arc_length(&self, a: f64, b: f64) -> f64 {
        let velocity = self.derivative();
        self.pieces(a, b).windows(2).map(|w| speed_integral(&velocity, w[0], w[1])).sum()
    }

    /// Parameters splitting the closed curve into `count` pieces of equal arc length, from its
    /// start.
    pub fn equal_arc_parameters(&self, count: usize) -> Vec<f64> {
        let velocity = self.derivative();
        let breaks = self.pieces(self.start(), self.end());
        let mut cumulative = vec![0.0];
        for w in breaks.windows(2) {
            cumulative.push(cumulative[cumulative.len() - 1] + speed_integral(&velocity, w[0], w[1]));
        }
        let total = cumulative[cumulative.len() - 1];
        (0..count)
            .map(|i| {
                let target = total * i as f64 / count as f64;
                // The piece holding the target, then bisection inside it; 60 halvings reach rounding.
                let piece = cumulative.partition_point(|&c| c <= target).clamp(1, breaks.len() - 1) - 1;
                let (mut lo, mut hi) = (breaks[piece], breaks[piece + 1]);
                let rest = target - cumulative[piece];
                for _ in 0..60 {
                    let mid = (lo + hi) / 2.0;
                    if speed_integral(&velocity, breaks[piece], mid) < rest {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                (lo + hi) / 2.0
            })
            .collect()
    }

    /// Breakpoints for quadrature between `a` and `b`: the knots, each knot interval cut into
    /// [`PIECES_PER_INTERVAL`] equal pieces, because the speed can dip steeply inside one.
    fn pieces(&self, a: f64, b: f64) -> Vec<f64> {
        let mut knots: Vec<f64> = self.knots.iter().copied().filter(|&t| t > a && t < b).collect();
        knots.insert(0, a);
        knots.push(b);
        let mut breaks = vec![a];
        for w in knots.windows(2) {
            let step = (w[1] - w[0]) / PIECES_PER_INTERVAL as f64;
            breaks.extend((1..PIECES_PER_INTERVAL).map(|i| w[0] + step * i as f64));
            breaks.push(w[1]);
        }
        breaks
    }
}

/// Quadrature pieces per knot interval.
const PIECES_PER_INTERVAL: usize = 32;

/// ∫ |velocity(x)| dx over [a, b] by 8-point Gauss–Legendre.
fn speed_integral(velocity: &BSplineCurve, a: f64, b: f64) -> f64 {
    gauss_legendre(a, b, |x| velocity.point(x).norm())
}

/// Nodes and weights of 8-point Gauss–Legendre quadrature on [-1, 1].
// The published 8-point Gauss–Legendre table, digits as printed (they round to these f64s).
#[allow(clippy::excessive_precision)]
const GAUSS_8: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (-0.525_532_409_916_329_0, 0.313_706_645_877_887_3),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362_0),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362_0),
    (0.525_532_409_916_329_0, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
];

fn gauss_legendre(a: f64, b: f64, f: impl Fn(f64) -> f64) -> f64 {
    let (mid, half) = ((a + b) / 2.0, (b - a) / 2.0);
    half * GAUSS_8.iter().map(|(x, w)| w * f(mid + half * x)).sum::<f64>()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Clamped cubic Bézier segment as a B-spline: knots 0,0,0,0,1,1,1,1.
    fn bezier() -> BSplineCurve {
        BSplineCurve {
            knots: vec![0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0],
            coefficients: [vec![0.0, 1.0, 2.0, 3.0], vec![0.0, 2.0, 2.0, 0.0], vec![1.0, 1.0, 1.0, 1.0]],
            degree: 3,
        }
    }

    #[test]
    fn basis_functions_sum_to_one() {
        let t = [0.0, 0.1, 0.3, 0.35, 0.6, 0.8, 0.9, 1.4, 2.0];
        for x in [0.35, 0.4, 0.5, 0.59] {
            let h = basis(&t, 3, 3, x);
            assert!((h.iter().sum::<f64>() - 1.0).abs() < 1e-14);
            assert!(h.iter().all(|v| *v >= 0.0));
        }
    }

    #[test]
    fn bezier_points_and_derivative_match_bernstein_form() {
        let c = bezier();
        let u: f64 = 0.3;
        let b = [(1.0 - u).powi(3), 3.0 * u * (1.0 - u).powi(2), 3.0 * u * u * (1.0 - u), u.powi(3)];
        // y = 2 b1 + 2 b2 = 6 u (1 - u), so y' = 6 - 12 u.
        let y = 2.0 * b[1] + 2.0 * b[2];
        let p = c.point(u);
        assert!((p.x - 3.0 * u).abs() < 1e-14 && (p.y - y).abs() < 1e-14 && (p.z - 1.0).abs() < 1e-14);
        let dy = 6.0 - 12.0 * u;
        let d = c.derivative().point(u);
        assert!((d.x - 3.0).abs() < 1e-13 && (d.y - dy).abs() < 1e-13 && d.z.abs() < 1e-13);
    }

    #[test]
    fn arc_length_of_a_straight_segment_is_exact() {
        let mut c = bezier();
        c.coefficients[1] = vec![0.0, 0.0, 0.0, 0.0];
        assert!((c.arc_length(0.0, 1.0) - 3.0).abs() < 1e-13);
        assert!((c.arc_length(0.25, 0.75) - 1.5).abs() < 1e-13);
    }
}
