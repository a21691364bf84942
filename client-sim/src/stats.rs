//! Means, 95 % confidence intervals, Welch's t-test, and the paired t-test
//! over seeds: what the papers' error bars show (Burgard et al. 2005 Fig. 9,
//! Wurm et al. 2008 Fig. 5), and the right test for our runs, where a seed
//! gives every policy the same world and start.

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

/// A sample of one figure, each value with the seed of its run when known.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    values: Vec<f64>,
    seeds: Vec<Option<u64>>,
}

impl Sample {
    /// A sample of these values.
    pub fn new(values: Vec<f64>) -> Self {
        let seeds = vec![None; values.len()];
        Self { values, seeds }
    }

    /// A sample of (seed, value) pairs.
    pub fn seeded(pairs: Vec<(u64, f64)>) -> Self {
        let (seeds, values) = pairs.into_iter().map(|(s, v)| (Some(s), v)).unzip();
        Self { values, seeds }
    }

    /// Number of values.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Each value with the seed of its run, where known.
    pub fn seeded_values(&self) -> impl Iterator<Item = (Option<u64>, f64)> + '_ {
        self.seeds.iter().copied().zip(self.values.iter().copied())
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

/// The paired t-test of a − b over the seeds both samples hold (a seed
/// gives both the same world and start): the mean difference, its 95 %
/// confidence half-width, whether it is significant at 5 % (two-sided), and
/// the number of pairs. `None` with fewer than two pairs.
pub fn paired(a: &Sample, b: &Sample) -> Option<(f64, f64, bool, usize)> {
    let of = |s: &Sample| -> std::collections::BTreeMap<u64, f64> {
        s.seeds.iter().zip(&s.values).filter_map(|(seed, v)| Some(((*seed)?, *v))).collect()
    };
    let (a, b) = (of(a), of(b));
    let differences: Vec<f64> = a.iter().filter_map(|(seed, x)| Some(x - b.get(seed)?)).collect();
    let n = differences.len();
    if n < 2 {
        return None;
    }
    let d = Sample::new(differences);
    let half = d.ci95();
    Some((d.mean(), half, d.mean().abs() > half, n))
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

    #[test]
    fn pairing_by_seed_sees_a_shift_that_spread_hides() {
        // Seeds differ a lot between themselves; one policy is always 2 better.
        let base: Vec<(u64, f64)> = (0..10).map(|s| (s, 100.0 + 40.0 * (s % 4) as f64)).collect();
        let better: Vec<(u64, f64)> = base.iter().map(|&(s, v)| (s, v - 2.0 - 0.1 * (s % 2) as f64)).collect();
        let (a, b) = (Sample::seeded(better), Sample::seeded(base));
        assert!(!welch(&a, &b).2, "between seeds the spread swamps 2 steps");
        let (difference, _, significant, n) = paired(&a, &b).unwrap();
        assert!((difference + 2.05).abs() < 1e-9);
        assert!(significant);
        assert_eq!(n, 10);
        assert!(paired(&Sample::new(vec![1.0, 2.0]), &Sample::new(vec![1.0, 2.0])).is_none(), "no seeds, no pairs");
    }
}
