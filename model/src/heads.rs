//! Update heads (design.md §7.7): what one feedback step predicts from the Point Transformer's
//! per-vertex features `h` (`[V↓, 32]`).
//!
//! - **Low-res vertices** (coupled multi-resolution: only these move): a residual
//!   `Δxyz = MLP(h)` and a new query embedding `Linear(h)` for the next step's fusion.
//! - **Faces of the subdivided mesh**: `h` is interpolated to the high-res vertices with the
//!   subdivision's barycentric tables, the three corner features are concatenated in face-vertex
//!   order (`3·32`), and the source-image features sampled at the projected face centroid are
//!   appended per view (`N·D`, zeroed where the face is not fully visible in that view). Four
//!   heads map this to `so3`, `scale`, `offset` and `rgb`, each added to the **constant** initial
//!   value (0, 1, 0, 0), not to the previous step's: faces are re-predicted every step; only the
//!   vertices accumulate.
//!
//! The last layers of the xyz, so3, scale and offset heads start at U(±1e-5) with zero bias, so
//! the first steps barely move the template; the rgb head keeps the default initialisation.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::module::linear;
use burn::tensor::{Device, IndexingUpdateOp, Int, Tensor};
use lifegom_ops::activation::relu;

use crate::norm_folds::NormFolds;
use lifegom_ops::activation::Activation;
use lifegom_ops::linear_op;
use lifegom_render::gom::GomParams;
use lifegom_render::select::select_rows;

/// `Linear → ReLU → Linear`, named `l0`/`l2` after the reference's `Sequential` indices.
#[derive(Module, Debug)]
pub struct Mlp {
    l0: Linear,
    l2: Linear,
}

/// How the last layer of an [`Mlp`] starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LastLayerInit {
    /// Weights U(±1e-5), bias 0: the head's output starts at (almost) zero.
    NearZero,
    /// The framework default (kaiming-uniform, bound `1/√fan_in`).
    Default,
}

impl Mlp {
    fn new(
        input: usize,
        hidden: usize,
        output: usize,
        last: LastLayerInit,
        device: &Device,
    ) -> Self {
        let l0 = LinearConfig::new(input, hidden).init(device);
        let l2 = match last {
            LastLayerInit::Default => LinearConfig::new(hidden, output).init(device),
            LastLayerInit::NearZero => {
                let mut l = LinearConfig::new(hidden, output)
                    .with_initializer(Initializer::Uniform {
                        min: -1e-5,
                        max: 1e-5,
                    })
                    .init(device);
                l.bias = Some(Param::from_tensor(Tensor::zeros([output], device)));
                l
            }
        };
        Self { l0, l2 }
    }

    /// `[.., input] → [.., output]`, both layers shared through `folds` (a reconstruction's
    /// feedback steps run it once each).
    pub fn forward<'a>(&'a self, folds: &NormFolds<'a>, x: Tensor<2>) -> Tensor<2> {
        folds.apply(&self.l2, folds.apply_with(&self.l0, x, Activation::Relu))
    }
}

/// Sizes of the update heads.
#[derive(Config, Debug)]
pub struct UpdateHeadsConfig {
    /// Width of the Point Transformer's per-vertex output (32).
    #[config(default = 32)]
    pub point_dim: usize,
    /// Width of the per-vertex embedding and of one view's image feature (1152).
    pub feature_dim: usize,
    /// Number of source views N.
    pub num_views: usize,
    /// Hidden width of every head (32).
    #[config(default = 32)]
    pub hidden: usize,
}

impl UpdateHeadsConfig {
    /// Width of a face's input: three corner features and one image feature per view.
    pub fn face_input_dim(&self) -> usize {
        3 * self.point_dim + self.num_views * self.feature_dim
    }

    /// Builds the heads.
    pub fn init(&self, device: &Device) -> UpdateHeads {
        let g = self.face_input_dim();
        let h = self.hidden;
        UpdateHeads {
            xyz: Mlp::new(self.point_dim, h, 3, LastLayerInit::NearZero, device),
            embed: LinearConfig::new(self.point_dim, self.feature_dim).init(device),
            so3: Mlp::new(g, h, 3, LastLayerInit::NearZero, device),
            scale: Mlp::new(g, h, 3, LastLayerInit::NearZero, device),
            offset: Mlp::new(g, h, 3, LastLayerInit::NearZero, device),
            rgb: Mlp::new(g, h, 3, LastLayerInit::Default, device),
        }
    }
}

