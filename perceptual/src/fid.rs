//! Gaussian feature statistics and the Fréchet distance of pytorch-fid.
//!
//! `pytorch_fid.fid_score` computes, for two sets of pool3 features,
//! `μ = mean(act, axis=0)`, `Σ = np.cov(act, rowvar=False)` (unbiased, divisor `n − 1`) and
//!
//! ```text
//! FID = ‖μ1 − μ2‖² + Tr(Σ1) + Tr(Σ2) − 2·Tr((Σ1 Σ2)^½)
//! ```
//!
//! with `scipy.linalg.sqrtm` of the non-symmetric product. Here the last trace is computed
//! from symmetric eigendecompositions instead: `Σ1 Σ2` is similar to
//! `M = Σ1^½ Σ2 Σ1^½` (`Σ1^½ (Σ1^½ Σ2 Σ1^½) Σ1^-½`, and by continuity also for singular
//! `Σ1`), which is symmetric positive semi-definite, so
//! `Tr((Σ1 Σ2)^½) = Σ_i √λ_i(M)`. `Σ1 = V diag(λ) Vᵀ` and the eigenvalues of
//! `M ~ D Vᵀ Σ2 V D` (`D = diag(√max(λ, 0))`, an orthogonal similarity) come from `nalgebra`'s
//! symmetric QR algorithm in f64.
//!
//! With no more images than dimensions (the usual case: a split has dozens, the features 2048)
//! the trace comes from the images' centred features instead: the non-zero eigenvalues of
//! `Σ1 Σ2` are the squared singular values of `X1 X2ᵀ / √((n1 − 1)(n2 − 1))`, an `n1 × n2`
//! matrix, which is exact and takes milliseconds where the `2048³` eigendecompositions take
//! tens of seconds on two cores.
//!
//! **eps handling vs pytorch-fid:** pytorch-fid calls `sqrtm(Σ1 Σ2)` and, only if the result
//! is not finite (a numerically singular product), retries with `1e-6` added to both
//! diagonals; it then drops an imaginary part if it is below `1e-3` on the diagonal and raises
//! otherwise. Here no offset is ever added: eigenvalues that round-off makes slightly negative
//! (in `Σ1` or in `M`) are clamped to 0, which is exact for rank-deficient covariances (fewer
//! images than 2048 dimensions), so the result is always finite and real. Where pytorch-fid
//! does not need its retry the two agree to round-off (relative ~1e-9 on well-conditioned
//! inputs; `sqrtm` of a singular product is itself only accurate to about `√ε·‖Σ‖`, so
//! rank-deficient cases agree to ~1e-6 relative). Where it does retry, its value includes the
//! `1e-6` offset, a bias of order `1e-6·√d` per side that we do not reproduce.

use nalgebra::{DMatrix, DVector, SymmetricEigen};

use super::PerceptualError;

/// Mean and unbiased covariance of a set of feature vectors (`np.mean(act, axis=0)`,
/// `np.cov(act, rowvar=False)`), in f64.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    /// Mean, `dim` values.
    pub mean: Vec<f64>,
    /// Covariance, `dim × dim`, row-major.
    pub cov: Vec<f64>,
    /// Feature dimension.
    pub dim: usize,
    /// Number of feature vectors the statistics were computed from.
    pub count: usize,
    /// The centred feature vectors (`count × dim`, row-major), kept when there are no more of
    /// them than dimensions: then `Σ = XᵀX / (count − 1)` has rank below `count` and
    /// [`frechet_distance`] works on the small `X₁X₂ᵀ` instead of `dim × dim` matrices.
    pub centred: Option<Vec<f64>>,
}

