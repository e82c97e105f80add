//! The fusion layers' attention and residual LayerNorm on host slices: the forwards and
//! hand-written backwards of [`super::op`] on the CPU backends (design.md §7.4).
//!
//! **Attention over short sequences.** Fusion attends over the N views of one vertex (N = 3…5
//! keys, N or 1 queries) for every low-res vertex at once, so a call is thousands of tiny
//! problems. As tensor ops that is four head reshapes, two batched matmuls of `N×d_k` matrices
//! (one gemm call each, thousands per op), a scale and a five-op softmax, and every one of them
//! keeps an autodiff node and an intermediate. Here one task per block of vertices does it all in
//! registers-sized loops. With `s = 1/√d_k`, per vertex `b` and head `h` (channels `h·d_k..`):
//!
//! `S_ij = s·⟨q_i, k_j⟩`, `P_i = softmax_j(S_i)` (max-subtracted), `o_i = Σ_j P_ij·v_j`.
//!
//! Backward, given `g_i = ∂L/∂o_i`, recomputing `P` rather than storing it (`L_q·L_k` per head
//! costs less to redo than to keep):
//!
//! `dP_ij = ⟨g_i, v_j⟩`, `∂v_j = Σ_i P_ij·g_i`, `dS_ij = P_ij·(dP_ij − Σ_j' P_ij'·dP_ij')`,
//! `∂q_i = s·Σ_j dS_ij·k_j`, `∂k_j = s·Σ_i dS_ij·q_i`.
//!
//! **LayerNorm of a residual sum.** `y = LN(x + r) = x̂·γ + β` with `x̂ = (z − μ)·ρ`, `z = x + r`,
//! `μ` the row mean, `ρ = 1/√(mean((z − μ)²) + ε)` (biased variance, as PyTorch). Backward:
//! `∂γ = Σ_rows g·x̂`, `∂β = Σ_rows g`, and with `a = g·γ`,
//! `∂z = ρ·(a − mean(a) − x̂·mean(a·x̂))`, which is also `∂x` and `∂r`.
//!
//! Both split their rows over rayon tasks; each task writes disjoint output rows, and the
//! LayerNorm's parameter gradients are per-task partial sums added at the end.

use std::ops::AddAssign;

use num_traits::Float;
use rayon::prelude::*;

use crate::lanes;

/// Vertices per rayon task in the attention kernels: two cores get dozens of tasks each.
const BATCH_PER_TASK: usize = 64;
/// Rows per rayon task in the LayerNorm kernels.
const ROWS_PER_TASK: usize = 128;

/// The float types the kernels run in (`f32`, and `f64` for the precision tests).
pub trait Real: Float + Send + Sync + AddAssign + Default {}
impl<T: Float + Send + Sync + AddAssign + Default> Real for T {}

/// Shape of one attention call: `batch` independent problems of `len_q` queries against
/// `len_k` keys and values, `d_model` channels split into `heads` heads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AttentionShape {
    /// Independent problems B (the vertices).
    pub batch: usize,
    /// Queries per problem.
    pub len_q: usize,
    /// Keys (and values) per problem.
    pub len_k: usize,
    /// Channels D, a multiple of `heads`.
    pub d_model: usize,
    /// Heads H.
    pub heads: usize,
}

impl AttentionShape {
    fn head_dim(&self) -> usize {
        self.d_model / self.heads
    }

    fn scale<T: Real>(&self) -> T {
        T::one()
            / T::from(self.head_dim())
                .expect("a head width is a float")
                .sqrt()
    }
}

/// `p ← softmax(s·⟨q, k_j⟩)` over the keys of one head; `keys` is the problem's `[L_k, D]` block
/// and `c` the head's first channel.
fn head_probabilities<T: Real>(p: &mut [T], q: &[T], keys: &[T], c: usize, dk: usize, scale: T) {
    let d = keys.len() / p.len().max(1);
    let mut max = T::neg_infinity();
    for (j, pj) in p.iter_mut().enumerate() {
        *pj = scale * lanes::dot(q, &keys[j * d + c..j * d + c + dk]);
        max = max.max(*pj);
    }
    let mut sum = T::zero();
    for pj in p.iter_mut() {
        *pj = (*pj - max).exp();
        sum += *pj;
    }
    for pj in p.iter_mut() {
        *pj = *pj / sum;
    }
}