/// See [`UpdateHeadsConfig`].
#[derive(Module, Debug)]
pub struct UpdateHeads {
    /// Residual low-res vertex update.
    pub xyz: Mlp,
    /// New per-vertex query embedding.
    pub embed: Linear,
    /// Face rotation (axis-angle in the Steiner frame).
    pub so3: Mlp,
    /// Face scales.
    pub scale: Mlp,
    /// Face offsets in the Steiner frame.
    pub offset: Mlp,
    /// Face colours.
    pub rgb: Mlp,
}

/// What a step predicts for the low-res vertices.
#[derive(Debug, Clone)]
pub struct VertexUpdate {
    /// `Δxyz`, `[V↓, 3]`: added to the current canonical vertices.
    pub delta_xyz: Tensor<2>,
    /// The next embedding, `[V↓, D]`: replaces the current one.
    pub embed: Tensor<2>,
}

impl UpdateHeads {
    /// Vertex update from the per-vertex features `h` `[V↓, point_dim]`, the layers shared
    /// through `folds` (one gradient product per layer for all of a reconstruction's feedback
    /// steps on devices).
    pub fn vertices<'a>(&'a self, folds: &NormFolds<'a>, h: Tensor<2>) -> VertexUpdate {
        VertexUpdate {
            delta_xyz: self.xyz.forward(folds, h.clone()),
            embed: folds.apply(&self.embed, h),
        }
    }

    /// Face parameters from the face inputs (see [`face_inputs`]): the constant init (so3 0,
    /// scale 1, offset 0, rgb 0, opacity 1) plus each head's output.
    ///
    /// The four heads' first layers run as **one** product over their concatenated weights
    /// (`[G, 4·hidden]`): the face inputs (`G = 3·32 + N·1152` wide, one row per high-res face)
    /// are by far the largest operand of a feedback step, and one product reads them once
    /// instead of four times, forward and backward. That product is split by rows of the weight
    /// into the corner block and the image block, `z = c·W_c + m·W_m + b`, which is the product
    /// with `[c ‖ m]` without ever building the `[F, G]` concatenation (nor, in the backward,
    /// slicing its gradient apart again). The second layers run as one block-diagonal product
    /// likewise. The parameters keep their own names and shapes, so
    /// checkpoints and their import are unchanged; the result equals four separate heads on the
    /// concatenated input up to float summation order (tested below). The stacked first layers
    /// and the block-diagonal second layers are made once per `folds` (a reconstruction's
    /// feedback steps share them; on a GPU each is a few concatenation launches, and their
    /// backward as many slices).
    pub fn faces<'a>(&'a self, folds: &NormFolds<'a>, inputs: FaceInputs) -> GomParams {
        let FaceInputs { corners, images } = inputs;
        let [f, corner_width] = corners.dims();
        let device = corners.device();
        let init = GomParams::init(f, &device);
        let heads = [&self.so3, &self.scale, &self.offset, &self.rgb];
        let (w_corners, w_images, bias) = folds.keep(&self.so3.l0, "heads: first layers", || {
            let weight = lifegom_render::split::join_columns(
                heads.iter().map(|m| m.l0.weight.val()).collect(),
            );
            // The corner rows and the image rows, split once per reconstruction: rows of a
            // row-major `[G, O]` are column blocks of its `[1, G·O]` view, and one split's
            // backward is one join, where a row slice per feedback step costs a zero fill, a
            // slice-assign and a sum each.
            let [g, o] = weight.dims();
            let mut rows = lifegom_render::split::split_columns(
                weight.reshape([1, g * o]),
                &[corner_width * o, (g - corner_width) * o],
            )
            .into_iter();
            let mut next = |height: usize| rows.next().expect("two blocks").reshape([height, o]);
            let (w_corners, w_images) = (next(corner_width), next(g - corner_width));
            let bias = heads
                .iter()
                .map(|m| m.l0.bias.as_ref().map(|b| b.val()))
                .collect::<Option<Vec<_>>>()
                .map(lifegom_render::split::join_columns);
            (w_corners, w_images, bias)
        });
        let first = match images {
            // The image block is the large product: on the CPU backends it runs as the Linear op.
            FaceImages::Dense(images) => {
                linear_op::affine(images, w_images, bias) + linear(corners, w_corners, None)
            }
            FaceImages::Visible(visible) => {
                linear_op::affine(corners, w_corners, bias) + visible.product(w_images, f)
            }
        };
        let hidden = relu(first);
        // The second layers as one block-diagonal product `[F, 4·hidden] · [4·hidden, 12]`,
        // whose output is split by head: slicing `hidden` by head instead costs, in the
        // backward, one zeroed `[F, 4·hidden]` gradient per head and three sums of them, far
        // more than the product's zero blocks.
        let (second, second_bias) = folds.keep(&self.so3.l2, "heads: second layers", || {
            let second = block_diagonal(heads.iter().map(|m| m.l2.weight.val()).collect());
            let second_bias = heads
                .iter()
                .map(|m| m.l2.bias.as_ref().map(|b| b.val()))
                .collect::<Option<Vec<_>>>()
                .map(lifegom_render::split::join_columns);
            (second, second_bias)
        });
        let outputs = match second_bias {
            Some(bias) => folds
                .shared(&self.so3.l2, "heads: second layers", || (second, bias))
                .forward(hidden),
            None => linear_op::affine(hidden, second, None),
        };
        // One split for the four heads' columns: on a GPU one launch each way, where a slice
        // per head costs a copy forward and a zero fill, a slice-assign and a sum backward.
        let widths: Vec<usize> = heads.iter().map(|m| m.l2.weight.dims()[1]).collect();
        let mut out = lifegom_render::split::split_columns(outputs, &widths).into_iter();
        let mut next = || out.next().expect("four heads");
        GomParams {
            so3: init.so3 + next(),
            scales: init.scales + next(),
            offsets: init.offsets + next(),
            colors: init.colors + next(),
            opacities: init.opacities,
        }
    }
}