impl FeatureStats {
    /// Statistics of `rows`, row-major `count × dim` (`count = rows.len() / dim`), e.g.
    /// concatenated [`super::InceptionPool3::features`] outputs.
    ///
    /// Needs at least two rows (`np.cov` of one row divides by zero) and finite values.
    pub fn from_features(rows: &[f32], dim: usize) -> Result<Self, PerceptualError> {
        if dim == 0 {
            return Err(PerceptualError::Stats {
                field: "dim",
                reason: "must be at least 1".into(),
            });
        }
        if !rows.len().is_multiple_of(dim) {
            return Err(PerceptualError::Stats {
                field: "rows",
                reason: format!("has {} values, not a multiple of dim = {dim}", rows.len()),
            });
        }
        let count = rows.len() / dim;
        if count < 2 {
            return Err(PerceptualError::Stats {
                field: "rows",
                reason: format!(
                    "has {count} feature vector(s); the unbiased covariance needs at least 2"
                ),
            });
        }
        if let Some(i) = rows.iter().position(|v| !v.is_finite()) {
            return Err(PerceptualError::Stats {
                field: "rows",
                reason: format!(
                    "value {} (row {}, column {}) is not finite",
                    rows[i],
                    i / dim,
                    i % dim
                ),
            });
        }
        let x = DMatrix::<f64>::from_iterator(dim, count, rows.iter().map(|&v| f64::from(v)));
        // `x` is dim × count (column j = row j of the input).
        let mean: DVector<f64> = x.column_mean();
        let mut centred = x;
        for mut col in centred.column_iter_mut() {
            col -= &mean;
        }
        let cov = (&centred * centred.transpose()) / (count as f64 - 1.0);
        // Symmetric, so column-major storage is also the row-major layout; `centred` is
        // dim × count column-major, i.e. count × dim row-major.
        Ok(Self {
            mean: mean.iter().copied().collect(),
            cov: cov.as_slice().to_vec(),
            dim,
            count,
            centred: (count <= dim).then(|| centred.as_slice().to_vec()),
        })
    }

    /// Checks the field lengths and finiteness; `which` names the argument in errors.
    fn validate(&self, which: &'static str) -> Result<(), PerceptualError> {
        let fail = |reason: String| {
            Err(PerceptualError::Stats {
                field: which,
                reason,
            })
        };
        if self.dim == 0 {
            return fail("has dim 0".into());
        }
        if self.mean.len() != self.dim {
            return fail(format!(
                "mean has {} values but dim is {}",
                self.mean.len(),
                self.dim
            ));
        }
        if self.cov.len() != self.dim * self.dim {
            return fail(format!(
                "cov has {} values but dim² is {}",
                self.cov.len(),
                self.dim * self.dim
            ));
        }
        if !self.mean.iter().chain(&self.cov).all(|v| v.is_finite()) {
            return fail("mean or cov has non-finite values".into());
        }
        Ok(())
    }
}

/// Eigenvalues and eigenvectors of a symmetric matrix; `None` if the QR iteration does not
/// converge.
fn eigen_with_vectors(m: DMatrix<f64>) -> Option<(DVector<f64>, DMatrix<f64>)> {
    // A generous iteration cap instead of nalgebra's "unlimited" (0), so that a pathological
    // input is an error rather than a hang. Typical inputs need a few sweeps per eigenvalue.
    let max_iter = 1000 * m.nrows().max(1);
    SymmetricEigen::try_new(m, f64::EPSILON, max_iter).map(|e| (e.eigenvalues, e.eigenvectors))
}

/// Eigenvalues only of a symmetric matrix (no eigenvector accumulation: much cheaper).
/// `None` if the solver fails.
fn eigenvalues(m: DMatrix<f64>) -> Option<DVector<f64>> {
    // nalgebra exposes the vector-free decomposition only through `symmetric_eigenvalues`,
    // which unwraps its convergence check internally; inputs are validated finite, where the
    // implicit QR always converges, but a failure must still be an error, not a panic.
    std::panic::catch_unwind(move || m.symmetric_eigenvalues()).ok()
}

/// `(A + Aᵀ)/2`: removes round-off asymmetry before a symmetric solver.
fn symmetrised(m: DMatrix<f64>) -> DMatrix<f64> {
    (&m + m.transpose()) * 0.5
}

/// The Fréchet distance `‖μ1 − μ2‖² + Tr(Σ1 + Σ2 − 2(Σ1 Σ2)^½)` between two Gaussians (the
/// FID when the statistics come from Inception pool3 features). See the module docs for the
/// method and for how it differs from pytorch-fid's eps retry.
pub fn frechet_distance(a: &FeatureStats, b: &FeatureStats) -> Result<f64, PerceptualError> {
    a.validate("a")?;
    b.validate("b")?;
    if a.dim != b.dim {
        return Err(PerceptualError::Stats {
            field: "b",
            reason: format!("has dim {} but `a` has dim {}", b.dim, a.dim),
        });
    }
    let d = a.dim;
    let mean_term: f64 = a
        .mean
        .iter()
        .zip(&b.mean)
        .map(|(x, y)| (x - y) * (x - y))
        .sum();
    let trace = |s: &FeatureStats| (0..d).map(|i| s.cov[i * d + i]).sum::<f64>();
    let tr_covmean = match (&a.centred, &b.centred) {
        (Some(x1), Some(x2)) => low_rank_trace(a, b, x1, x2)?,
        _ => eigen_trace(a, b)?,
    };
    let fid = mean_term + trace(a) + trace(b) - 2.0 * tr_covmean;
    if fid.is_finite() {
        Ok(fid)
    } else {
        Err(PerceptualError::Stats {
            field: "cov",
            reason: format!("the Fréchet distance is not finite ({fid})"),
        })
    }
}