/// The attention forward: `q` `[B, L_q, D]`, `k`, `v` `[B, L_k, D]` → `[B, L_q, D]`.
pub fn attention_forward<T: Real>(q: &[T], k: &[T], v: &[T], shape: AttentionShape) -> Vec<T> {
    let AttentionShape {
        len_q,
        len_k,
        d_model: d,
        heads,
        ..
    } = shape;
    let dk = shape.head_dim();
    let scale = shape.scale::<T>();
    let mut out = vec![T::zero(); q.len()];
    let (q_block, k_block) = (len_q * d, len_k * d);
    out.par_chunks_mut(BATCH_PER_TASK * q_block)
        .enumerate()
        .for_each(|(task, out)| {
            let mut p = vec![T::zero(); len_k];
            for (local, out_b) in out.chunks_mut(q_block).enumerate() {
                let b = task * BATCH_PER_TASK + local;
                let (qb, kb, vb) = (
                    &q[b * q_block..][..q_block],
                    &k[b * k_block..][..k_block],
                    &v[b * k_block..][..k_block],
                );
                for h in 0..heads {
                    let c = h * dk;
                    for i in 0..len_q {
                        head_probabilities(&mut p, &qb[i * d + c..][..dk], kb, c, dk, scale);
                        let o = &mut out_b[i * d + c..][..dk];
                        for (j, &pj) in p.iter().enumerate() {
                            for (o, &vv) in o.iter_mut().zip(&vb[j * d + c..][..dk]) {
                                *o += pj * vv;
                            }
                        }
                    }
                }
            }
        });
    out
}

/// Gradients of the attention w.r.t. `q`, `k` and `v` given `grad` `= ∂L/∂out` `[B, L_q, D]`.
pub fn attention_backward<T: Real>(
    q: &[T],
    k: &[T],
    v: &[T],
    grad: &[T],
    shape: AttentionShape,
) -> (Vec<T>, Vec<T>, Vec<T>) {
    let AttentionShape {
        len_q,
        len_k,
        d_model: d,
        heads,
        ..
    } = shape;
    let dk = shape.head_dim();
    let scale = shape.scale::<T>();
    let mut dq = vec![T::zero(); q.len()];
    let mut dkv = vec![T::zero(); k.len()];
    let mut dv = vec![T::zero(); v.len()];
    let (q_block, k_block) = (len_q * d, len_k * d);
    dq.par_chunks_mut(BATCH_PER_TASK * q_block)
        .zip(dkv.par_chunks_mut(BATCH_PER_TASK * k_block))
        .zip(dv.par_chunks_mut(BATCH_PER_TASK * k_block))
        .enumerate()
        .for_each(|(task, ((dq, dkt), dvt))| {
            let mut p = vec![T::zero(); len_k];
            let mut ds = vec![T::zero(); len_k];
            let blocks = dq
                .chunks_mut(q_block)
                .zip(dkt.chunks_mut(k_block))
                .zip(dvt.chunks_mut(k_block));
            for (local, ((dq_b, dk_b), dv_b)) in blocks.enumerate() {
                let b = task * BATCH_PER_TASK + local;
                let (qb, kb, vb, gb) = (
                    &q[b * q_block..][..q_block],
                    &k[b * k_block..][..k_block],
                    &v[b * k_block..][..k_block],
                    &grad[b * q_block..][..q_block],
                );
                for h in 0..heads {
                    let c = h * dk;
                    for i in 0..len_q {
                        let qi = &qb[i * d + c..][..dk];
                        let gi = &gb[i * d + c..][..dk];
                        head_probabilities(&mut p, qi, kb, c, dk, scale);
                        let mut weighted = T::zero();
                        for (j, dsj) in ds.iter_mut().enumerate() {
                            *dsj = lanes::dot(gi, &vb[j * d + c..][..dk]);
                            weighted += p[j] * *dsj;
                            for (dvv, &g) in dv_b[j * d + c..][..dk].iter_mut().zip(gi) {
                                *dvv += p[j] * g;
                            }
                        }
                        let dqi = &mut dq_b[i * d + c..][..dk];
                        for (j, dsj) in ds.iter_mut().enumerate() {
                            *dsj = scale * p[j] * (*dsj - weighted);
                            for (dqv, &kv) in dqi.iter_mut().zip(&kb[j * d + c..][..dk]) {
                                *dqv += *dsj * kv;
                            }
                            for (dkv, &qv) in dk_b[j * d + c..][..dk].iter_mut().zip(qi) {
                                *dkv += *dsj * qv;
                            }
                        }
                    }
                }
            }
        });
    (dq, dkv, dv)
}

