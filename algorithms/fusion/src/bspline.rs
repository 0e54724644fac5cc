//! The local path of a segment as a cubic B-spline over time, with covariance (EQUATIONS §6.1,
//! \[3D\] eq 33-37, erratum §9).
//!
//! - Parameter: u = (t − t₀)/(tₙ − t₀) (eq 34); the data parameters ū_k are the samples' u.
//! - Knots: clamped, by averaging (Piegl & Tiller eq 9.8), see [`clamped_knots`]; degree min(3, n−1).
//! - Basis: Cox–de Boor (eq 35-36, 0/0 := 0), see [`basis`].
//! - Curve: GLOBAL INTERPOLATION (Piegl & Tiller §9.2.1). Eq 33 uses the data points themselves as
//!   control points, S(u) = Σ p_v(i)·N_{i,3}(u); that curve only approximates the path (it cuts the
//!   corners, erratum §9). Here the control points P_i solve A·P = Q with A_{ki} = N_{i,p}(ū_k) and
//!   Q_k the samples, so S(ū_k) = Q_k exactly, and any polynomial path of degree ≤ p in t is
//!   reproduced. A is banded (at most p+1 nonzeros per row, bandwidths found from the spans) and
//!   totally positive, so Gaussian elimination without pivoting is stable (de Boor 1978, P&T §9.2.1):
//!   `fit` factors it once in O(n).
//! - Covariance: eq 37 corrected is P(u) = Σ N_i(u)²·P_i for independent CONTROL points P_i. With
//!   interpolation the curve is a linear combination of the DATA samples, S(u) = Σ_k w_k(u)·Q_k with
//!   wᵀ = N(u)ᵀ·A⁻¹ (the weights sum to 1, w_k(ū_j) = δ_kj), so treating the samples as independent
//!   the covariance is P(u) = Σ_k w_k(u)²·P_k. At a sample time it is that sample's covariance; in
//!   between it is a blend of the neighbours, typically smaller (Σw² ≈ 0.64 half-way between evenly
//!   spaced samples). Correlations between consecutive
//!   SLAM poses are ignored (they are not available per sample); with fully correlated neighbours
//!   the true value would be larger, up to (Σ|w_k|·σ_k)².
//! - Cost of the weights: w = A⁻ᵀ·N(u) is dense in principle but decays geometrically away from u
//!   (by ≈ 2 − √3 ≈ 0.27 per sample for evenly spaced cubic data). [`LocalPathSpline::evaluate`]
//!   solves Uᵀ·y = N(u) forward and Lᵀ·w = y backward with the stored banded LU factors, starting at
//!   the p+1 nonzeros of N(u) and stopping once the last band-width entries fall below
//!   [`WEIGHT_TOLERANCE`] of the largest (at most [`MAX_WEIGHT_REACH`] samples either side). That is
//!   O(log n) for the span search plus O(p²) for the basis plus O(W) for the W samples whose weight
//!   matters (≈ 25 for even spacing; bounded by the reach), independent of n. The dropped tail
//!   contributes below 1e-20 relative to the covariance.

use nalgebra::{Matrix3, Vector3};

use crate::FusionError;
use crate::fuse::{check_covariance, symmetrise};

/// Relative size below which covariance weights w_k(u) are dropped (their square is < 1e-24).
pub const WEIGHT_TOLERANCE: f64 = 1e-12;
/// Largest number of samples on either side of a query whose covariance weight is computed.
pub const MAX_WEIGHT_REACH: usize = 256;

/// One sample of a local path: time, position and covariance in the segment's local frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathSample {
    /// Time, s (the pipeline's shared clock).
    pub t_s: f64,
    /// Position in the local frame, m.
    pub position_m: Vector3<f64>,
    /// Position covariance, m² (full symmetric 3×3, positive semi-definite).
    pub covariance_m2: Matrix3<f64>,
}

/// A banded n×n matrix, row-major band storage: row r holds columns r−kl ..= r+ku.
#[derive(Debug, Clone)]
struct Band {
    n: usize,
    kl: usize,
    ku: usize,
    a: Vec<f64>,
}