/// `Tr((Σ1 Σ2)^½)` from the covariances, through symmetric eigendecompositions (module docs).
fn eigen_trace(a: &FeatureStats, b: &FeatureStats) -> Result<f64, PerceptualError> {
    let d = a.dim;
    let s1 = symmetrised(DMatrix::from_row_slice(d, d, &a.cov));
    let s2 = symmetrised(DMatrix::from_row_slice(d, d, &b.cov));
    let no_convergence = || PerceptualError::Stats {
        field: "a",
        reason: "cov: the symmetric eigensolver did not converge".into(),
    };
    let (l1, v1) = eigen_with_vectors(s1).ok_or_else(no_convergence)?;
    // With Σ1^½ = V D Vᵀ (D = diag(√λ)), M = Σ1^½ Σ2 Σ1^½ = V (D Vᵀ Σ2 V D) Vᵀ has the
    // eigenvalues of D (Vᵀ Σ2 V) D. Rows and columns where λ is zero are zero, so only the
    // numerical range of Σ1 is kept (λ above d·ε·λ_max, numpy's matrix-rank threshold): exact
    // up to round-off, cheaper, and it avoids nalgebra's QR returning infinite eigenvalues for
    // a matrix that is mostly zero blocks (seen on the quickstart's 24 renders).
    let l_max = l1.iter().copied().fold(0.0f64, f64::max);
    let kept: Vec<usize> = (0..d)
        .filter(|&i| l1[i] > l_max * d as f64 * f64::EPSILON)
        .collect();
    // Σ1 = 0 (every row the same) leaves nothing: the trace is 0.
    if kept.is_empty() {
        return Ok(0.0);
    }
    let v_kept = v1.select_columns(&kept);
    let sqrt_l1: Vec<f64> = kept.iter().map(|&i| l1[i].sqrt()).collect();
    let w = v_kept.transpose() * s2 * &v_kept;
    let r = kept.len();
    let m = symmetrised(DMatrix::from_fn(r, r, |i, j| {
        sqrt_l1[i] * w[(i, j)] * sqrt_l1[j]
    }));
    let lm = eigenvalues(m).ok_or_else(no_convergence)?;
    Ok(lm.iter().map(|l| l.max(0.0).sqrt()).sum())
}