/// Row statistics of `z = x + r`: writes `z` into `z_out` and returns `(μ, ρ)`.
fn residual_row<T: Real>(x: &[T], r: &[T], z_out: &mut [T], epsilon: T) -> (T, T) {
    let n = T::from(x.len()).expect("a row length is a float");
    for ((z, &a), &b) in z_out.iter_mut().zip(x).zip(r) {
        *z = a + b;
    }
    let mean = lanes::sum(z_out) / n;
    let var = lanes::sum_squared_deviation(z_out, mean) / n;
    (mean, T::one() / (var + epsilon).sqrt())
}

/// `LN(x + r)·γ + β` over rows of `gamma.len()` channels.
pub fn add_layer_norm_forward<T: Real>(
    x: &[T],
    r: &[T],
    gamma: &[T],
    beta: &[T],
    epsilon: f64,
) -> Vec<T> {
    let d = gamma.len();
    let eps = T::from(epsilon).expect("epsilon is a float");
    let mut out = vec![T::zero(); x.len()];
    out.par_chunks_mut(ROWS_PER_TASK * d)
        .enumerate()
        .for_each(|(task, out)| {
            for (local, y) in out.chunks_mut(d).enumerate() {
                let row = (task * ROWS_PER_TASK + local) * d;
                let (mean, rstd) = residual_row(&x[row..][..d], &r[row..][..d], y, eps);
                for ((y, &g), &b) in y.iter_mut().zip(gamma).zip(beta) {
                    *y = (*y - mean) * rstd * g + b;
                }
            }
        });
    out
}