impl Band {
    fn zeros(n: usize, kl: usize, ku: usize) -> Self {
        Self { n, kl, ku, a: vec![0.0; n * (kl + ku + 1)] }
    }
    /// Index of (r, c); the caller keeps c within r−kl ..= r+ku.
    fn idx(&self, r: usize, c: usize) -> usize {
        r * (self.kl + self.ku + 1) + (c + self.kl - r)
    }
    fn get(&self, r: usize, c: usize) -> f64 {
        self.a[self.idx(r, c)]
    }
    fn set(&mut self, r: usize, c: usize, v: f64) {
        let i = self.idx(r, c);
        self.a[i] = v;
    }

    /// In-place LU without pivoting (Doolittle: L unit lower, stored below the diagonal; U on and above).
    fn factor(&mut self) -> Result<(), FusionError> {
        for k in 0..self.n {
            let pivot = self.get(k, k);
            if pivot.is_nan() || pivot.abs() <= 1e-14 {
                return Err(FusionError::Singular("B-spline interpolation matrix"));
            }
            for i in k + 1..=(k + self.kl).min(self.n - 1) {
                let l = self.get(i, k) / pivot;
                self.set(i, k, l);
                if l != 0.0 {
                    for j in k + 1..=(k + self.ku).min(self.n - 1) {
                        let v = self.get(i, j) - l * self.get(k, j);
                        self.set(i, j, v);
                    }
                }
            }
        }
        Ok(())
    }

    /// Solves A·x = b with the factors, in place.
    fn solve(&self, b: &mut [Vector3<f64>]) {
        for i in 0..self.n {
            let mut s = b[i];
            for (k, bk) in b.iter().enumerate().take(i).skip(i.saturating_sub(self.kl)) {
                s -= bk * self.get(i, k);
            }
            b[i] = s;
        }
        for i in (0..self.n).rev() {
            let mut s = b[i];
            for (j, bj) in b.iter().enumerate().take((i + self.ku).min(self.n - 1) + 1).skip(i + 1) {
                s -= bj * self.get(i, j);
            }
            b[i] = s / self.get(i, i);
        }
    }
}

/// The cubic (or lower degree for 2-3 samples) B-spline interpolating a segment's local path over
/// time, with the covariance of the interpolated position. See the module docs.
#[derive(Debug, Clone)]
pub struct LocalPathSpline {
    t0_s: f64,
    t1_s: f64,
    degree: usize,
    knots: Vec<f64>,
    control_m: Vec<Vector3<f64>>,
    sample_cov_m2: Vec<Matrix3<f64>>,
    /// LU factors of the interpolation matrix, for the covariance weights.
    lu: Band,
}