/// The matrices `blocks` (`[rows_k, cols_k]`) on the diagonal of one `[Σ rows, Σ cols]` matrix,
/// zero elsewhere.
fn block_diagonal(blocks: Vec<Tensor<2>>) -> Tensor<2> {
    let widths: Vec<usize> = blocks.iter().map(|b| b.dims()[1]).collect();
    let total: usize = widths.iter().sum();
    let mut before = 0;
    let rows = blocks
        .into_iter()
        .zip(&widths)
        .map(|(block, &width)| {
            let [rows, _] = block.dims();
            let device = block.device();
            let after = total - before - width;
            let zeros = |cols: usize| (cols > 0).then(|| Tensor::zeros([rows, cols], &device));
            let row: Vec<Tensor<2>> = [zeros(before), Some(block), zeros(after)]
                .into_iter()
                .flatten()
                .collect();
            before += width;
            Tensor::cat(row, 1)
        })
        .collect();
    Tensor::cat(rows, 0)
}

/// Each high-res face's head input (design.md §7.7) as its two blocks: the official code's
/// `[F, 3P + N·D]` input is [`FaceInputs::concatenated`], which [`UpdateHeads::faces`] never
/// needs to build.
#[derive(Debug, Clone)]
pub struct FaceInputs {
    /// The three corners' point features in face-vertex order, `[F, 3P]`.
    pub corners: Tensor<2>,
    /// The source-image features of each view.
    pub images: FaceImages,
}

impl FaceInputs {
    /// `[corners ‖ images]`, `[F, 3P + N·D]`: the input as the official code builds it.
    pub fn concatenated(self) -> Tensor<2> {
        let [f, _] = self.corners.dims();
        Tensor::cat(vec![self.corners, self.images.dense(f)], 1)
    }
}

/// The image block of the face inputs, in one of two layouts with the same meaning.
// One value per feedback step, moved into the heads: its size (tensor handles are hundreds of
// bytes) costs nothing, and boxing a variant would only add an allocation.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum FaceImages {
    /// `[F, N·D]`, view after view, zero for a view in which the face is not fully visible:
    /// the official layout.
    Dense(Tensor<2>),
    /// Only the (face, view) pairs in which the face is visible (design.md §7.7).
    Visible(VisibleFaceImages),
}

impl FaceImages {
    /// The [`FaceImages::Dense`] layout, `[F, N·D]`, for `faces` faces.
    pub fn dense(self, faces: usize) -> Tensor<2> {
        match self {
            Self::Dense(images) => images,
            Self::Visible(visible) => visible.dense(faces),
        }
    }
}