/// `Tr((Σ1 Σ2)^½)` from the centred features, when both sets have no more vectors than
/// dimensions: with `Σk = XkᵀXk / (nk − 1)`, the non-zero eigenvalues of `Σ1 Σ2` are those of
/// `A Aᵀ / ((n1 − 1)(n2 − 1))` with `A = X1 X2ᵀ` (`n1 × n2`), so the trace is the sum of `A`'s
/// singular values over `√((n1 − 1)(n2 − 1))`: exact, and `n1·n2·d` work instead of `d³`.
fn low_rank_trace(
    a: &FeatureStats,
    b: &FeatureStats,
    x1: &[f64],
    x2: &[f64],
) -> Result<f64, PerceptualError> {
    let d = a.dim;
    let bad = |field| PerceptualError::Stats {
        field,
        reason: "centred has the wrong length".into(),
    };
    if x1.len() != a.count * d {
        return Err(bad("a"));
    }
    if x2.len() != b.count * d {
        return Err(bad("b"));
    }
    let m1 = DMatrix::from_row_slice(a.count, d, x1);
    let m2 = DMatrix::from_row_slice(b.count, d, x2);
    let norm = ((a.count as f64 - 1.0) * (b.count as f64 - 1.0)).sqrt();
    Ok((&m1 * m2.transpose()).singular_values().iter().sum::<f64>() / norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lifegom_render::rng::Rng;

    fn random_rows(rng: &mut Rng, n: usize, dim: usize, scale: f32, shift: f32) -> Vec<f32> {
        (0..n * dim)
            .map(|i| {
                // Correlated columns: each value mixes its own noise with the row's first one.
                let base = rng.next_f32() - 0.5;
                shift + scale * (base + 0.3 * ((i % dim) as f32 * 0.7).sin())
            })
            .collect()
    }

    /// Pool3 features of the quickstart's 24 template-in-one-colour renders and their targets:
    /// a rank-23 pair on which nalgebra's QR, run on the whole 2048² product, returned
    /// infinite eigenvalues (FID −∞). The reference is pytorch-fid's formula under scipy 1.10
    /// on the same f32 features.
    #[test]
    fn rank_deficient_quickstart_features_match_scipy() {
        let load = |name: &str| -> Vec<f32> {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/fixtures")
                .join(name);
            std::fs::read(path)
                .unwrap()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect()
        };
        let a = FeatureStats::from_features(&load("fid_template_renders.f32"), 2048).unwrap();
        let b = FeatureStats::from_features(&load("fid_template_targets.f32"), 2048).unwrap();
        let scipy = 246.852_776_870_619_92;
        // From the features (the small cross product), and from the covariances alone (the
        // eigendecompositions on Σ1's range).
        let fid = frechet_distance(&a, &b).unwrap();
        assert!(
            (fid - scipy).abs() / scipy < 1e-6,
            "FID {fid} vs scipy {scipy}"
        );
        let (a, b) = (
            FeatureStats { centred: None, ..a },
            FeatureStats { centred: None, ..b },
        );
        let fid = frechet_distance(&a, &b).unwrap();
        assert!(
            (fid - scipy).abs() / scipy < 1e-6,
            "FID {fid} vs scipy {scipy} (covariances)"
        );
    }

    #[test]
    fn cov_matches_np_cov() {
        // np.cov([[1,2],[3,5],[4,4]], rowvar=False) = [[7/3, 11/6], [11/6, 7/3]].
        let s = FeatureStats::from_features(&[1.0, 2.0, 3.0, 5.0, 4.0, 4.0], 2).unwrap();
        assert_eq!(s.count, 3);
        for (g, w) in s.mean.iter().zip([8.0 / 3.0, 11.0 / 3.0]) {
            assert!((g - w).abs() < 1e-12, "{:?}", s.mean);
        }
        let want = [7.0 / 3.0, 11.0 / 6.0, 11.0 / 6.0, 7.0 / 3.0];
        for (g, w) in s.cov.iter().zip(want) {
            assert!((g - w).abs() < 1e-12, "{:?}", s.cov);
        }
    }

    #[test]
    fn identical_stats_give_zero_and_distance_is_symmetric() {
        let mut rng = Rng::new(7);
        let a = FeatureStats::from_features(&random_rows(&mut rng, 40, 16, 1.0, 0.0), 16).unwrap();
        let b = FeatureStats::from_features(&random_rows(&mut rng, 30, 16, 1.5, 0.2), 16).unwrap();
        let aa = frechet_distance(&a, &a).unwrap();
        assert!(aa.abs() < 1e-6, "FID(a, a) = {aa}");
        let ab = frechet_distance(&a, &b).unwrap();
        let ba = frechet_distance(&b, &a).unwrap();
        assert!(ab > 0.0);
        assert!((ab - ba).abs() < 1e-9 * ab, "{ab} vs {ba}");
    }

    /// Diagonal covariances: the Fréchet distance is Σ(μ1−μ2)² + Σ(√σ1 − √σ2)², and for
    /// commuting non-diagonal ones the same holds in their shared eigenbasis.
    #[test]
    fn analytic_two_dimensional_cases() {
        let stats = |mean: [f64; 2], cov: [f64; 4]| FeatureStats {
            mean: mean.to_vec(),
            cov: cov.to_vec(),
            dim: 2,
            count: 10,
            centred: None,
        };
        let a = stats([1.0, 2.0], [4.0, 0.0, 0.0, 9.0]);
        let b = stats([0.0, 0.0], [1.0, 0.0, 0.0, 1.0]);
        let want = 1.0 + 4.0 + (2.0f64 - 1.0).powi(2) + (3.0f64 - 1.0).powi(2);
        let got = frechet_distance(&a, &b).unwrap();
        assert!((got - want).abs() < 1e-10, "{got} vs {want}");

        // Σ1 = R diag(4, 1) Rᵀ, Σ2 = R diag(1, 9) Rᵀ with R a 45° rotation.
        let rot = |l1: f64, l2: f64| {
            let (p, q) = ((l1 + l2) / 2.0, (l1 - l2) / 2.0);
            [p, q, q, p]
        };
        let a = stats([0.5, -0.5], rot(4.0, 1.0));
        let b = stats([0.0, 0.0], rot(1.0, 9.0));
        let want = 0.5 + (2.0f64 - 1.0).powi(2) + (1.0f64 - 3.0).powi(2);
        let got = frechet_distance(&a, &b).unwrap();
        assert!((got - want).abs() < 1e-10, "{got} vs {want}");
    }

    /// Fewer samples than dimensions (singular covariances, the usual FID situation with few
    /// images): finite, non-negative, zero for identical sets, and equal to the nuclear-norm
    /// formula Tr((Σ1Σ2)^½) = ‖X1 X2ᵀ‖_* / √((n1−1)(n2−1)) computed independently.
    #[test]
    fn rank_deficient_covariances_stay_finite() {
        let mut rng = Rng::new(11);
        let dim = 24;
        let (n1, n2) = (5, 8);
        let r1 = random_rows(&mut rng, n1, dim, 1.0, 0.0);
        let r2 = random_rows(&mut rng, n2, dim, 2.0, 0.1);
        let a = FeatureStats::from_features(&r1, dim).unwrap();
        let b = FeatureStats::from_features(&r2, dim).unwrap();
        let aa = frechet_distance(&a, &a).unwrap();
        assert!(aa.abs() < 1e-6, "{aa}");
        let ab = frechet_distance(&a, &b).unwrap();
        assert!(ab.is_finite() && ab > 0.0, "{ab}");

        let centred = |rows: &[f32], n: usize, s: &FeatureStats| {
            DMatrix::from_fn(n, dim, |i, j| f64::from(rows[i * dim + j]) - s.mean[j])
        };
        let x1 = centred(&r1, n1, &a);
        let x2 = centred(&r2, n2, &b);
        let nuclear: f64 = (&x1 * x2.transpose()).singular_values().iter().sum();
        let tr_covmean = nuclear / (((n1 - 1) * (n2 - 1)) as f64).sqrt();
        let mean: f64 = a
            .mean
            .iter()
            .zip(&b.mean)
            .map(|(x, y)| (x - y).powi(2))
            .sum();
        let trace = |s: &FeatureStats| (0..dim).map(|i| s.cov[i * dim + i]).sum::<f64>();
        let want = mean + trace(&a) + trace(&b) - 2.0 * tr_covmean;
        assert!((ab - want).abs() < 1e-7 * want, "{ab} vs {want}");

        // All-zero covariance (every row identical) too.
        let flat = FeatureStats::from_features(&[0.5; 3 * 4], 4).unwrap();
        let d = frechet_distance(&flat, &flat).unwrap();
        assert_eq!(d, 0.0);
    }

    #[test]
    fn bad_inputs_are_errors_naming_the_field() {
        let msg = |e: PerceptualError| e.to_string();
        assert!(msg(FeatureStats::from_features(&[1.0; 5], 2).unwrap_err()).contains("`rows`"));
        assert!(msg(FeatureStats::from_features(&[1.0; 4], 4).unwrap_err()).contains("at least 2"));
        assert!(msg(FeatureStats::from_features(&[1.0; 4], 0).unwrap_err()).contains("`dim`"));
        let nan = msg(FeatureStats::from_features(&[1.0, f32::NAN, 2.0, 3.0], 2).unwrap_err());
        assert!(nan.contains("row 0, column 1"), "{nan}");
        let a = FeatureStats::from_features(&[1.0, 2.0, 3.0, 5.0], 2).unwrap();
        let b = FeatureStats::from_features(&[1.0, 2.0, 3.0, 5.0, 1.0, 1.0], 3).unwrap();
        assert!(msg(frechet_distance(&a, &b).unwrap_err()).contains("dim"));
        let mut bad = a.clone();
        bad.cov.pop();
        assert!(msg(frechet_distance(&a, &bad).unwrap_err()).contains("`b`"));
        let mut inf = a.clone();
        inf.mean[0] = f64::INFINITY;
        assert!(msg(frechet_distance(&inf, &a).unwrap_err()).contains("`a`"));
    }

    /// The real size: 2048-d covariances from 64 samples each. Run with
    /// `cargo test --workspace fid_2048_timing -- --ignored --nocapture`.
    #[test]
    #[ignore = "timing report"]
    fn fid_2048_timing() {
        let mut rng = Rng::new(3);
        let dim = 2048;
        let a =
            FeatureStats::from_features(&random_rows(&mut rng, 64, dim, 1.0, 0.0), dim).unwrap();
        let b =
            FeatureStats::from_features(&random_rows(&mut rng, 64, dim, 1.2, 0.1), dim).unwrap();
        let t = std::time::Instant::now();
        let d = frechet_distance(&a, &b).unwrap();
        eprintln!("FID 2048-d: {d} in {:.2} s", t.elapsed().as_secs_f64());
    }
}