impl LocalPathSpline {
    /// Fits through the samples (times strictly increasing, ≥ 2; degree min(3, n−1)) by global
    /// interpolation, in O(n).
    ///
    /// Errors: fewer than 2 samples ([`FusionError::TooFew`]); a non-finite time, position or
    /// covariance ([`FusionError::NonFinite`]); times not strictly increasing
    /// ([`FusionError::TimesNotIncreasing`]); a covariance that is not symmetric positive
    /// semi-definite ([`FusionError::NotPositiveDefinite`]).
    pub fn fit(samples: &[PathSample]) -> Result<Self, FusionError> {
        let count = samples.len();
        if count < 2 {
            return Err(FusionError::TooFew { what: "path samples", got: count, need: 2 });
        }
        let mut sample_cov_m2 = Vec::with_capacity(count);
        for (k, s) in samples.iter().enumerate() {
            if !s.t_s.is_finite() {
                return Err(FusionError::NonFinite("sample time"));
            }
            if !s.position_m.iter().all(|v| v.is_finite()) {
                return Err(FusionError::NonFinite("sample position"));
            }
            if k > 0 && s.t_s <= samples[k - 1].t_s {
                return Err(FusionError::TimesNotIncreasing { index: k });
            }
            sample_cov_m2.push(check_covariance("sample covariance", &s.covariance_m2)?);
        }
        let t0_s = samples[0].t_s;
        let t1_s = samples[count - 1].t_s;
        let span = t1_s - t0_s;
        if !(span.is_finite() && span > 0.0) {
            return Err(FusionError::NonFinite("time span"));
        }
        // eq 34; the last is exactly 1.
        let mut params: Vec<f64> = samples.iter().map(|s| (s.t_s - t0_s) / span).collect();
        params[count - 1] = 1.0;
        for k in 1..count {
            if params[k] <= params[k - 1] {
                // Times so close that their parameters round together.
                return Err(FusionError::TimesNotIncreasing { index: k });
            }
        }
        let degree = 3.min(count - 1);
        let knots = clamped_knots(&params, degree);
        // Rows of the interpolation matrix: row k has N_{s−p..=s, p}(ū_k) in columns s−p ..= s.
        let mut rows = Vec::with_capacity(count);
        let (mut kl, mut ku) = (0usize, 0usize);
        for (k, &u) in params.iter().enumerate() {
            let s = find_span(&knots, degree, count, u);
            let first = s - degree;
            let n = basis_funs(&knots, s, degree, u);
            // Only the nonzero entries widen the band.
            let nz: Vec<usize> = (0..=degree).filter(|&j| n[j] != 0.0).map(|j| first + j).collect();
            if let (Some(&lo), Some(&hi)) = (nz.first(), nz.last()) {
                kl = kl.max(k.saturating_sub(lo));
                ku = ku.max(hi.saturating_sub(k));
            }
            rows.push((first, n));
        }
        let mut lu = Band::zeros(count, kl, ku);
        for (k, (first, n)) in rows.iter().enumerate() {
            for (j, &v) in n.iter().enumerate().take(degree + 1) {
                if v != 0.0 {
                    lu.set(k, first + j, v);
                }
            }
        }
        lu.factor()?;
        let mut control_m: Vec<Vector3<f64>> = samples.iter().map(|s| s.position_m).collect();
        lu.solve(&mut control_m);
        if !control_m.iter().all(|c| c.iter().all(|v| v.is_finite())) {
            return Err(FusionError::Singular("B-spline control points"));
        }
        Ok(Self { t0_s, t1_s, degree, knots, control_m, sample_cov_m2, lu })
    }

    /// The time range covered, s: (first sample, last sample).
    pub fn t_range_s(&self) -> (f64, f64) {
        (self.t0_s, self.t1_s)
    }

    /// Degree of the spline: min(3, samples − 1).
    pub fn degree(&self) -> usize {
        self.degree
    }

    /// The knot vector (clamped, in u ∈ [0, 1]).
    pub fn knots(&self) -> &[f64] {
        &self.knots
    }

    /// The control points found by the interpolation, m (local frame).
    pub fn control_points_m(&self) -> &[Vector3<f64>] {
        &self.control_m
    }

    /// u of a time, with its span; error outside the range.
    fn locate(&self, t_s: f64) -> Result<(f64, usize), FusionError> {
        if !t_s.is_finite() {
            return Err(FusionError::NonFinite("query time"));
        }
        if t_s < self.t0_s || t_s > self.t1_s {
            return Err(FusionError::OutOfRange { t_s, from_s: self.t0_s, to_s: self.t1_s });
        }
        let u = ((t_s - self.t0_s) / (self.t1_s - self.t0_s)).clamp(0.0, 1.0);
        Ok((u, find_span(&self.knots, self.degree, self.control_m.len(), u)))
    }

    /// Position at t, m (local frame): O(log n + p²). Error outside the range or for a non-finite t.
    pub fn evaluate_position(&self, t_s: f64) -> Result<Vector3<f64>, FusionError> {
        let (u, s) = self.locate(t_s)?;
        let n = basis_funs(&self.knots, s, self.degree, u);
        Ok((0..=self.degree).map(|j| self.control_m[s - self.degree + j] * n[j]).sum())
    }