/// The visible (face, view) pairs' image features. A face hidden in a view has a zero image
/// feature there, and its rows of the first layer's product are zero; at the quickstart's 96²
/// a view sees 9–14 % of the 9,816 faces whole, so the dense product is mostly zeros.
///
/// Row `r` of view `v` is the `r`-th face visible in `v`; views with fewer visible faces than
/// the most are padded with rows that sample outside every map (zero features, zero gradients)
/// and belong to no face.
#[derive(Debug, Clone)]
pub struct VisibleFaceImages {
    /// `[R, N, D]`: row `r` of view `v` is the feature of face `faces[v·R + r]` in view `v`.
    pub features: Tensor<3>,
    /// `[N·R]`, view-major: the face each row belongs to, or `F` for a padding row.
    pub faces: Tensor<1, Int>,
}

impl VisibleFaceImages {
    /// `Σ_v images_v · W_v` as `[F, O]` for the image block's weight rows `weight` `[N·D, O]`:
    /// one product per view over its visible rows, added into each row's face. Equal to the
    /// dense `[F, N·D] · [N·D, O]` up to the order of the sums (the dense one adds zeros).
    fn product(self, weight: Tensor<2>, faces: usize) -> Tensor<2> {
        let [r, n, d] = self.features.dims();
        let [_, o] = weight.dims();
        let per_view = self
            .features
            .swap_dims(0, 1)
            .matmul(weight.reshape([n, d, o]))
            .reshape([n * r, o]);
        Self::scatter(per_view, self.faces, faces)
    }

    /// `[F, N·D]` with each visible pair's feature in its face's row and view block.
    fn dense(self, faces: usize) -> Tensor<2> {
        let [r, n, d] = self.features.dims();
        let views = (0..n)
            .map(|v| {
                let rows = self.features.clone().narrow(1, v, 1).reshape([r, d]);
                Self::scatter(rows, self.faces.clone().narrow(0, v * r, r), faces)
            })
            .collect();
        Tensor::cat(views, 1)
    }

    /// Rows `values` `[K, C]` added into a zero `[F, C]` at `faces` (`F` drops the row).
    fn scatter(values: Tensor<2>, faces_of_rows: Tensor<1, Int>, faces: usize) -> Tensor<2> {
        let [_, c] = values.dims();
        let device = values.device();
        Tensor::zeros([faces + 1, c], &device)
            .select_assign(0, faces_of_rows, values, IndexingUpdateOp::Add)
            .narrow(0, 0, faces)
    }
}

/// Builds each high-res face's head input (design.md §7.7).
///
/// - `h` `[V↓, P]`: per low-res vertex features;
/// - `highres_index` `[Vh·3]`, `highres_weight` `[Vh, 3]`: the subdivision's barycentric tables
///   (each high-res vertex as ≤3 weighted low-res vertices);
/// - `faces` `[F·3]`: high-res face corners, in face-vertex order;
/// - `image_features` `[F, N, D]`: source-image features at each face's projected centroid,
///   already zero in a view where the face is not fully visible (the reconstructor samples
///   hidden faces outside the maps, [`lifegom_ops::sampling::hide_invisible`]).
pub fn face_inputs(
    h: Tensor<2>,
    highres_index: Tensor<1, Int>,
    highres_weight: Tensor<2>,
    faces: Tensor<1, Int>,
    image_features: Tensor<3>,
) -> FaceInputs {
    let h_hr = highres_features(h, highres_index, highres_weight);
    face_inputs_from_highres(h_hr, faces, image_features)
}

/// The per-vertex features carried to the high-res vertices, `[V↓, P] → [Vh, P]`, through the
/// subdivision's barycentric tables: the part of [`face_inputs`] shared by every block of faces.
pub fn highres_features(
    h: Tensor<2>,
    highres_index: Tensor<1, Int>,
    highres_weight: Tensor<2>,
) -> Tensor<2> {
    let [_, p] = h.dims();
    let [vh, k] = highres_weight.dims();
    (select_rows(h, 0, highres_index).reshape([vh, k, p]) * highres_weight.reshape([vh, k, 1]))
        .sum_dim(1)
        .reshape([vh, p])
}

/// [`face_inputs`] for the faces `faces` (`[F·3]` corners) given the high-res vertex features
/// of [`highres_features`] and those faces' image features `[F, N, D]`.
pub fn face_inputs_from_highres(
    h_hr: Tensor<2>,
    faces: Tensor<1, Int>,
    image_features: Tensor<3>,
) -> FaceInputs {
    let [f, n, d] = image_features.dims();
    FaceInputs {
        corners: face_corners(h_hr, faces),
        images: FaceImages::Dense(image_features.reshape([f, n * d])),
    }
}

