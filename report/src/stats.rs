//! Monte Carlo statistics of one quantity over seeds: mean, sample standard
//! deviation and the 95 % confidence interval of the mean from Student's t
//! distribution.

use serde::Serialize;

/// Mean, spread and 95 % confidence interval of a sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stat {
    pub n: usize,
    pub mean: f64,
    /// Sample standard deviation (n − 1 in the denominator); 0 for n = 1.
    pub sd: f64,
    /// 95 % confidence interval of the mean, mean ∓ t₀.₉₇₅(n−1) sd/√n;
    /// (mean, mean) for n = 1.
    pub ci_low: f64,
    pub ci_high: f64,
    pub min: f64,
    pub max: f64,
}

impl Stat {
    /// The statistics of `values` (`None` when there are none).
    pub fn of(values: &[f64]) -> Option<Stat> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let (min, max) = values.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        // Identical values (a quantity the noise does not reach) would leave
        // rounding dust in the mean and spread: they are the value, spread 0.
        let mean = if max == min { min } else { values.iter().sum::<f64>() / n as f64 };
        if n == 1 {
            return Some(Stat { n, mean, sd: 0.0, ci_low: mean, ci_high: mean, min, max });
        }
        let var = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1) as f64;
        let sd = if max == min { 0.0 } else { var.sqrt() };
        let half = t_975(n - 1) * sd / (n as f64).sqrt();
        Some(Stat { n, mean, sd, ci_low: mean - half, ci_high: mean + half, min, max })
    }

    /// The same statistics with every number multiplied by `k` (k > 0).
    pub fn scaled(&self, k: f64) -> Stat {
        Stat {
            n: self.n,
            mean: self.mean * k,
            sd: self.sd * k,
            ci_low: self.ci_low * k,
            ci_high: self.ci_high * k,
            min: self.min * k,
            max: self.max * k,
        }
    }

    /// `mean` for one sample, `mean ± sd [low, high]` for several, each with
    /// `decimals` decimals.
    pub fn display(&self, decimals: usize) -> String {
        if self.n <= 1 {
            format!("{:.*}", decimals, self.mean)
        } else {
            format!("{:.d$} ± {:.d$} [{:.d$}, {:.d$}]", self.mean, self.sd, self.ci_low, self.ci_high, d = decimals)
        }
    }
}

/// Two-sided 95 % quantile t₀.₉₇₅ of Student's t with `df` degrees of freedom.
/// Tabulated for df ≤ 30 (4 decimals, standard tables); above, the
/// Cornish–Fisher expansion around z₀.₉₇₅ = 1.959964 (error < 1e-4 there).
pub fn t_975(df: usize) -> f64 {
    const TABLE: [f64; 30] = [
        12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281, 2.2010, 2.1788, 2.1604,
        2.1448, 2.1314, 2.1199, 2.1098, 2.1009, 2.0930, 2.0860, 2.0796, 2.0739, 2.0687, 2.0639, 2.0595, 2.0555, 2.0518,
        2.0484, 2.0452, 2.0423,
    ];
    match df {
        0 => f64::NAN,
        1..=30 => TABLE[df - 1],
        _ => cornish_fisher(df as f64),
    }
}

fn cornish_fisher(df: f64) -> f64 {
    let z = 1.959_963_985_f64;
    let z3 = z.powi(3);
    let z5 = z.powi(5);
    let z7 = z.powi(7);
    z + (z3 + z) / (4.0 * df)
        + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * df * df)
        + (3.0 * z7 + 19.0 * z5 + 17.0 * z3 - 15.0 * z) / (384.0 * df.powi(3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_sample_is_just_the_value() {
        let s = Stat::of(&[0.97]).unwrap();
        assert_eq!((s.mean, s.sd, s.ci_low, s.ci_high), (0.97, 0.0, 0.97, 0.97));
        assert_eq!(s.display(2), "0.97");
    }

    #[test]
    fn mean_sd_and_interval_of_a_known_sample() {
        // 1..=5: mean 3, sample sd √2.5; t₀.₉₇₅(4) = 2.7764 (tables).
        let s = Stat::of(&[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
        assert!((s.mean - 3.0).abs() < 1e-12);
        assert!((s.sd - 2.5_f64.sqrt()).abs() < 1e-12);
        let half = 2.7764 * 2.5_f64.sqrt() / 5.0_f64.sqrt();
        assert!((s.ci_high - 3.0 - half).abs() < 1e-12 && (3.0 - s.ci_low - half).abs() < 1e-12);
        assert_eq!((s.min, s.max), (1.0, 5.0));
    }

    #[test]
    fn expansion_continues_the_table() {
        // t₀.₉₇₅(30) = 2.0423, (40) = 2.0211, (60) = 2.0003, (120) = 1.9799 (tables).
        assert!((cornish_fisher(30.0) - 2.0423).abs() < 2e-4);
        for (df, t) in [(40, 2.0211), (60, 2.0003), (120, 1.9799)] {
            assert!((t_975(df) - t).abs() < 1e-4, "df {df}: {}", t_975(df));
        }
    }

    #[test]
    fn empty_sample_has_no_statistics() {
        assert!(Stat::of(&[]).is_none());
    }
}