    /// Position (m) and covariance (m², symmetric PSD) at t. Error outside the range or for a
    /// non-finite t. The covariance is Σ_k w_k(u)²·P_k over the data samples (module docs), computed
    /// in O(log n + p² + W) with W the samples whose weight exceeds [`WEIGHT_TOLERANCE`].
    pub fn evaluate(&self, t_s: f64) -> Result<(Vector3<f64>, Matrix3<f64>), FusionError> {
        let (u, s) = self.locate(t_s)?;
        let p = self.degree;
        let n = basis_funs(&self.knots, s, p, u);
        let first = s - p;
        let position: Vector3<f64> = (0..=p).map(|j| self.control_m[first + j] * n[j]).sum();
        let (w_first, w) = self.sample_weights(first, &n[..=p]);
        let mut cov = Matrix3::zeros();
        for (k, wk) in w.iter().enumerate() {
            if *wk != 0.0 {
                cov += self.sample_cov_m2[w_first + k] * (wk * wk);
            }
        }
        Ok((position, symmetrise(&cov)))
    }

    /// The weights w_k of the data samples in S(u) = Σ_k w_k·Q_k, given the nonzero basis values
    /// `nb` (columns `first` ..): w = A⁻ᵀ·N = L⁻ᵀ·U⁻ᵀ·N, truncated (module docs). Returns the index
    /// of the first returned weight and the weights.
    fn sample_weights(&self, first: usize, nb: &[f64]) -> (usize, Vec<f64>) {
        let lu = &self.lu;
        let n = lu.n;
        let last_nb = first + nb.len() - 1;
        // Forward: Uᵀ·y = N, y_j = (N_j − Σ_{l=j−ku}^{j−1} U_{lj}·y_l)/U_jj, y_j = 0 for j < first.
        let mut y: Vec<f64> = Vec::with_capacity(nb.len() + 32);
        let mut y_max = 0.0_f64;
        let mut j = first;
        while j < n {
            let mut v = if j <= last_nb { nb[j - first] } else { 0.0 };
            for l in j.saturating_sub(lu.ku).max(first)..j {
                v -= lu.get(l, j) * y[l - first];
            }
            v /= lu.get(j, j);
            y.push(v);
            y_max = y_max.max(v.abs());
            if j >= last_nb {
                let tail = &y[y.len().saturating_sub(lu.ku.max(1))..];
                if tail.iter().all(|t| t.abs() <= WEIGHT_TOLERANCE * y_max) || j >= last_nb + MAX_WEIGHT_REACH {
                    break;
                }
            }
            j += 1;
        }
        let y_end = first + y.len() - 1; // last index kept
        // Backward: Lᵀ·w = y, w_j = y_j − Σ_{l=j+1}^{j+kl} L_{lj}·w_l, over j = y_end down.
        let mut w_rev: Vec<f64> = Vec::with_capacity(y.len() + 32);
        let mut w_max = 0.0_f64;
        let mut j = y_end as isize;
        while j >= 0 {
            let ju = j as usize;
            let mut v = if ju >= first { y[ju - first] } else { 0.0 };
            for l in ju + 1..=(ju + lu.kl).min(y_end) {
                v -= lu.get(l, ju) * w_rev[y_end - l];
            }
            w_rev.push(v);
            w_max = w_max.max(v.abs());
            if ju <= first {
                let tail = &w_rev[w_rev.len().saturating_sub(lu.kl.max(1))..];
                if tail.iter().all(|t| t.abs() <= WEIGHT_TOLERANCE * w_max) || ju + MAX_WEIGHT_REACH <= first {
                    break;
                }
            }
            j -= 1;
        }
        let w_first = y_end + 1 - w_rev.len();
        w_rev.reverse();
        (w_first, w_rev)
    }

    /// The weights w_k(u) at time t of the data samples in S(u) = Σ_k w_k·Q_k, as (index of the
    /// first sample, weights); samples outside the returned window have |w| below the tolerance.
    pub fn sample_weights_at(&self, t_s: f64) -> Result<(usize, Vec<f64>), FusionError> {
        let (u, s) = self.locate(t_s)?;
        let n = basis_funs(&self.knots, s, self.degree, u);
        Ok(self.sample_weights(s - self.degree, &n[..=self.degree]))
    }
}