/// The corner block of the face inputs, `[F, 3P]`: the high-res vertex features `h_hr`
/// (`[Vh, P]`, [`highres_features`]) of each face's three corners `faces` (`[F·3]`).
pub fn face_corners(h_hr: Tensor<2>, faces: Tensor<1, Int>) -> Tensor<2> {
    let [_, p] = h_hr.dims();
    let [corners] = faces.dims();
    select_rows(h_hr, 0, faces).reshape([corners / 3, 3 * p])
}

/// Largest number of floats in one block's `[faces, N·D]` image features: the face stage
/// (sampling, [`face_inputs`], [`UpdateHeads::faces`]) runs block after block of faces below
/// it, and below what one buffer of the device holds
/// ([`lifegom_render::device::max_buffer_bytes`]: wgpu refused the 6 GB `[438,720, 3·1152]`
/// features of the paper network at two subdivisions on an H100, lavapipe holds 128 MiB). Every
/// preset that trains on a CPU fits in one block, so its ops, and its numerics, are those of
/// the unblocked stage.
pub const FACE_BLOCK_FLOATS: usize = 1 << 28;

/// Faces per block of the face stage for `faces` faces of `width` image-feature floats each
/// on `device`, with at most `cap` floats in one block's features besides
/// [`FACE_BLOCK_FLOATS`]; `faces` itself when they fit one block.
pub fn faces_per_block(device: &Device, faces: usize, width: usize, cap: usize) -> usize {
    lifegom_render::device::rows_per_block(device, faces, width, cap.min(FACE_BLOCK_FLOATS))
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::{Distribution, TensorData};
    use lifegom_render::mesh::MeshTopology;
    use lifegom_render::subdivision::{Subdivision, SubdivisionTables};

    use lifegom_render::testing::read;

    /// Two triangles sharing an edge (4 low-res vertices), subdivided `levels` times: the
    /// subdivision's tables, the high-res faces `[F·3]`, and `F`.
    fn two_triangles(levels: u32, device: &Device) -> (SubdivisionTables, Tensor<1, Int>, usize) {
        let topo = MeshTopology::new(vec![[0, 1, 2], [2, 1, 3]], 4).unwrap();
        let sub = Subdivision::new(&topo, levels).unwrap();
        (
            sub.tables(device),
            sub.highres.face_index_tensor(device),
            sub.highres.faces.len(),
        )
    }

    /// `got` equals `reference` within 1e-5 relative (float summation order).
    fn assert_close(got: &[f32], reference: &[f32], what: &str) {
        assert_eq!(got.len(), reference.len(), "{what}");
        for (i, (x, y)) in got.iter().zip(reference).enumerate() {
            assert!(
                (x - y).abs() <= 1e-5 * (1.0 + y.abs()),
                "{what}[{i}]: {x} vs reference {y}"
            );
        }
    }

    fn check(device: &Device) {
        let cfg = UpdateHeadsConfig::new(8, 2)
            .with_point_dim(4)
            .with_hidden(6);
        let heads = cfg.init(device);
        // Near-zero heads: the first step barely moves vertices and faces start at their init.
        let h = Tensor::<2>::random([5, 4], Distribution::Normal(0.0, 1.0), device);
        let v = heads.vertices(&NormFolds::new(), h.clone());
        assert_eq!(v.delta_xyz.dims(), [5, 3]);
        assert_eq!(v.embed.dims(), [5, 8]);
        assert!(read(v.delta_xyz).iter().all(|x| x.abs() < 1e-3));

        let (tables, faces, f) = two_triangles(1, device);
        let h4 = Tensor::<2>::random([4, 4], Distribution::Normal(0.0, 1.0), device);
        let feats = Tensor::<3>::random([f, 2, 8], Distribution::Normal(0.0, 1.0), device);
        let inputs = face_inputs(
            h4.clone(),
            tables.index.clone(),
            tables.weight.clone(),
            faces,
            feats.clone(),
        );
        assert_eq!(inputs.corners.dims(), [f, 12]);
        assert_eq!(
            inputs.clone().concatenated().dims(),
            [f, cfg.face_input_dim()]
        );
        // The image block is the features, view after view.
        assert_eq!(
            read(inputs.images.clone().dense(f)),
            read(feats.reshape([f, 16]))
        );
        let row0 = &read(inputs.corners.clone())[..12];
        // Corner 0 of child face 0 is low-res vertex 0 itself: its feature is copied exactly.
        let h4v = read(h4);
        for c in 0..4 {
            assert!((row0[c] - h4v[c]).abs() < 1e-6);
        }
        let params = heads.faces(&NormFolds::new(), inputs);
        let scales = read(params.scales);
        assert!(
            scales.iter().all(|s| (s - 1.0).abs() < 1e-3),
            "scale starts at 1"
        );
        assert_eq!(params.colors.dims(), [f, 3]);
    }

    /// The fused first layer, split into the corner and image blocks, gives the four separate
    /// heads' outputs and gradients on the concatenated input (inputs and every parameter), up
    /// to float summation order.
    fn fused_faces_equal_separate_heads(device: &Device) {
        let ad = device.clone().autodiff();
        let heads = UpdateHeadsConfig::new(16, 3)
            .with_point_dim(5)
            .with_hidden(7)
            .init(&ad);
        let corners =
            Tensor::<2>::random([11, 3 * 5], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let images =
            Tensor::<2>::random([11, 3 * 16], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let x = Tensor::cat(vec![corners.clone(), images.clone()], 1);
        let w = Tensor::<2>::random([11, 3], Distribution::Normal(0.0, 1.0), &ad);
        let fused = heads.faces(
            &NormFolds::new(),
            FaceInputs {
                corners: corners.clone(),
                images: FaceImages::Dense(images.clone()),
            },
        );
        let separate = [
            heads.so3.forward(&NormFolds::new(), x.clone()),
            heads.scale.forward(&NormFolds::new(), x.clone()) + 1.0,
            heads.offset.forward(&NormFolds::new(), x.clone()),
            heads.rgb.forward(&NormFolds::new(), x.clone()),
        ];
        let fused_out = [fused.so3, fused.scales, fused.offsets, fused.colors];
        let loss = |outs: &[Tensor<2>]| {
            outs.iter()
                .enumerate()
                .map(|(k, o)| (o.clone() * w.clone().mul_scalar(k as f32 + 1.0)).sum())
                .reduce(|a, b| a + b)
                .expect("four heads")
        };
        for (k, (a, b)) in fused_out.iter().zip(&separate).enumerate() {
            assert_close(
                &read(a.clone()),
                &read(b.clone()),
                &format!("head {k} output"),
            );
        }
        let grads_fused = loss(&fused_out).backward();
        let grads_sep = loss(&separate).backward();
        // The separate heads read the concatenation, whose gradient is the two blocks'.
        let block_grads = |grads: &burn::tensor::Gradients| {
            Tensor::cat(
                vec![
                    corners.grad(grads).expect("corner gradient"),
                    images.grad(grads).expect("image gradient"),
                ],
                1,
            )
        };
        assert_close(
            &read(block_grads(&grads_fused)),
            &read(block_grads(&grads_sep)),
            "input gradient",
        );
        for (name, m) in [
            ("so3", &heads.so3),
            ("scale", &heads.scale),
            ("offset", &heads.offset),
            ("rgb", &heads.rgb),
        ] {
            for (layer, l) in [("l0", &m.l0), ("l2", &m.l2)] {
                let wf = l.weight.val().grad(&grads_fused).expect("weight gradient");
                let ws = l.weight.val().grad(&grads_sep).expect("weight gradient");
                assert_close(
                    &read(wf),
                    &read(ws),
                    &format!("{name}.{layer}.weight gradient"),
                );
                let bias = l.bias.as_ref().expect("heads have biases").val();
                let bf = bias.grad(&grads_fused).expect("bias gradient");
                let bs = bias.grad(&grads_sep).expect("bias gradient");
                assert_close(
                    &read(bf),
                    &read(bs),
                    &format!("{name}.{layer}.bias gradient"),
                );
            }
        }
    }

    /// The face stage run block after block of faces (as the reconstructor does past
    /// [`FACE_BLOCK_FLOATS`]) gives the unblocked stage's parameters.
    fn blocked_faces_equal_one_block(device: &Device) {
        let heads = UpdateHeadsConfig::new(16, 2)
            .with_point_dim(5)
            .with_hidden(7)
            .init(device);
        let (tables, faces, f) = two_triangles(2, device);
        let h = Tensor::<2>::random([4, 5], Distribution::Normal(0.0, 1.0), device);
        let feats = Tensor::<3>::random([f, 2, 16], Distribution::Normal(0.0, 1.0), device);
        let h_hr = highres_features(h, tables.index.clone(), tables.weight.clone());
        let whole = heads.faces(
            &NormFolds::new(),
            face_inputs_from_highres(h_hr.clone(), faces.clone(), feats.clone()),
        );
        let block = 5;
        let blocks = (0..f)
            .step_by(block)
            .map(|start| {
                let len = block.min(f - start);
                heads.faces(
                    &NormFolds::new(),
                    face_inputs_from_highres(
                        h_hr.clone(),
                        faces.clone().narrow(0, 3 * start, 3 * len),
                        feats.clone().narrow(0, start, len),
                    ),
                )
            })
            .collect();
        let blocked = GomParams::cat(blocks, device);
        for (a, b) in [
            (whole.so3, blocked.so3),
            (whole.scales, blocked.scales),
            (whole.offsets, blocked.offsets),
            (whole.colors, blocked.colors),
        ] {
            assert_eq!(a.dims(), [f, 3]);
            let (a, b) = (read(a), read(b));
            assert!(
                a.iter()
                    .zip(&b)
                    .all(|(p, q)| (p - q).abs() <= 1e-6 * (1.0 + q.abs())),
                "blocked {b:?} vs whole {a:?}"
            );
        }
        assert_eq!(read(whole.opacities), read(blocked.opacities));
        assert_eq!(faces_per_block(device, f, 32, usize::MAX), f);
        assert_eq!(
            faces_per_block(device, 10, FACE_BLOCK_FLOATS / 3, usize::MAX),
            3
        );
        assert_eq!(faces_per_block(device, 10, 8, 20), 2);
        assert_eq!(faces_per_block(device, 0, 32, usize::MAX), 1);
    }

    /// The visible rows' layout gives the dense layout's face parameters and gradients (the
    /// corners, every parameter, and each visible pair's image feature), up to float summation
    /// order; the dense layout rebuilt from it is the dense input exactly.
    fn visible_rows_equal_dense_images(device: &Device) {
        let ad = device.clone().autodiff();
        let (f, n, d, p) = (13usize, 3usize, 6usize, 4usize);
        let heads = UpdateHeadsConfig::new(d, n)
            .with_point_dim(p)
            .with_hidden(5)
            .init(&ad);
        // Face k is visible in view v for a fixed irregular pattern: view 0 sees 6 faces, view 1
        // sees 2, view 2 none (every row of view 2 is padding).
        let visible = |face: usize, view: usize| match view {
            0 => face.is_multiple_of(2),
            1 => face == 3 || face == 11,
            _ => false,
        };
        let mut rng = lifegom_render::rng::Rng::new(5);
        let full: Vec<f32> = (0..f * n * d).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let dense_host: Vec<f32> = (0..f * n * d)
            .map(|i| {
                let (face, view) = (i / (n * d), (i / d) % n);
                if visible(face, view) { full[i] } else { 0.0 }
            })
            .collect();
        let rows: Vec<Vec<usize>> = (0..n)
            .map(|view| (0..f).filter(|&face| visible(face, view)).collect())
            .collect();
        let r = rows.iter().map(Vec::len).max().unwrap();
        let mut features = vec![0.0f32; r * n * d];
        let mut owners = vec![f as i64; n * r];
        for (view, faces) in rows.iter().enumerate() {
            for (k, &face) in faces.iter().enumerate() {
                let src = (face * n + view) * d;
                features[(k * n + view) * d..][..d].copy_from_slice(&full[src..src + d]);
                owners[view * r + k] = face as i64;
            }
        }
        let dense = Tensor::<2>::from_data(TensorData::new(dense_host.clone(), [f, n * d]), &ad)
            .require_grad();
        let rows_t =
            Tensor::<3>::from_data(TensorData::new(features, [r, n, d]), &ad).require_grad();
        let owners = Tensor::<1, Int>::from_data(TensorData::new(owners, [n * r]), &ad);
        let corners =
            Tensor::<2>::random([f, 3 * p], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let visible_images = VisibleFaceImages {
            features: rows_t.clone(),
            faces: owners,
        };
        assert_eq!(read(visible_images.clone().dense(f)), dense_host);

        let w = Tensor::<2>::random([f, 3], Distribution::Normal(0.0, 1.0), &ad);
        let run = |images: FaceImages| {
            let out = heads.faces(
                &NormFolds::new(),
                FaceInputs {
                    corners: corners.clone(),
                    images,
                },
            );
            let loss = [out.so3, out.scales, out.offsets, out.colors]
                .into_iter()
                .enumerate()
                .map(|(k, o)| (o * w.clone().mul_scalar(k as f32 + 1.0)).sum())
                .reduce(|a, b| a + b)
                .expect("four heads");
            (read(loss.clone()), loss.backward())
        };
        let (loss_dense, g_dense) = run(FaceImages::Dense(dense.clone()));
        let (loss_rows, g_rows) = run(FaceImages::Visible(visible_images));
        assert_close(&loss_rows, &loss_dense, "loss");
        assert_close(
            &read(corners.grad(&g_rows).unwrap()),
            &read(corners.grad(&g_dense).unwrap()),
            "corner gradient",
        );
        for m in [&heads.so3, &heads.scale, &heads.offset, &heads.rgb] {
            for l in [&m.l0, &m.l2] {
                assert_close(
                    &read(l.weight.val().grad(&g_rows).unwrap()),
                    &read(l.weight.val().grad(&g_dense).unwrap()),
                    "weight gradient",
                );
            }
        }
        let grad_dense = read(dense.grad(&g_dense).unwrap());
        let grad_rows = read(rows_t.grad(&g_rows).unwrap());
        for (view, faces) in rows.iter().enumerate() {
            for k in 0..r {
                let got = &grad_rows[(k * n + view) * d..][..d];
                match faces.get(k) {
                    Some(&face) => {
                        assert_close(got, &grad_dense[(face * n + view) * d..][..d], "image");
                    }
                    None => assert!(got.iter().all(|&g| g == 0.0), "padding row gradient"),
                }
            }
        }
    }

    lifegom_render::cpu_backend_tests!(heads => check);
    lifegom_render::cpu_backend_tests!(visible_rows => visible_rows_equal_dense_images);
    lifegom_render::cpu_backend_tests!(blocked_faces => blocked_faces_equal_one_block);
    lifegom_render::cpu_backend_tests!(fused_heads => fused_faces_equal_separate_heads);

    /// Two feedback steps' face heads with one [`NormFolds`] (the stacked weights made once, as
    /// a reconstruction on a GPU makes them) against fresh weights each step: the same outputs,
    /// and the same gradients of the inputs and of every parameter up to float order.
    fn kept_weights_equal_fresh_ones(device: &Device) {
        let ad = device.clone().autodiff();
        let heads = UpdateHeadsConfig::new(16, 3)
            .with_point_dim(5)
            .with_hidden(7)
            .init(&ad);
        let inputs: Vec<(Tensor<2>, Tensor<2>)> = (0..2)
            .map(|_| {
                let c = Tensor::<2>::random([11, 15], Distribution::Normal(0.0, 1.0), &ad);
                let m = Tensor::<2>::random([11, 48], Distribution::Normal(0.0, 1.0), &ad);
                (c.require_grad(), m.require_grad())
            })
            .collect();
        let run = |kept: bool| {
            let folds = NormFolds::new();
            let mut loss = None;
            for (k, (c, m)) in inputs.iter().enumerate() {
                let face = FaceInputs {
                    corners: c.clone(),
                    images: FaceImages::Dense(m.clone()),
                };
                let p = if kept {
                    heads.faces(&folds, face)
                } else {
                    heads.faces(&NormFolds::new(), face)
                };
                let term = (p.so3 + p.scales.mul_scalar(2.0) + p.offsets.mul_scalar(3.0)
                    - p.colors.mul_scalar(k as f32 + 0.5))
                .sum();
                loss = Some(match loss {
                    Some(l) => l + term,
                    None => term,
                });
            }
            let loss = loss.expect("two steps");
            let grads = loss.clone().backward();
            let mut all = read(loss);
            for (c, m) in &inputs {
                all.extend(read(c.grad(&grads).expect("corner gradient")));
                all.extend(read(m.grad(&grads).expect("image gradient")));
            }
            for mlp in [&heads.so3, &heads.scale, &heads.offset, &heads.rgb] {
                for layer in [&mlp.l0, &mlp.l2] {
                    all.extend(read(
                        layer.weight.val().grad(&grads).expect("weight gradient"),
                    ));
                    let bias = layer.bias.as_ref().expect("bias").val();
                    all.extend(read(bias.grad(&grads).expect("bias gradient")));
                }
            }
            all
        };
        assert_close(&run(true), &run(false), "kept against fresh weights");
    }

    lifegom_render::cpu_backend_tests!(kept_head_weights => kept_weights_equal_fresh_ones);

    #[test]
    fn kept_head_weights_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            kept_weights_equal_fresh_ones(&device);
        }
    }
}