/// Gradients of [`add_layer_norm_forward`] given `grad` `= ∂L/∂y`: `(∂z, ∂γ, ∂β)`, where `∂z`
/// is the gradient of both `x` and `r`.
pub fn add_layer_norm_backward<T: Real>(
    x: &[T],
    r: &[T],
    gamma: &[T],
    grad: &[T],
    epsilon: f64,
) -> (Vec<T>, Vec<T>, Vec<T>) {
    let d = gamma.len();
    let eps = T::from(epsilon).expect("epsilon is a float");
    let n = T::from(d).expect("a row length is a float");
    let mut dz = vec![T::zero(); x.len()];
    let partials: Vec<(Vec<T>, Vec<T>)> = dz
        .par_chunks_mut(ROWS_PER_TASK * d)
        .enumerate()
        .map(|(task, dz)| {
            let mut dgamma = vec![T::zero(); d];
            let mut dbeta = vec![T::zero(); d];
            let mut xhat = vec![T::zero(); d];
            let mut a = vec![T::zero(); d];
            for (local, dz_row) in dz.chunks_mut(d).enumerate() {
                let row = (task * ROWS_PER_TASK + local) * d;
                let (mean, rstd) = residual_row(&x[row..][..d], &r[row..][..d], &mut xhat, eps);
                let g = &grad[row..][..d];
                for c in 0..d {
                    xhat[c] = (xhat[c] - mean) * rstd;
                    a[c] = g[c] * gamma[c];
                    dgamma[c] += g[c] * xhat[c];
                    dbeta[c] += g[c];
                }
                let (mean_a, mean_ax) = (lanes::sum(&a) / n, lanes::dot(&a, &xhat) / n);
                for c in 0..d {
                    dz_row[c] = rstd * (a[c] - mean_a - xhat[c] * mean_ax);
                }
            }
            (dgamma, dbeta)
        })
        .collect();
    let mut dgamma = vec![T::zero(); d];
    let mut dbeta = vec![T::zero(); d];
    for (pg, pb) in partials {
        for c in 0..d {
            dgamma[c] += pg[c];
            dbeta[c] += pb[c];
        }
    }
    (dz, dgamma, dbeta)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lifegom_render::rng::Rng;

    fn random(n: usize, rng: &mut Rng) -> Vec<f64> {
        (0..n).map(|_| rng.uniform() * 2.0 - 1.0).collect()
    }

    /// A weighted sum of the outputs, so every output element has its own gradient.
    fn weighted(out: &[f64], w: &[f64]) -> f64 {
        out.iter().zip(w).map(|(a, b)| a * b).sum()
    }

    /// Central differences of `f` at `x` along every coordinate, against `analytic`.
    fn check_gradient(what: &str, x: &[f64], analytic: &[f64], f: &dyn Fn(&[f64]) -> f64) {
        let h = 1e-6;
        for i in 0..x.len() {
            let mut plus = x.to_vec();
            let mut minus = x.to_vec();
            plus[i] += h;
            minus[i] -= h;
            let numeric = (f(&plus) - f(&minus)) / (2.0 * h);
            assert!(
                (numeric - analytic[i]).abs() <= 1e-6 * (1.0 + numeric.abs()),
                "{what}[{i}]: finite difference {numeric} vs analytic {}",
                analytic[i]
            );
        }
    }

    #[test]
    fn attention_matches_a_direct_softmax_and_finite_differences() {
        let mut rng = Rng::new(7);
        // Batch 3 spans more than one task only with many vertices; a second case below does.
        for shape in [
            AttentionShape {
                batch: 3,
                len_q: 2,
                len_k: 3,
                d_model: 6,
                heads: 2,
            },
            AttentionShape {
                batch: 2,
                len_q: 1,
                len_k: 4,
                d_model: 4,
                heads: 1,
            },
        ] {
            let (qn, kn) = (
                shape.batch * shape.len_q * shape.d_model,
                shape.batch * shape.len_k * shape.d_model,
            );
            let (q, k, v) = (
                random(qn, &mut rng),
                random(kn, &mut rng),
                random(kn, &mut rng),
            );
            let out = attention_forward(&q, &k, &v, shape);
            // Direct: softmax over keys of each head, written without the kernel's loops.
            let (d, dk) = (shape.d_model, shape.d_model / shape.heads);
            let s = 1.0 / (dk as f64).sqrt();
            for b in 0..shape.batch {
                for h in 0..shape.heads {
                    for i in 0..shape.len_q {
                        let logits: Vec<f64> = (0..shape.len_k)
                            .map(|j| {
                                (0..dk)
                                    .map(|c| {
                                        q[(b * shape.len_q + i) * d + h * dk + c]
                                            * k[(b * shape.len_k + j) * d + h * dk + c]
                                    })
                                    .sum::<f64>()
                                    * s
                            })
                            .collect();
                        let z: f64 = logits.iter().map(|l| l.exp()).sum();
                        for c in 0..dk {
                            let expect: f64 = (0..shape.len_k)
                                .map(|j| {
                                    logits[j].exp() / z * v[(b * shape.len_k + j) * d + h * dk + c]
                                })
                                .sum();
                            let got = out[(b * shape.len_q + i) * d + h * dk + c];
                            assert!((got - expect).abs() < 1e-12, "{got} vs {expect}");
                        }
                    }
                }
            }
            let w = random(qn, &mut rng);
            let (dq, dkk, dv) = attention_backward(&q, &k, &v, &w, shape);
            check_gradient("dq", &q, &dq, &|x| {
                weighted(&attention_forward(x, &k, &v, shape), &w)
            });
            check_gradient("dk", &k, &dkk, &|x| {
                weighted(&attention_forward(&q, x, &v, shape), &w)
            });
            check_gradient("dv", &v, &dv, &|x| {
                weighted(&attention_forward(&q, &k, x, shape), &w)
            });
        }
    }

    #[test]
    fn attention_tasks_cover_every_vertex() {
        // More vertices than one task holds, and a batch that is no multiple of the task size.
        let mut rng = Rng::new(3);
        let shape = AttentionShape {
            batch: 2 * BATCH_PER_TASK + 5,
            len_q: 1,
            len_k: 2,
            d_model: 2,
            heads: 1,
        };
        let q = random(shape.batch * 2, &mut rng);
        let k = random(shape.batch * 4, &mut rng);
        // Equal values per vertex: any convex combination returns them exactly.
        let v: Vec<f64> = (0..shape.batch)
            .flat_map(|b| [b as f64, -(b as f64), b as f64, -(b as f64)])
            .collect();
        let out = attention_forward(&q, &k, &v, shape);
        for b in 0..shape.batch {
            assert!(
                (out[2 * b] - b as f64).abs() < 1e-9 && (out[2 * b + 1] + b as f64).abs() < 1e-9
            );
        }
    }

    #[test]
    fn add_layer_norm_matches_its_definition_and_finite_differences() {
        let mut rng = Rng::new(11);
        // 2·ROWS_PER_TASK + 3 rows: several tasks and a partial one, whose partial parameter
        // gradients must all be summed.
        let (rows, d) = (2 * ROWS_PER_TASK + 3, 5);
        let (x, r) = (random(rows * d, &mut rng), random(rows * d, &mut rng));
        let (gamma, beta) = (random(d, &mut rng), random(d, &mut rng));
        let eps = 1e-5;
        let y = add_layer_norm_forward(&x, &r, &gamma, &beta, eps);
        for row in 0..rows {
            let z: Vec<f64> = (0..d).map(|c| x[row * d + c] + r[row * d + c]).collect();
            let mean = z.iter().sum::<f64>() / d as f64;
            let var = z.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d as f64;
            for c in 0..d {
                let expect = (z[c] - mean) / (var + eps).sqrt() * gamma[c] + beta[c];
                assert!((y[row * d + c] - expect).abs() < 1e-12);
            }
        }
        // Finite differences on a few rows (every coordinate of 600+ rows would be slow).
        let small = 3 * d;
        let (xs, rs) = (&x[..small], &r[..small]);
        let w = random(small, &mut rng);
        let (dz, dgamma, dbeta) = add_layer_norm_backward(xs, rs, &gamma, &w, eps);
        let loss = |x: &[f64], r: &[f64], g: &[f64], b: &[f64]| {
            weighted(&add_layer_norm_forward(x, r, g, b, eps), &w)
        };
        check_gradient("dx", xs, &dz, &|v| loss(v, rs, &gamma, &beta));
        check_gradient("dr", rs, &dz, &|v| loss(xs, v, &gamma, &beta));
        check_gradient("dgamma", &gamma, &dgamma, &|v| loss(xs, rs, v, &beta));
        check_gradient("dbeta", &beta, &dbeta, &|v| loss(xs, rs, &gamma, v));
        // Across tasks: the parameter gradients of all rows equal a serial sum.
        let w = random(rows * d, &mut rng);
        let (_, dgamma, dbeta) = add_layer_norm_backward(&x, &r, &gamma, &w, eps);
        let mut serial = (vec![0.0; d], vec![0.0; d]);
        for row in 0..rows {
            let (_, g1, b1) = add_layer_norm_backward(
                &x[row * d..][..d],
                &r[row * d..][..d],
                &gamma,
                &w[row * d..][..d],
                eps,
            );
            for c in 0..d {
                serial.0[c] += g1[c];
                serial.1[c] += b1[c];
            }
        }
        for c in 0..d {
            assert!(
                (dgamma[c] - serial.0[c]).abs() < 1e-9 && (dbeta[c] - serial.1[c]).abs() < 1e-9
            );
        }
    }
}