/// Cox–de Boor basis N_{i,p}(u) on a knot vector (eq 35-36, 0/0 := 0), public for tests. The last
/// nonempty knot interval is closed on the right, so the basis is a partition of unity on the whole
/// clamped range including its end. 0 for an index or degree the knot vector does not hold.
pub fn basis(knots: &[f64], i: usize, p: usize, u: f64) -> f64 {
    if i + p + 1 >= knots.len() || u.is_nan() {
        return 0.0;
    }
    if p == 0 {
        let (a, b) = (knots[i], knots[i + 1]);
        if a <= u && u < b {
            return 1.0;
        }
        // Closed on the right for the last nonempty interval: u equals the last knot.
        let last = knots[knots.len() - 1];
        if u == last && b == last && a < b {
            return 1.0;
        }
        return 0.0;
    }
    let ratio = |num: f64, den: f64| if den == 0.0 { 0.0 } else { num / den };
    let left = ratio(u - knots[i], knots[i + p] - knots[i]);
    let right = ratio(knots[i + p + 1] - u, knots[i + p + 1] - knots[i + 1]);
    let mut value = 0.0;
    if left != 0.0 {
        value += left * basis(knots, i, p - 1, u);
    }
    if right != 0.0 {
        value += right * basis(knots, i + 1, p - 1, u);
    }
    value
}

/// Clamped knot vector for parameters ū_0 < … < ū_n (averaging, Piegl & Tiller eq 9.8): p+1 copies
/// of ū_0, the interior knots u_{j+p} = (1/p)·Σ_{i=j}^{j+p−1} ū_i for j = 1 … n−p, p+1 copies of ū_n;
/// n+p+2 knots. Empty when `degree` is 0 or not below the number of parameters.
pub fn clamped_knots(params: &[f64], degree: usize) -> Vec<f64> {
    let count = params.len();
    if degree == 0 || degree >= count {
        return Vec::new();
    }
    let n = count - 1;
    let p = degree;
    let mut knots = Vec::with_capacity(n + p + 2);
    knots.extend(std::iter::repeat_n(params[0], p + 1));
    // Sliding sum over ū_j .. ū_{j+p−1}.
    let mut sum: f64 = params[1..p].iter().sum();
    for j in 1..=n.saturating_sub(p) {
        sum += params[j + p - 1];
        knots.push(sum / p as f64);
        sum -= params[j];
    }
    knots.extend(std::iter::repeat_n(params[n], p + 1));
    knots
}

