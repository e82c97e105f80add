//! Sparse constants made dense at load.
//!
//! TensorFlow Lite stores a sparse constant the TACO way: a traversal order of the dimensions
//! and, per traversed dimension, either its dense size or compressed (CSR) segments and
//! indices; the buffer holds only the stored values, in traversal order. The MediaPipe
//! detector keeps 38 of its 1 × 1 kernels so, behind `DENSIFY` operators: they are expanded
//! here once, so the graph runs dense convolutions.

/// One traversed dimension of a sparse constant.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Dimension {
    /// All `size` positions are stored.
    Dense {
        /// The dimension's size.
        size: usize,
    },
    /// Compressed: for parent position `p`, positions `indices[segments[p]..segments[p + 1]]`.
    Csr {
        /// Start of each parent position's run in `indices` (one more entry than parents).
        segments: Vec<usize>,
        /// The stored positions along this dimension.
        indices: Vec<usize>,
    },
}

/// The dense array (C order, `shape`) of `values` stored sparse with `dims`, traversed in
/// `order` (a permutation of the dimensions); `Err` says what does not fit.
pub(crate) fn densify(
    shape: &[usize],
    order: &[usize],
    dims: &[Dimension],
    values: &[f32],
) -> Result<Vec<f32>, String> {
    let rank = shape.len();
    if order.len() != rank || dims.len() != rank {
        return Err(format!(
            "a sparse constant of rank {rank} with {} traversal entries and {} dimension \
             records (block-sparse constants are not read)",
            order.len(),
            dims.len()
        ));
    }
    let mut seen = vec![false; rank];
    for &d in order {
        if d >= rank || std::mem::replace(&mut seen[d], true) {
            return Err(format!(
                "traversal order {order:?} is not a permutation of 0..{rank}"
            ));
        }
    }
    for (level, dim) in dims.iter().enumerate() {
        let extent = shape[order[level]];
        match dim {
            Dimension::Dense { size } if *size != extent => {
                return Err(format!(
                    "dimension {} is dense of size {size}, the shape says {extent}",
                    order[level]
                ));
            }
            Dimension::Csr { segments, indices } => {
                if segments.windows(2).any(|w| w[0] > w[1])
                    || segments.last().is_some_and(|&end| end > indices.len())
                {
                    return Err(format!(
                        "dimension {}: CSR segments out of order or past the {} indices",
                        order[level],
                        indices.len()
                    ));
                }
                if let Some(&bad) = indices.iter().find(|&&i| i >= extent) {
                    return Err(format!(
                        "dimension {}: index {bad} past its size {extent}",
                        order[level]
                    ));
                }
            }
            Dimension::Dense { .. } => {}
        }
    }
    let mut strides = vec![1usize; rank];
    for d in (0..rank.saturating_sub(1)).rev() {
        strides[d] = strides[d + 1] * shape[d + 1];
    }
    let mut dense = vec![0f32; shape.iter().product()];
    let walk = Walk {
        order,
        dims,
        values,
        strides: &strides,
    };
    walk.level(0, 0, 0, &mut dense)?;
    Ok(dense)
}

struct Walk<'a> {
    order: &'a [usize],
    dims: &'a [Dimension],
    values: &'a [f32],
    strides: &'a [usize],
}

impl Walk<'_> {
    /// Visits traversal level `level` under parent position `parent` (the position in the
    /// previous level's stored sequence), `offset` being the dense offset so far.
    fn level(
        &self,
        level: usize,
        parent: usize,
        offset: usize,
        dense: &mut [f32],
    ) -> Result<(), String> {
        if level == self.dims.len() {
            let value = self.values.get(parent).ok_or_else(|| {
                format!(
                    "the traversal reaches stored value {parent}, the buffer holds {}",
                    self.values.len()
                )
            })?;
            dense[offset] = *value;
            return Ok(());
        }
        let stride = self.strides[self.order[level]];
        match &self.dims[level] {
            Dimension::Dense { size } => {
                for i in 0..*size {
                    self.level(level + 1, parent * size + i, offset + i * stride, dense)?;
                }
            }
            Dimension::Csr { segments, indices } => {
                let (Some(&start), Some(&end)) = (segments.get(parent), segments.get(parent + 1))
                else {
                    return Err(format!(
                        "CSR segments of dimension {} end at parent {parent}",
                        self.order[level]
                    ));
                };
                for (j, &i) in indices.iter().enumerate().take(end).skip(start) {
                    self.level(level + 1, j, offset + i * stride, dense)?;
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_csr_matrix_is_made_dense() {
        // [[1, 0, 2], [0, 0, 0], [0, 3, 0]]: rows dense, columns compressed.
        let dims = [
            Dimension::Dense { size: 3 },
            Dimension::Csr {
                segments: vec![0, 2, 2, 3],
                indices: vec![0, 2, 1],
            },
        ];
        let dense = densify(&[3, 3], &[0, 1], &dims, &[1.0, 2.0, 3.0]).unwrap();
        assert_eq!(dense, [1.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0]);
        // The same matrix traversed column first: columns dense, rows compressed.
        let dims = [
            Dimension::Dense { size: 3 },
            Dimension::Csr {
                segments: vec![0, 1, 2, 3],
                indices: vec![0, 2, 0],
            },
        ];
        let dense = densify(&[3, 3], &[1, 0], &dims, &[1.0, 3.0, 2.0]).unwrap();
        assert_eq!(dense, [1.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0]);
    }

    #[test]
    fn records_that_do_not_fit_are_errors() {
        let csr = |segments: Vec<usize>, indices: Vec<usize>| {
            [
                Dimension::Dense { size: 2 },
                Dimension::Csr { segments, indices },
            ]
        };
        for (dims, values) in [
            (csr(vec![0, 1, 2], vec![0, 5]), vec![1.0, 2.0]),
            (csr(vec![0, 2, 1], vec![0, 1]), vec![1.0, 2.0]),
            (csr(vec![0, 1], vec![0]), vec![1.0]),
            (csr(vec![0, 1, 2], vec![0, 1]), vec![1.0]),
        ] {
            assert!(densify(&[2, 2], &[0, 1], &dims, &values).is_err());
        }
        let dense = [Dimension::Dense { size: 2 }, Dimension::Dense { size: 2 }];
        assert!(densify(&[2, 2], &[0, 0], &dense, &[0.0; 4]).is_err());
        assert!(densify(&[2, 3], &[0, 1], &dense, &[0.0; 6]).is_err());
    }
}
