//! Means, 95 % confidence intervals and Welch's t-test: what the papers'
//! error bars show (Burgard et al. 2005 Fig. 9, Wurm et al. 2008 Fig. 5).

/// Two-sided 95 % quantiles of Student's t for 1 ..= 30 degrees of freedom.
const T975: [f64; 30] = [
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131, 2.120,
    2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
];

/// The 97.5 % quantile of Student's t with `df` degrees of freedom
/// (tabulated to 30; beyond, the normal quantile plus its first correction).
pub fn t975(df: f64) -> f64 {
    if df < 1.0 {
        return f64::INFINITY;
    }
    if df <= 30.0 {
        // Interpolate between table entries for fractional (Welch) df.
        let lo = df.floor() as usize;
        let hi = (lo + 1).min(30);
        let frac = df - lo as f64;
        return T975[lo - 1] * (1.0 - frac) + T975[hi - 1] * frac;
    }
    1.959_964 + 2.372 / df
}

/// A sample of one figure.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    values: Vec<f64>,
}

impl Sample {
    /// A sample of these values.
    pub fn new(values: Vec<f64>) -> Self {
        Self { values }
    }

    /// Number of values.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// The values.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Mean (NaN when empty).
    pub fn mean(&self) -> f64 {
        self.values.iter().sum::<f64>() / self.values.len() as f64
    }

    /// Sample variance (n − 1).
    pub fn variance(&self) -> f64 {
        let n = self.values.len();
        if n < 2 {
            return 0.0;
        }
        let m = self.mean();
        self.values.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1) as f64
    }

    /// Half-width of the 95 % confidence interval of the mean.
    pub fn ci95(&self) -> f64 {
        let n = self.values.len();
        if n < 2 {
            return 0.0;
        }
        t975((n - 1) as f64) * (self.variance() / n as f64).sqrt()
    }
}

/// Welch's t-test of mean(a) − mean(b): the difference, its 95 % confidence
/// half-width, and whether it is significant at 5 % (two-sided).
pub fn welch(a: &Sample, b: &Sample) -> (f64, f64, bool) {
    let (va, vb) = (a.variance() / a.len() as f64, b.variance() / b.len() as f64);
    let difference = a.mean() - b.mean();
    let se = (va + vb).sqrt();
    if se == 0.0 {
        return (difference, 0.0, difference != 0.0);
    }
    let df =
        (va + vb).powi(2) / (va * va / (a.len() as f64 - 1.0).max(1.0) + vb * vb / (b.len() as f64 - 1.0).max(1.0));
    let half = t975(df) * se;
    (difference, half, difference.abs() > half)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn confidence_intervals_match_textbook_values() {
        // Mean 5, sd 1, n = 10: half-width 2.262 · 1/√10.
        let s = Sample::new(vec![4.0, 6.0, 4.0, 6.0, 4.0, 6.0, 4.0, 6.0, 5.0, 5.0]);
        assert!((s.mean() - 5.0).abs() < 1e-12);
        let sd = s.variance().sqrt();
        assert!((s.ci95() - 2.262 * sd / 10f64.sqrt()).abs() < 1e-9);
        assert!((t975(1000.0) - 1.962).abs() < 0.01);
        assert!((t975(2.5) - (4.303 + 3.182) / 2.0).abs() < 1e-9);
    }

    #[test]
    fn welch_separates_clear_differences_only() {
        let a = Sample::new((0..20).map(|i| 100.0 + f64::from(i % 5)).collect());
        let b = Sample::new((0..20).map(|i| 110.0 + f64::from(i % 5)).collect());
        let (d, _, significant) = welch(&a, &b);
        assert!((d + 10.0).abs() < 1e-9);
        assert!(significant);
        let c = Sample::new((0..20).map(|i| 100.5 + f64::from(i % 5)).collect());
        assert!(!welch(&a, &c).2);
    }
}