/// The knot span s ∈ [p, n_ctrl−1] with u_s ≤ u < u_{s+1} (the last span at the right end), by
/// bisection (Piegl & Tiller A2.1). `n_ctrl` is the number of control points.
fn find_span(knots: &[f64], p: usize, n_ctrl: usize, u: f64) -> usize {
    let n = n_ctrl - 1;
    if u >= knots[n + 1] {
        return n;
    }
    if u <= knots[p] {
        return p;
    }
    let (mut lo, mut hi) = (p, n + 1);
    while hi - lo > 1 {
        let mid = (lo + hi) / 2;
        if u < knots[mid] {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    lo
}

/// The p+1 nonzero basis values N_{s−p..=s, p}(u) on span s (Piegl & Tiller A2.2), in the first
/// p+1 entries.
fn basis_funs(knots: &[f64], s: usize, p: usize, u: f64) -> [f64; 4] {
    let mut n = [0.0; 4];
    let mut left = [0.0; 4];
    let mut right = [0.0; 4];
    n[0] = 1.0;
    for j in 1..=p {
        left[j] = u - knots[s + 1 - j];
        right[j] = knots[s + j] - u;
        let mut saved = 0.0;
        for r in 0..j {
            let den = right[r + 1] + left[j - r];
            let temp = if den == 0.0 { 0.0 } else { n[r] / den };
            n[r] = saved + right[r + 1] * temp;
            saved = left[j - r] * temp;
        }
        n[j] = saved;
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector, SymmetricEigen};
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal, Uniform};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn random_cov(rng: &mut Xoshiro256PlusPlus, scale: f64) -> Matrix3<f64> {
        let n = Normal::new(0.0, 1.0).unwrap();
        let a = Matrix3::from_fn(|_, _| n.sample(rng));
        (a * a.transpose() + Matrix3::identity() * 0.1) * scale
    }

    /// Irregular increasing times, a wiggly path and random covariances.
    fn random_samples(count: usize, seed: u64) -> Vec<PathSample> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let dt = Uniform::new(0.02, 0.2).unwrap();
        let mut t = 100.0;
        (0..count)
            .map(|_| {
                t += dt.sample(&mut rng);
                PathSample {
                    t_s: t,
                    position_m: Vector3::new(t.sin() * 3.0, (0.7 * t).cos() * 2.0, 0.1 * t),
                    covariance_m2: random_cov(&mut rng, 0.01),
                }
            })
            .collect()
    }

    fn samples_of(times: &[f64], f: impl Fn(f64) -> Vector3<f64>) -> Vec<PathSample> {
        times
            .iter()
            .map(|&t| PathSample { t_s: t, position_m: f(t), covariance_m2: Matrix3::identity() * 0.01 })
            .collect()
    }

    proptest! {
        #[test]
        fn the_basis_is_a_partition_of_unity_over_the_whole_range(
            gaps in proptest::collection::vec(1e-3..10.0f64, 1..30),
            degree in 1usize..=3,
            frac in 0.0..=1.0f64,
        ) {
            let mut params = vec![0.0];
            for g in &gaps {
                params.push(params.last().unwrap() + g);
            }
            let last = *params.last().unwrap();
            for p in params.iter_mut() {
                *p /= last;
            }
            let degree = degree.min(params.len() - 1);
            let knots = clamped_knots(&params, degree);
            prop_assert_eq!(knots.len(), params.len() + degree + 1);
            prop_assert!(knots.windows(2).all(|w| w[0] <= w[1]), "knots not sorted: {:?}", knots);
            let n_ctrl = params.len();
            for u in [frac, 0.0, 1.0, params[params.len() / 2]] {
                let values: Vec<f64> = (0..n_ctrl).map(|i| basis(&knots, i, degree, u)).collect();
                prop_assert!(values.iter().all(|v| *v >= -1e-15), "negative basis {:?}", values);
                let sum: f64 = values.iter().sum();
                prop_assert!((sum - 1.0).abs() < 1e-12, "Σ N = {} at u = {}", sum, u);
                // The fast evaluation agrees with the recursion.
                let s = find_span(&knots, degree, n_ctrl, u);
                let fast = basis_funs(&knots, s, degree, u);
                for j in 0..=degree {
                    prop_assert!((fast[j] - values[s - degree + j]).abs() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn the_basis_and_knots_match_a_hand_computed_case() {
        // Piegl & Tiller Ex 9.1-like: params 0, 1/4, 1/2, 1 (4 points), cubic → knots 0,0,0,0,1,1,1,1.
        assert_eq!(clamped_knots(&[0.0, 0.25, 0.5, 1.0], 3), vec![0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0]);
        // 5 points, cubic: one interior knot (ū1+ū2+ū3)/3.
        let k = clamped_knots(&[0.0, 0.1, 0.4, 0.7, 1.0], 3);
        assert_eq!(k.len(), 9);
        assert!((k[4] - 0.4).abs() < 1e-15);
        // Bézier cubic on [0,0,0,0,1,1,1,1]: N_1,3(u) = 3u(1−u)².
        let bez = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0];
        assert!((basis(&bez, 1, 3, 0.3) - 3.0 * 0.3 * 0.49).abs() < 1e-15);
        assert_eq!(basis(&bez, 3, 3, 1.0), 1.0);
        assert_eq!(basis(&bez, 0, 3, 0.0), 1.0);
        assert_eq!(basis(&bez, 7, 3, 0.5), 0.0); // index beyond the knot vector: 0, no panic
        assert!(clamped_knots(&[0.0, 1.0], 2).is_empty());
        assert!(clamped_knots(&[0.0, 1.0], 0).is_empty());
    }

    #[test]
    fn the_clamped_ends_and_every_sample_are_interpolated() {
        for count in [2, 3, 4, 5, 7, 50, 333] {
            let samples = random_samples(count, count as u64);
            let spline = LocalPathSpline::fit(&samples).unwrap();
            assert_eq!(spline.degree(), 3.min(count - 1));
            assert_eq!(spline.t_range_s(), (samples[0].t_s, samples[count - 1].t_s));
            let start = spline.evaluate_position(samples[0].t_s).unwrap();
            let end = spline.evaluate_position(samples[count - 1].t_s).unwrap();
            assert!((start - samples[0].position_m).norm() < 1e-12);
            assert!((end - samples[count - 1].position_m).norm() < 1e-12);
            // The clamped ends: the first and last control points are the end samples.
            assert!((spline.control_points_m()[0] - samples[0].position_m).norm() < 1e-12);
            for s in &samples {
                let (p, _) = spline.evaluate(s.t_s).unwrap();
                assert!((p - s.position_m).norm() < 1e-9, "n = {count}: {p} vs {}", s.position_m);
            }
        }
    }

    #[test]
    fn interpolation_differs_from_eq_33_with_the_samples_as_control_points() {
        // The erratum: Σ Q_i N_i(u) misses the samples; the interpolating curve does not.
        let samples = random_samples(20, 9);
        let spline = LocalPathSpline::fit(&samples).unwrap();
        let knots = spline.knots().to_vec();
        let (t0, t1) = spline.t_range_s();
        let s = &samples[10];
        let u = (s.t_s - t0) / (t1 - t0);
        let approx: Vector3<f64> = samples.iter().enumerate().map(|(i, q)| q.position_m * basis(&knots, i, 3, u)).sum();
        assert!((approx - s.position_m).norm() > 1e-3);
        assert!((spline.evaluate_position(s.t_s).unwrap() - s.position_m).norm() < 1e-9);
    }

    #[test]
    fn a_straight_line_and_a_quadratic_in_t_are_reproduced() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
        let dt = Uniform::new(0.01, 1.0).unwrap();
        let mut times = vec![5.0];
        for _ in 0..40 {
            let t = times.last().unwrap() + dt.sample(&mut rng);
            times.push(t);
        }
        let line = |t: f64| Vector3::new(1.0 + 2.0 * t, -3.0 + 0.5 * t, 0.25 * t);
        let quad = |t: f64| Vector3::new(0.3 * t * t - t, 2.0 - 0.1 * t * t, 1.0 + t + 0.02 * t * t);
        for (f, count) in [(&line as &dyn Fn(f64) -> Vector3<f64>, 2usize), (&line, 41), (&quad, 3), (&quad, 41)] {
            let spline = LocalPathSpline::fit(&samples_of(&times[..count], f)).unwrap();
            let (a, b) = spline.t_range_s();
            for k in 0..=200 {
                let t = a + (b - a) * k as f64 / 200.0;
                let p = spline.evaluate_position(t).unwrap();
                assert!((p - f(t)).norm() < 1e-9 * (1.0 + f(t).norm()), "n = {count}, t = {t}: {p} vs {}", f(t));
            }
        }
    }

    #[test]
    fn the_covariance_equals_the_sample_covariance_at_sample_times_and_is_symmetric_psd() {
        let samples = random_samples(200, 17);
        let spline = LocalPathSpline::fit(&samples).unwrap();
        for s in &samples {
            let (_, c) = spline.evaluate(s.t_s).unwrap();
            assert!((c - s.covariance_m2).amax() < 1e-9 * s.covariance_m2.amax(), "{c} vs {}", s.covariance_m2);
        }
        let (a, b) = spline.t_range_s();
        for k in 0..=1000 {
            let t = a + (b - a) * k as f64 / 1000.0;
            let (_, c) = spline.evaluate(t).unwrap();
            assert_eq!(c, c.transpose());
            assert!(SymmetricEigen::new(c).eigenvalues.min() > 0.0);
            let (_, w) = spline.sample_weights_at(t).unwrap();
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-9, "weights sum to {}", w.iter().sum::<f64>());
        }
    }

    #[test]
    fn the_truncated_covariance_weights_match_a_dense_inverse() {
        for count in [2, 3, 4, 5, 6, 60] {
            let samples = random_samples(count, 23 + count as u64);
            let spline = LocalPathSpline::fit(&samples).unwrap();
            let p = spline.degree();
            let (t0, t1) = spline.t_range_s();
            let params: Vec<f64> = samples.iter().map(|s| (s.t_s - t0) / (t1 - t0)).collect();
            let knots = spline.knots().to_vec();
            let a = DMatrix::from_fn(count, count, |k, i| basis(&knots, i, p, params[k]));
            let a_inv = a.try_inverse().unwrap();
            for frac in [0.0, 0.013, 0.25, 0.5, 0.77, 0.999, 1.0] {
                let t = t0 + (t1 - t0) * frac;
                let u = (t - t0) / (t1 - t0);
                let nu = DVector::from_fn(count, |i, _| basis(&knots, i, p, u));
                let w_dense = a_inv.transpose() * nu;
                let (first, w) = spline.sample_weights_at(t).unwrap();
                for k in 0..count {
                    let wk = if k >= first && k < first + w.len() { w[k - first] } else { 0.0 };
                    assert!(
                        (wk - w_dense[k]).abs() < 1e-10,
                        "n {count}, t fraction {frac}, sample {k}: {wk} vs {}",
                        w_dense[k]
                    );
                }
                let cov_dense: Matrix3<f64> = (0..count).map(|k| samples[k].covariance_m2 * w_dense[k].powi(2)).sum();
                let (_, c) = spline.evaluate(t).unwrap();
                assert!((c - cov_dense).amax() < 1e-12, "{c} vs {cov_dense}");
                assert!(w.len() < 80, "{} weights", w.len());
            }
        }
        // Two samples: linear interpolation, at the middle w = (½, ½) and P = (P₀ + P₁)/4.
        let two = random_samples(2, 1);
        let spline = LocalPathSpline::fit(&two).unwrap();
        let (_, c) = spline.evaluate(0.5 * (two[0].t_s + two[1].t_s)).unwrap();
        assert!((c - (two[0].covariance_m2 + two[1].covariance_m2) * 0.25).amax() < 1e-15);
    }

    #[test]
    fn ten_thousand_samples_fit_and_evaluate_quickly() {
        let samples = random_samples(10_000, 1);
        let start = std::time::Instant::now();
        let spline = LocalPathSpline::fit(&samples).unwrap();
        let fit = start.elapsed();
        let (a, b) = spline.t_range_s();
        let start = std::time::Instant::now();
        let mut max_window = 0;
        for k in 0..10_000 {
            let t = a + (b - a) * k as f64 / 9_999.0;
            spline.evaluate(t).unwrap();
            max_window = max_window.max(spline.sample_weights_at(t).unwrap().1.len());
        }
        println!(
            "10 000 samples: fit {fit:?}, 10 000 evaluations {:?}, widest weight window {max_window}",
            start.elapsed()
        );
        assert!(max_window < 100);
        assert!((spline.evaluate_position(samples[5000].t_s).unwrap() - samples[5000].position_m).norm() < 1e-9);
    }

    #[test]
    fn bad_input_is_an_error() {
        let good = random_samples(5, 2);
        assert_eq!(
            LocalPathSpline::fit(&good[..1]).unwrap_err(),
            FusionError::TooFew { what: "path samples", got: 1, need: 2 }
        );
        assert!(matches!(LocalPathSpline::fit(&[]), Err(FusionError::TooFew { got: 0, .. })));
        let mut s = good.clone();
        s[2].position_m.y = f64::NAN;
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::NonFinite("sample position"));
        let mut s = good.clone();
        s[3].t_s = f64::NAN;
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::NonFinite("sample time"));
        let mut s = good.clone();
        s[3].t_s = s[2].t_s;
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::TimesNotIncreasing { index: 3 });
        let mut s = good.clone();
        s.swap(1, 2);
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::TimesNotIncreasing { index: 2 });
        let mut s = good.clone();
        s[0].covariance_m2[(0, 0)] = -1.0;
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::NotPositiveDefinite("sample covariance"));
        let mut s = good.clone();
        s[4].covariance_m2[(0, 1)] = f64::INFINITY;
        assert_eq!(LocalPathSpline::fit(&s).unwrap_err(), FusionError::NonFinite("sample covariance"));
        let spline = LocalPathSpline::fit(&good).unwrap();
        let (a, b) = spline.t_range_s();
        assert!(matches!(spline.evaluate(a - 1e-6), Err(FusionError::OutOfRange { .. })));
        assert!(matches!(spline.evaluate(b + 1.0), Err(FusionError::OutOfRange { .. })));
        assert_eq!(spline.evaluate(f64::NAN).unwrap_err(), FusionError::NonFinite("query time"));
    }
}
