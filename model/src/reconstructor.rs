//! The reconstructor with learned iterative feedback (design.md §2.3–§2.4, §7).
//!
//! ```text
//! feats_src = Enc(I_src)                                   once, with gradients
//! state_0   = (xyz = canonical template, embed = learned per-vertex, faces = init)
//! R_0, M_0  = render(state_0) in every source view
//! for t in 1..=T:
//!     feats_ren = Enc(R_{t-1})                             no gradient
//!     state_t   = update(state_{t-1}, feats_src, feats_ren, M_{t-1})
//!     R_t, M_t  = render(state_t)                          kept for supervision
//! ```
//!
//! One update: pose the current low-res vertices into each view (LBS), project them, sample
//! the source and rendered feature maps there; blend each with the learned visibility
//! embedding (source: by the discrete triangle-ID visibility; rendered: by the sampled soft
//! alpha); fuse across views (shared weights, the rendered branch detached); run the Point
//! Transformer on the canonical vertices with `[source ‖ rendered]` features; predict `Δxyz`,
//! the next embedding, and the per-face Gaussian parameters of the subdivided mesh.
//!
//! **Coupled multi-resolution**: only the low-res vertices are state; the Gaussians live on the
//! `s`-times subdivided mesh given by the [`GomMesh`] the caller passes, so one trained model
//! serves any `s` (the reference trains with `s = 1` and tests with `s = 2`).

use std::thread::JoinHandle;

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Distribution, Int, Tensor, TensorData};
use glam::Affine3A;

use lifegom_render::camera::Camera;
use lifegom_render::device::{CostModel, on_pool_thread, rows_per_block};
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::mesh::MeshTopology;
use lifegom_render::rasterizer::{Gaussians, RasterSettings, composite_views};
use lifegom_render::readback;
use lifegom_render::skeleton::Skeleton;
use lifegom_render::skinning::skin_vertices;
use lifegom_render::visibility::{ViewSet, visibility_in_views};

use crate::avatar::Avatar;
use crate::encoder::{EncodedViews, ImageEncoder, ImageEncoderConfig};
use crate::error::{ModelError, Result};
use crate::fusion::{Fusion, FusionConfig, FusionMasks, FusionRun, RepeatedTokens};
use crate::heads::{
    FaceImages, FaceInputs, UpdateHeads, UpdateHeadsConfig, VisibleFaceImages, face_corners,
    faces_per_block, highres_features,
};
use crate::norm_folds::NormFolds;
use crate::point_transformer::{
    Hierarchy, HierarchyPlanning, HostHierarchy, PointTransformer, PointTransformerConfig,
    read_points,
};
use lifegom_ops::sampling::{hide_invisible, project_points, sample_single};
use lifegom_render::select::select_rows;
use lifegom_render::split::join_columns;

/// Width of the encoder's concatenated pyramid for a configuration (1152 for the paper's).
fn encoder_feature_dim(cfg: &ImageEncoderConfig) -> usize {
    cfg.resnet_channels().iter().sum::<usize>() + cfg.rgb_embed_channels
}

/// What a mesh is built for, which picks its subdivision level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshPurpose {
    /// Training (`subdivide_train`).
    Training,
    /// Inference and evaluation (`subdivide_test`).
    Inference,
}

/// Configuration of the [`Reconstructor`].
#[derive(Config, Debug)]
pub struct ReconstructorConfig {
    /// The image encoder.
    pub encoder: ImageEncoderConfig,
    /// The Point Transformer; its `in_dim` must be `3 + 2·feature_dim`.
    pub point_transformer: PointTransformerConfig,
    /// Number of source views N.
    pub num_views: usize,
    /// Attention heads of the fusion layers (must divide the feature width).
    #[config(default = 6)]
    pub n_heads: usize,
    /// Dropout of the fusion layers (training only).
    #[config(default = 0.1)]
    pub dropout: f64,
    /// Feedback steps T.
    #[config(default = 3)]
    pub iterations: usize,
    /// Subdivisions of the Gaussians' mesh in training (the reference forces 1).
    #[config(default = 1)]
    pub subdivide_train: u32,
    /// Subdivisions at inference (2 for THuman, 1 for AIST++). The weights do not depend on it.
    #[config(default = 2)]
    pub subdivide_test: u32,
}

impl ReconstructorConfig {
    /// The paper's network (1152 channels, 6 heads, the full Point Transformer) for N views.
    pub fn paper(num_views: usize) -> Self {
        let encoder = ImageEncoderConfig::new();
        let d = encoder_feature_dim(&encoder);
        Self::new(encoder, PointTransformerConfig::paper(3 + 2 * d), num_views)
    }

    /// A small network with every component, for CPU tests and quick runs.
    pub fn tiny(num_views: usize) -> Self {
        let encoder = ImageEncoderConfig::new()
            .with_width(0.125)
            .with_rgb_embed_channels(16);
        let d = encoder_feature_dim(&encoder);
        Self::new(encoder, PointTransformerConfig::tiny(3 + 2 * d), num_views).with_n_heads(4)
    }

    /// A mid-size network for CPU runs: encoder at ¼ width (288 channels), the paper's Point
    /// Transformer and fusion depth.
    pub fn cpu(num_views: usize) -> Self {
        let encoder = ImageEncoderConfig::new()
            .with_width(0.25)
            .with_rgb_embed_channels(32);
        let d = encoder_feature_dim(&encoder);
        Self::new(encoder, PointTransformerConfig::paper(3 + 2 * d), num_views)
    }

    /// The Gaussians' mesh for `purpose`: the low-res template subdivided `subdivide_train` or
    /// `subdivide_test` times (coupled multi-resolution: one model serves both).
    pub fn mesh(
        &self,
        lowres: &MeshTopology,
        purpose: MeshPurpose,
        device: &Device,
    ) -> Result<GomMesh> {
        let levels = match purpose {
            MeshPurpose::Training => self.subdivide_train,
            MeshPurpose::Inference => self.subdivide_test,
        };
        Ok(GomMesh::new(lowres, levels, device)?)
    }

    /// Width of one view's image feature.
    pub fn feature_dim(&self) -> usize {
        encoder_feature_dim(&self.encoder)
    }

    /// Builds the reconstructor for a template with `num_lowres_vertices` vertices (the
    /// per-vertex query embedding has one row per vertex).
    pub fn init(&self, num_lowres_vertices: usize, device: &Device) -> Result<Reconstructor> {
        let d = self.feature_dim();
        if self.point_transformer.in_dim != 3 + 2 * d {
            return Err(ModelError::InvalidInput {
                what: "point_transformer.in_dim",
                reason: format!(
                    "must be 3 + 2·{d} = {}, got {}",
                    3 + 2 * d,
                    self.point_transformer.in_dim
                ),
            });
        }
        if self.n_heads == 0 || !d.is_multiple_of(self.n_heads) {
            return Err(ModelError::InvalidInput {
                what: "n_heads",
                reason: format!("{} does not divide the feature width {d}", self.n_heads),
            });
        }
        if self.iterations == 0 {
            return Err(ModelError::InvalidInput {
                what: "iterations",
                reason: "at least one feedback step is needed".into(),
            });
        }
        let point_dim = self.point_transformer.planes[0];
        Ok(Reconstructor {
            encoder: self.encoder.init(device),
            fusion: FusionConfig::new(d)
                .with_n_heads(self.n_heads)
                .with_dropout(self.dropout)
                .init(device),
            point_transformer: self.point_transformer.init(device),
            heads: UpdateHeadsConfig::new(d, self.num_views)
                .with_point_dim(point_dim)
                .init(device),
            visibility_embed: Param::from_tensor(Tensor::zeros([d], device)),
            vertex_embed: Param::from_tensor(Tensor::random(
                [num_lowres_vertices, d],
                Distribution::Normal(0.0, 1.0),
                device,
            )),
            iterations: self.iterations,
            concurrency: HostConcurrency::default(),
            buffer_floats: usize::MAX,
            num_views: self.num_views,
        })
    }
}

/// The reconstructor: encoder, fusion, Point Transformer, update heads and the two learned
/// embeddings. See the module docs for the algorithm.
#[derive(Module, Debug)]
pub struct Reconstructor {
    /// Image encoder (source images with gradients, renders without).
    pub encoder: ImageEncoder,
    /// Multi-source fusion, shared by the source and rendered branches.
    pub fusion: Fusion,
    /// Point Transformer over the low-res canonical vertices.
    pub point_transformer: PointTransformer,
    /// Update heads.
    pub heads: UpdateHeads,
    /// Feature used where a vertex is not visible (`e_vis`), `[D]`, initialised to zeros.
    pub visibility_embed: Param<Tensor<1>>,
    /// Initial per-vertex query embedding, `[V↓, D]`, initialised N(0, 1).
    pub vertex_embed: Param<Tensor<2>>,
    iterations: usize,
    num_views: usize,
    #[module(skip)]
    concurrency: HostConcurrency,
    #[module(skip)]
    buffer_floats: usize,
}

/// How a forward pass on a host (CPU) device spreads a feedback step over threads, beyond the
/// rayon parallelism inside each op (design.md §7.4). The result is the same either way, up to
/// float summation order; on CubeCL devices every op is queued from the calling thread.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum HostConcurrency {
    /// Independent parts of a feedback step run side by side: the fusion's rendered branch as
    /// a rayon task beside its source branch.
    #[default]
    Branches,
    /// The branches one after the other, in program order (each op still on rayon's threads):
    /// for one process per core, and to measure what [`HostConcurrency::Branches`] gains.
    Sequential,
}

/// The person's body in canonical T-pose: low-res vertices and skinning weights.
#[derive(Debug, Clone)]
pub struct CanonicalSubject {
    /// Canonical low-res vertices, `[V↓, 3]` (the estimated body shape, not the clothed surface).
    pub canonical_vertices: Tensor<2>,
    /// Dense skinning weights, `[V↓, J]`.
    pub lbs_weights: Tensor<2>,
    /// The subject's skeleton (canonical joints), to pose the avatar later.
    pub skeleton: Skeleton,
}

/// The source views: images, cameras and the body pose seen in each.
#[derive(Debug, Clone)]
pub struct SourceViews {
    /// Background-composited images in [0, 1], `[N, 3, H, W]`.
    pub images: Tensor<4>,
    /// One camera per view, with the view's global body transform folded in.
    pub cameras: Vec<Camera>,
    /// Per view, one canonical-to-posed transform per joint (`Skeleton::skinning_transforms`).
    pub skinning: Vec<Vec<Affine3A>>,
    /// Background colour the images were composited on.
    pub background: [f32; 3],
}

impl SourceViews {
    fn check(&self, num_views: usize) -> Result<(u32, u32)> {
        let [n, c, h, w] = self.images.dims();
        let fail = |what, reason: String| Err(ModelError::InvalidInput { what, reason });
        if n != num_views || c != 3 {
            return fail(
                "images",
                format!(
                    "expected [{num_views}, 3, H, W], got {:?}",
                    self.images.dims()
                ),
            );
        }
        if self.cameras.len() != n || self.skinning.len() != n {
            return fail(
                "cameras/skinning",
                format!(
                    "{} images but {} cameras and {} poses",
                    n,
                    self.cameras.len(),
                    self.skinning.len()
                ),
            );
        }
        for (i, cam) in self.cameras.iter().enumerate() {
            cam.validate()?;
            if cam.width as usize != w || cam.height as usize != h {
                return fail(
                    "cameras",
                    format!(
                        "camera {i} is {}x{}, images are {w}x{h}",
                        cam.width, cam.height
                    ),
                );
            }
        }
        Ok((w as u32, h as u32))
    }
}

/// The reconstructor's state after a step.
#[derive(Debug, Clone)]
pub struct GomState {
    /// Canonical low-res vertices, `[V↓, 3]`.
    pub xyz: Tensor<2>,
    /// Per-vertex query embedding, `[V↓, D]`.
    pub embed: Tensor<2>,
    /// Per-face Gaussian parameters of the subdivided mesh.
    pub faces: GomParams,
}

/// Renders of the current state in the source views.
#[derive(Debug, Clone)]
pub struct SourceRenders {
    /// Composited as the reference does (`rgb·α + bg·(1−α)`), `[N, 3, H, W]`.
    pub rgb: Tensor<4>,
    /// Alpha, `[N, 1, H, W]`.
    pub alpha: Tensor<4>,
}

/// Views rendered beside the source views for supervision only
/// ([`Reconstructor::forward_with_targets`]): a camera and the skinning transforms of each.
#[derive(Debug, Clone, Default)]
pub struct TargetViews {
    /// One camera per view (of the source views' image size).
    pub cameras: Vec<Camera>,
    /// Per view, one canonical-to-posed transform per joint.
    pub skinning: Vec<Vec<Affine3A>>,
}

/// Everything a forward pass produces: the state after every step and its source renders.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// `state_1 … state_T`.
    pub states: Vec<GomState>,
    /// `R_1, M_1 … R_T, M_T` (for the training losses): each state rendered in the N source
    /// views, then in the target views of [`Reconstructor::forward_with_targets`], `[N + M, …]`.
    pub renders: Vec<SourceRenders>,
    /// Host wall time of each stage: `encode_sources`, `render_init`, then `step_t` per
    /// feedback step (update + re-render). Meaningful on eager backends (ndarray, Flex); a lazy
    /// backend only shows the time to enqueue.
    pub timings: Vec<(String, std::time::Duration)>,
}

impl Reconstruction {
    /// The final state.
    pub fn last(&self) -> &GomState {
        self.states
            .last()
            .expect("a reconstruction has at least one step")
    }
}

/// Renders `state` posed into each source view.
///
/// Views with the same skinning transforms (the N cameras of one frame, as in the THuman
/// setting) share one posed mesh and one set of Gaussians: skinning and the Gaussians-on-Mesh
/// geometry run once per distinct pose, not once per view, forward and backward (the rasterizers'
/// gradients add up on the shared Gaussians, which is the same sum the separate copies' gradients
/// made on the vertices).
pub fn render_views(
    mesh: &GomMesh,
    state_xyz: &Tensor<2>,
    faces: &GomParams,
    subject: &CanonicalSubject,
    cameras: &[Camera],
    skinning: &[Vec<Affine3A>],
    background: [f32; 3],
) -> Result<SourceRenders> {
    let _span = tracing::debug_span!("render_views", views = cameras.len()).entered();
    // Each run of consecutive views of one pose is one call of the renderer
    // ([`composite_views`], which batches the views where that saves launches).
    let mut rgb = Vec::new();
    let mut alpha = Vec::new();
    let mut posed_gaussians: Vec<(&[Affine3A], Gaussians)> = Vec::new();
    let mut start = 0;
    while start < cameras.len() {
        let pose = skinning[start].as_slice();
        let end = (start..cameras.len())
            .find(|&k| skinning[k] != pose)
            .unwrap_or(cameras.len());
        let known = posed_gaussians.iter().find(|(seen, _)| *seen == pose);
        let gaussians = match known {
            Some((_, gaussians)) => gaussians.clone(),
            None => {
                let posed = skin_vertices(state_xyz.clone(), subject.lbs_weights.clone(), pose)?;
                let gaussians = mesh.gaussians(posed, faces);
                posed_gaussians.push((pose, gaussians.clone()));
                gaussians
            }
        };
        let settings: Vec<RasterSettings> = cameras[start..end]
            .iter()
            .map(|&c| RasterSettings::new(c))
            .collect();
        let (run_rgb, run_alpha) = composite_views(&gaussians, &settings, background)?;
        rgb.push(run_rgb);
        alpha.push(run_alpha);
        start = end;
    }
    let join = |mut parts: Vec<Tensor<4>>| match parts.len() {
        1 => parts.pop().expect("one run"),
        _ => Tensor::cat(parts, 0),
    };
    Ok(SourceRenders {
        rgb: join(rgb).permute([0, 3, 1, 2]),
        alpha: join(alpha).permute([0, 3, 1, 2]),
    })
}

impl Reconstructor {
    /// Number of feedback steps.
    pub fn iterations(&self) -> usize {
        self.iterations
    }

    /// The same weights run for `t` feedback steps (the paper's Table 4 varies T at test time;
    /// `t = 0` is clamped to 1).
    pub fn with_iterations(mut self, t: usize) -> Self {
        self.iterations = t.max(1);
        self
    }

    /// How a host forward pass uses threads.
    pub fn concurrency(&self) -> HostConcurrency {
        self.concurrency
    }

    /// The same model with `concurrency`.
    pub fn with_concurrency(mut self, concurrency: HostConcurrency) -> Self {
        self.concurrency = concurrency;
        self
    }

    /// The most floats one buffer of the per-vertex stage (sampling and fusion) or the face
    /// stage holds, beside the device's own limit
    /// ([`lifegom_render::device::max_buffer_bytes`]): past it a stage runs block after block
    /// of vertices or faces. Unbounded by default.
    pub fn buffer_floats(&self) -> usize {
        self.buffer_floats
    }

    /// The same model with its stages' buffers held to `floats` (the blocks are then smaller:
    /// for tests, and to bound one op's memory).
    pub fn with_buffer_floats(mut self, floats: usize) -> Self {
        self.buffer_floats = floats;
        self
    }

    /// Reconstructs the avatar (inference): the forward pass, keeping only the final state.
    pub fn reconstruct(
        &self,
        subject: &CanonicalSubject,
        mesh: &GomMesh,
        sources: &SourceViews,
    ) -> Result<Avatar> {
        let last = self
            .forward(subject, mesh, sources)?
            .states
            .pop()
            .expect("T ≥ 1 steps");
        Ok(Avatar::new(
            last.xyz,
            last.faces,
            subject.lbs_weights.clone(),
            subject.skeleton.clone(),
            mesh.clone(),
        ))
    }

    /// Runs the encoder and `T` feedback steps; `mesh` fixes the subdivision level of the
    /// Gaussians (its low-res topology must be the subject's). On a CPU device the pass runs on
    /// one of rayon's threads (`lifegom_render::device::on_pool_thread`).
    pub fn forward(
        &self,
        subject: &CanonicalSubject,
        mesh: &GomMesh,
        sources: &SourceViews,
    ) -> Result<Reconstruction> {
        self.forward_with_targets(subject, mesh, sources, &TargetViews::default())
    }

    /// [`Self::forward`], each state also rendered in the `targets` views, after the source
    /// views in [`Reconstruction::renders`] (the training loss's target view). The feedback
    /// reads the source views only; on a CubeCL device a target of the sources' pose is
    /// rendered in the same rasterizer call as they are ([`render_views`]).
    pub fn forward_with_targets(
        &self,
        subject: &CanonicalSubject,
        mesh: &GomMesh,
        sources: &SourceViews,
        targets: &TargetViews,
    ) -> Result<Reconstruction> {
        on_pool_thread(&subject.canonical_vertices.device(), |parent| {
            self.forward_here(subject, mesh, sources, targets, parent)
        })
    }

    /// [`Reconstructor::forward_with_targets`] on the calling thread; its span is a child of
    /// `parent`.
    fn forward_here(
        &self,
        subject: &CanonicalSubject,
        mesh: &GomMesh,
        sources: &SourceViews,
        targets: &TargetViews,
        parent: &tracing::Span,
    ) -> Result<Reconstruction> {
        let _span = tracing::info_span!(
            parent: parent,
            "reconstruct",
            views = sources.cameras.len(),
            steps = self.iterations
        )
        .entered();
        let (width, height) = sources.check(self.num_views)?;
        if targets.cameras.len() != targets.skinning.len()
            || targets
                .cameras
                .iter()
                .any(|c| (c.width, c.height) != (width, height))
        {
            return Err(ModelError::InvalidInput {
                what: "targets",
                reason: format!(
                    "{} cameras and {} skinning sets; every target camera must be {width}×{height} like the sources",
                    targets.cameras.len(),
                    targets.skinning.len()
                ),
            });
        }
        let [v, _] = subject.canonical_vertices.dims();
        if v != self.vertex_embed.dims()[0] || v != mesh.subdivision.lowres.num_vertices {
            return Err(ModelError::InvalidInput {
                what: "subject",
                reason: format!(
                    "{v} canonical vertices, but the model has {} vertex embeddings and the mesh {} low-res vertices",
                    self.vertex_embed.dims()[0],
                    mesh.subdivision.lowres.num_vertices
                ),
            });
        }
        let device = subject.canonical_vertices.device();
        let mut clock = std::time::Instant::now();
        let mut timings = Vec::new();
        let mut lap = |name: String, timings: &mut Vec<(String, std::time::Duration)>| {
            timings.push((name, clock.elapsed()));
            clock = std::time::Instant::now();
        };
        // The BN folds of the encoder and the Point Transformer, made in their first pass and
        // kept for the others.
        let folds = NormFolds::new();
        let feats_src = {
            let _span = tracing::debug_span!("encode_sources").entered();
            self.encoder.encode(&folds, sources.images.clone())?
        };
        lap("encode_sources".into(), &mut timings);
        let mut state = GomState {
            xyz: subject.canonical_vertices.clone(),
            embed: self.vertex_embed.val(),
            faces: GomParams::init(mesh.num_gaussians(), &device),
        };
        let mut renders = render_views(
            mesh,
            &state.xyz,
            &state.faces,
            subject,
            &sources.cameras,
            &sources.skinning,
            sources.background,
        )?;
        lap("render_init".into(), &mut timings);
        let mut out = Reconstruction {
            states: Vec::new(),
            renders: Vec::new(),
            timings: Vec::new(),
        };
        // Where merged passes pay ([`CostModel`]) the targets are rendered with the sources, in
        // one rasterizer call per pose; elsewhere after the feedback loop, one render per state,
        // as the trainer rendered them before it passed its target here (the same ops in the
        // same order: the same gradients to the bit).
        let n = sources.cameras.len();
        let targets_with_sources =
            CostModel::of(&device).merge_passes() && !targets.cameras.is_empty();
        let (cameras, skinning) = if targets_with_sources {
            let cameras: Vec<Camera> = sources
                .cameras
                .iter()
                .chain(&targets.cameras)
                .copied()
                .collect();
            let skinning: Vec<Vec<Affine3A>> = sources
                .skinning
                .iter()
                .chain(&targets.skinning)
                .cloned()
                .collect();
            (cameras, skinning)
        } else {
            (sources.cameras.clone(), sources.skinning.clone())
        };
        for step in 0..self.iterations {
            let _span = tracing::debug_span!("feedback_step", step).entered();
            let planned = self.plan_hierarchy_ahead(&state.xyz)?;
            // The rendered branch carries no gradient into the encoder (design.md §7.3, §12).
            let feats_ren = {
                let _span = tracing::debug_span!("encode_renders").entered();
                lifegom_ops::shared_linear::detached_passes(|| {
                    self.encoder.encode(&folds, renders.rgb.clone().detach())
                })?
                .detach()
            };
            state = self.update(
                subject,
                mesh,
                sources,
                &feats_src,
                &feats_ren,
                renders.alpha.clone().detach(),
                &state,
                &folds,
                planned,
            )?;
            let all = render_views(
                mesh,
                &state.xyz,
                &state.faces,
                subject,
                &cameras,
                &skinning,
                sources.background,
            )?;
            renders = match targets_with_sources {
                true => SourceRenders {
                    rgb: all.rgb.clone().narrow(0, 0, n),
                    alpha: all.alpha.clone().narrow(0, 0, n),
                },
                false => all.clone(),
            };
            out.states.push(state.clone());
            out.renders.push(all);
            lap(format!("step_{}", step + 1), &mut timings);
        }
        if !targets_with_sources && !targets.cameras.is_empty() {
            let _span = tracing::debug_span!("target_renders").entered();
            for (state, render) in out.states.iter().zip(&mut out.renders) {
                let target = render_views(
                    mesh,
                    &state.xyz,
                    &state.faces,
                    subject,
                    &targets.cameras,
                    &targets.skinning,
                    sources.background,
                )?;
                render.rgb = Tensor::cat(vec![render.rgb.clone(), target.rgb], 0);
                render.alpha = Tensor::cat(vec![render.alpha.clone(), target.alpha], 0);
            }
        }
        out.timings = timings;
        Ok(out)
    }

    /// Fuses the source and rendered branches with the shared fusion weights, the rendered
    /// branch detached, and answers the Point Transformer's input: each vertex's two fused
    /// features side by side, `[V, 2D]`.
    ///
    /// On a CubeCL device without autodiff (inference: no graph, no dropout) the two branches
    /// are one fusion pass over `2V` rows, vertex `i`'s source tokens in row `2i` and its
    /// rendered ones in row `2i + 1`, whose `[2V, D]` output is the `[V, 2D]` input as it stands: the same
    /// arithmetic per vertex in half the launches and products twice as tall (the fusion
    /// treats vertices independently). Training keeps two passes: the rendered branch must not
    /// reach the weights' gradients, and a stacked pass's backward would spend as much again on
    /// rows whose gradient is zero.
    ///
    /// The branches are independent, and much of a fusion call is ops that the CPU backends run
    /// on one core, so with [`HostConcurrency::Branches`] the rendered branch runs as a rayon
    /// task beside the source branch (design.md §7.4), on the pool's other thread. It runs on
    /// an inference copy of the weights: no graph is built for a branch whose output is
    /// detached anyway. In training its dropout masks stay what a sequential source-then-rendered
    /// run draws: both branches' mask seeds are drawn from the device's seeded RNG first, in
    /// that order, and handed to each branch. Where masks are drawn by Burn on the device
    /// (CubeCL), the branches run in order on the calling thread.
    ///
    /// `src_repeats`, where given, lists the source tokens that are the visibility embedding
    /// (a vertex hidden in a view), whose first-layer projections are then computed once
    /// ([`FusionRun::repeats`](crate::fusion::FusionRun::repeats)).
    fn fuse_branches<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        src: Tensor<3>,
        ren: Tensor<3>,
        embed: &Tensor<2>,
        src_repeats: Option<&RepeatedTokens>,
    ) -> Tensor<2> {
        let device = src.device();
        if CostModel::of(&device).merge_passes() && !device.is_autodiff() {
            return self.fuse_stacked(folds, src, ren, embed);
        }
        // The inference copy first: Burn initialises parameters lazily from the same RNG, and a
        // first use here, on this thread, keeps those draws ahead of the mask seeds and out of
        // the other branch.
        let inference = self.fusion.valid();
        // Source first, then rendered: the order a sequential run draws them in.
        let masks = self.fusion.draw_mask_seeds(&device).map(|src_seeds| {
            let ren_seeds = self
                .fusion
                .draw_mask_seeds(&device)
                .expect("a host device for one call is one for the next");
            (FusionMasks::Given(src_seeds), FusionMasks::Given(ren_seeds))
        });
        let Some((src_masks, ren_masks)) = masks else {
            let fused_src = {
                let _span = tracing::debug_span!("source").entered();
                self.fusion
                    .forward(folds, src, embed.clone(), FusionRun::default())
            };
            let fused_ren = {
                let _span = tracing::debug_span!("rendered").entered();
                lifegom_ops::shared_linear::detached_passes(|| {
                    self.fusion
                        .forward(folds, ren, embed.clone(), FusionRun::default())
                })
                .detach()
            };
            return join_columns(vec![fused_src, fused_ren]);
        };
        let parent = tracing::Span::current();
        let (ren, ren_embed) = (ren.inner(), embed.clone().inner());
        let rendered = move || {
            let _span = tracing::debug_span!(parent: &parent, "rendered").entered();
            inference.forward(
                &NormFolds::new(),
                ren,
                ren_embed,
                FusionRun {
                    masks: ren_masks,
                    repeats: None,
                },
            )
        };
        let source = || {
            let _span = tracing::debug_span!("source").entered();
            self.fusion.forward(
                &NormFolds::new(),
                src,
                embed.clone(),
                FusionRun {
                    masks: src_masks,
                    repeats: src_repeats,
                },
            )
        };
        // A rayon task, not a thread of its own: the pass runs on a rayon worker
        // (`on_pool_thread`), and a worker blocked joining a thread whose ops wait for the pool
        // deadlocks once every worker does so (two reconstructions at once on two cores).
        let (fused_src, fused_ren) = match self.concurrency {
            HostConcurrency::Branches => rayon::join(source, rendered),
            HostConcurrency::Sequential => (source(), rendered()),
        };
        // Back on the caller's device, as a tensor without a graph (detached).
        let fused_ren = if device.is_autodiff() {
            Tensor::from_inner(fused_ren)
        } else {
            fused_ren
        };
        join_columns(vec![fused_src, fused_ren])
    }

    /// [`Self::fuse_branches`] at inference on a CubeCL device: both branches in one pass over
    /// `2V` rows, whose `[2V, D]` output is the `[V, 2D]` result as it stands.
    fn fuse_stacked<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        src: Tensor<3>,
        ren: Tensor<3>,
        embed: &Tensor<2>,
    ) -> Tensor<2> {
        let _span = tracing::debug_span!("stacked").entered();
        let [v, n, d] = src.dims();
        // [V, 2, N, D] → [2V, N, D]: rows 2i and 2i + 1 are vertex i's two branches.
        let tokens = Tensor::stack::<4>(vec![src, ren], 1).reshape([2 * v, n, d]);
        let queries = embed
            .clone()
            .reshape([v, 1, d])
            .expand([v, 2, d])
            .reshape([2 * v, d]);
        self.fusion
            .forward(folds, tokens, queries, FusionRun::default())
            .reshape([v, 2 * d])
    }

    /// The most floats one vertex puts in a single buffer of [`Self::fuse_branches`] with `n`
    /// views on `device`: the first fusion layer's stacked query, key and value, `3·D` per view
    /// token, for both branches at once where they are one pass (inference on a CubeCL device).
    fn fusion_floats_per_vertex(&self, n: usize, device: &Device) -> usize {
        let branches = match CostModel::of(device).merge_passes() && !device.is_autodiff() {
            true => 2,
            false => 1,
        };
        branches * n * 3 * self.visibility_embed.dims()[0]
    }

    /// With [`HierarchyPlanning::Ahead`] on a CubeCL device: the Point Transformer's levels
    /// for the vertices `xyz`, planned on a thread of their own while the step's rendering,
    /// encoding and fusion are queued and run. The read-back here waits only for the previous
    /// step, which the step needs anyway; the host's FPS and kNN then no longer leave the device
    /// idle between a drained queue and the network's next ops.
    fn plan_hierarchy_ahead(&self, xyz: &Tensor<2>) -> Result<Option<JoinHandle<HostHierarchy>>> {
        if HierarchyPlanning::on_device(&xyz.device()) == HierarchyPlanning::Inline {
            return Ok(None);
        }
        let _span = tracing::debug_span!("hierarchy_readback").entered();
        let host = read_points(xyz.clone().detach())?;
        let windows = self.point_transformer.level_windows();
        Ok(Some(std::thread::spawn(move || {
            HostHierarchy::plan(&windows, host)
        })))
    }

    /// One feedback step (module docs). `planned`: the Point Transformer's levels for
    /// `state.xyz`, being planned ([`Self::plan_hierarchy_ahead`]); `None` plans them inline.
    #[allow(clippy::too_many_arguments)]
    fn update<'a>(
        &'a self,
        subject: &CanonicalSubject,
        mesh: &GomMesh,
        sources: &SourceViews,
        feats_src: &EncodedViews,
        feats_ren: &EncodedViews,
        alpha_prev: Tensor<4>,
        state: &GomState,
        folds: &NormFolds<'a>,
        planned: Option<JoinHandle<HostHierarchy>>,
    ) -> Result<GomState> {
        let (w, h) = (sources.cameras[0].width, sources.cameras[0].height);
        let n = sources.cameras.len();
        let [v, _] = state.xyz.dims();
        let d = self.visibility_embed.dims()[0];

        // Pose the current vertices into each view and project them.
        let span = tracing::debug_span!("pose_and_project").entered();
        let posed: Vec<Tensor<2>> = sources
            .skinning
            .iter()
            .map(|t| skin_vertices(state.xyz.clone(), subject.lbs_weights.clone(), t))
            .collect::<std::result::Result<_, _>>()?;
        let proj = project_points(Tensor::stack(posed.clone(), 0), &sources.cameras)?;

        // Discrete visibility of the high-res mesh in each view (no gradient), computed on the
        // device the mesh lives on: the CPU reference on ndarray/Flex, the GPU kernels on wgpu.
        // A face counts as visible when all three of its corners are.
        // The views' posed meshes side by side, `[V, 3n]`, subdivided in one gather.
        let tables = mesh.tables();
        let faces_flat = mesh.highres_faces().clone();
        let f = mesh.num_gaussians();
        let faces_hr = faces_flat.clone().reshape([f, 3]);
        let num_hr_vertices = mesh.subdivision.highres.num_vertices;
        let posed_hr = tables.apply_columns(join_columns(posed.clone()));
        drop(span);
        let (vis, face_vis) = {
            let _span = tracing::debug_span!("visibility").entered();
            let views = ViewSet {
                cameras: sources.cameras.clone(),
                lowres: v,
            };
            let flags = visibility_in_views(posed_hr.clone().detach(), faces_hr, &views)?;
            (flags.vertices.reshape([v, n, 1]), flags.faces)
        };
        // The source tokens of hidden (vertex, view) pairs are all e_vis: 80–90 % of them at
        // the small presets (BENCHMARKS.md, 2026-11-26: "the issue's own starting code against
        // today's"), projected once in the fusion where reading the visibility (the no-gradient
        // raster's result) back costs no sync ([`CostModel`]).
        let src_repeats = if CostModel::of(&state.xyz.device()).free_readback() {
            let host: Vec<f32> = readback::read("vertex visibility", vis.clone())?;
            let hidden: Vec<bool> = host.iter().map(|&x| x < 0.5).collect();
            RepeatedTokens::from_mask(&hidden, n, &state.xyz.device())
        } else {
            None
        };
        let e_vis = self.visibility_embed.val().reshape([1, 1, d]);

        // Sampling and fusion treat vertices independently; they run block after block of
        // vertices where one buffer of the device cannot hold a whole stage's largest tensor
        // (the fusion's stacked projections, `Self::fusion_floats_per_vertex`: 1.1 GB for the
        // paper network's 13,718 vertices at inference, against lavapipe's 128 MiB). One block,
        // the unblocked stage's ops, on the CPU backends and on cards with large buffers.
        let device = state.xyz.device();
        let per_vertex = self.fusion_floats_per_vertex(n, &device);
        let block = rows_per_block(&device, v, per_vertex, self.buffer_floats);
        let mut fused = Vec::with_capacity(v.div_ceil(block));
        // At least one block, so that no vertices are the unblocked stage's ops too.
        for start in (0..v.max(1)).step_by(block) {
            let len = block.min(v - start);
            let (uv, vis) = (
                block_rows(&proj.uv, 1, start, len),
                block_rows(&vis, 0, start, len),
            );
            let embed = block_rows(&state.embed, 0, start, len);
            // Source branch, blended with e_vis where the vertex is hidden.
            let span = tracing::debug_span!("sampling").entered();
            let f_src = feats_src.sample(uv.clone(), w, h)?;
            let src = f_src * vis.clone() + e_vis.clone() * (vis.ones_like() - vis);
            // Rendered branch, blended by the previous render's soft alpha.
            let f_ren = feats_ren.sample(uv.clone(), w, h)?;
            let m = sample_single(alpha_prev.clone(), uv, w, h)?.reshape([len, n, 1]);
            let ren = f_ren * m.clone() + e_vis.clone() * (m.ones_like() - m);
            drop(span);

            let _span = tracing::debug_span!("fusion").entered();
            // The repeated tokens index the whole stage (they are listed on the CPU backends,
            // which run it as one block).
            let repeats = src_repeats.as_ref().filter(|_| len == v);
            fused.push(self.fuse_branches(folds, src, ren, &embed, repeats));
        }
        let features = match fused.len() {
            1 => fused.pop().expect("one block"),
            _ => Tensor::cat(fused, 0),
        };
        let h_pt = {
            let _span = tracing::debug_span!("point_transformer").entered();
            match planned {
                Some(handle) => {
                    // A panic in FPS or kNN is a bug; it surfaces here as it would inline.
                    let plan = handle
                        .join()
                        .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                    self.point_transformer.forward(
                        folds,
                        state.xyz.clone(),
                        features,
                        Hierarchy::Planned(plan),
                    )?
                }
                None => self.point_transformer.forward(
                    folds,
                    state.xyz.clone(),
                    features,
                    Hierarchy::Plan,
                )?,
            }
        };
        let span = tracing::debug_span!("vertex_heads").entered();
        let vertex = self.heads.vertices(folds, h_pt.clone());
        drop(span);

        // Faces: source features at the projected centroid of each high-res face of the current
        // (pre-update) mesh, zeroed where the face is not fully visible in that view. The zeros
        // come from sampling hidden faces outside the maps, which equals the product with the
        // visibility in values and gradients without a `[F, N, D]` product (`hide_invisible`).
        let span = tracing::debug_span!("face_sampling").entered();
        let uv_faces = {
            let _span = tracing::debug_span!("face_centroids").entered();
            let posed_hr = posed_hr.reshape([num_hr_vertices, n, 3]).swap_dims(0, 1);
            let proj_hr = project_points(posed_hr, &sources.cameras)?;
            let centroids = select_rows(proj_hr.uv, 1, faces_flat.clone())
                .reshape([n, f, 3, 2])
                .mean_dim(2)
                .reshape([n, f, 2]);
            hide_invisible(centroids, face_vis.clone())
        };
        drop(span);
        // Block after block of faces, so no buffer outgrows a GPU's limit; one block (the whole
        // stage at once) at every preset that trains on a CPU (`FACE_BLOCK_FLOATS`). The
        // high-res features are made after the first block's sampling, so that one block
        // records the same ops in the same order as the unblocked stage (the same gradients to
        // the bit on the CPU backends).
        let block = faces_per_block(&device, f, n * d, self.buffer_floats);
        let mut blocks = Vec::with_capacity(f.div_ceil(block));
        let mut h_hr: Option<Tensor<2>> = None;
        for start in (0..f).step_by(block) {
            let len = block.min(f - start);
            let (uv, corners) = if len == f {
                (uv_faces.clone(), faces_flat.clone())
            } else {
                (
                    uv_faces.clone().narrow(1, start, len),
                    faces_flat.clone().narrow(0, 3 * start, 3 * len),
                )
            };
            // Where a read-back is free ([`CostModel`]) and the whole stage is one block, only
            // the visible (face, view) pairs are sampled and multiplied (`FaceImages::Visible`);
            // the dense layout stays for blocks and queued devices, and as the reference in
            // tests.
            let visible_only = len == f && CostModel::of(&state.xyz.device()).free_readback();
            let face_feats = {
                let _span = tracing::debug_span!("face_sampling").entered();
                let _span = tracing::debug_span!("sample_maps").entered();
                if visible_only {
                    FaceImages::Visible(sample_visible_faces(
                        feats_src,
                        uv,
                        face_vis.clone(),
                        w,
                        h,
                    )?)
                } else {
                    FaceImages::Dense(feats_src.sample(uv, w, h)?.reshape([len, n * d]))
                }
            };
            let _span = tracing::debug_span!("face_heads").entered();
            let h_hr = h_hr
                .get_or_insert_with(|| {
                    highres_features(h_pt.clone(), tables.index.clone(), tables.weight.clone())
                })
                .clone();
            let inputs = FaceInputs {
                corners: face_corners(h_hr, corners),
                images: face_feats,
            };
            // Where merged passes pay ([`CostModel`]) the heads' stacked weights are made once
            // per reconstruction; elsewhere per step as before, so that training's gradients
            // keep their summation order to the bit.
            blocks.push(if CostModel::of(&state.xyz.device()).merge_passes() {
                self.heads.faces(folds, inputs)
            } else {
                self.heads.faces(&NormFolds::new(), inputs)
            });
        }
        let faces = GomParams::cat(blocks, &state.xyz.device());
        Ok(GomState {
            xyz: state.xyz.clone() + vertex.delta_xyz,
            embed: vertex.embed,
            faces,
        })
    }
}

/// Rows `start..start + len` of `t` on axis `dim`: `t` itself when they are all of it (one
/// block: the unblocked stage's ops).
fn block_rows<const D: usize>(t: &Tensor<D>, dim: usize, start: usize, len: usize) -> Tensor<D> {
    match t.dims()[dim] == len {
        true => t.clone(),
        false => t.clone().narrow(dim, start, len),
    }
}

/// The image features of the visible (face, view) pairs only ([`VisibleFaceImages`]).
///
/// `uv` `[N, F, 2]` are the faces' projected centroids with hidden pairs already outside every
/// map ([`hide_invisible`]); `visible` `[F, N]` is 1 where a face is visible whole. The
/// visibility is read to the host to list each view's faces (it is the no-gradient triangle-ID
/// raster's result); a padding row takes the coordinate of a face hidden in its view, so it
/// samples zero with a zero gradient.
fn sample_visible_faces(
    maps: &EncodedViews,
    uv: Tensor<3>,
    visible: Tensor<2>,
    width: u32,
    height: u32,
) -> Result<VisibleFaceImages> {
    let [n, f, _] = uv.dims();
    let device = uv.device();
    let host: Vec<f32> = readback::read("face visibility", visible)?;
    let is_visible = |face: usize, view: usize| host[face * n + view] >= 0.5;
    let rows: Vec<Vec<usize>> = (0..n)
        .map(|view| (0..f).filter(|&face| is_visible(face, view)).collect())
        .collect();
    let r = rows.iter().map(Vec::len).max().unwrap_or(0).max(1);
    let mut gather = Vec::with_capacity(n * r);
    let mut owners = Vec::with_capacity(n * r);
    for (view, faces) in rows.iter().enumerate() {
        // Fewer than R ≤ F visible faces means some face is hidden in this view.
        let pad = (0..f).find(|&face| !is_visible(face, view)).unwrap_or(0);
        for k in 0..r {
            let (face, owner) = faces.get(k).map_or((pad, f), |&face| (face, face));
            gather.push((view * f + face) as i64);
            owners.push(owner as i64);
        }
    }
    let index =
        |values: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(values, [n * r]), &device);
    let uv_rows = select_rows(uv.reshape([n * f, 2]), 0, index(gather)).reshape([n, r, 2]);
    Ok(VisibleFaceImages {
        features: maps.sample(uv_rows, width, height)?,
        faces: index(owners),
    })
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use glam::Vec3;
    use lifegom_render::camera::Intrinsics;
    use lifegom_render::skeleton::BodyPose;
    use lifegom_render::template::{BodyTemplate, lowres_template_path};

    use lifegom_render::testing::read;

    struct Fixture {
        subject: CanonicalSubject,
        mesh: GomMesh,
        sources: SourceViews,
        vertices: usize,
    }

    fn fixture(device: &Device, size: u32) -> Fixture {
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let f = 0.8 * size as f32;
        let k = Intrinsics {
            fx: f,
            fy: f,
            cx: size as f32 / 2.0,
            cy: size as f32 / 2.0,
        };
        let cameras: Vec<Camera> = [Vec3::new(0.0, 0.1, 2.5), Vec3::new(2.0, 0.1, -1.5)]
            .iter()
            .map(|eye| {
                Camera::look_at(*eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k, size, size).unwrap()
            })
            .collect();
        let rest = body
            .skeleton
            .skinning_transforms(&BodyPose::rest(body.num_joints()))
            .unwrap();
        Fixture {
            subject: CanonicalSubject {
                canonical_vertices: body.vertex_tensor(device),
                lbs_weights: body.skin.tensor(device),
                skeleton: body.skeleton.clone(),
            },
            mesh: GomMesh::new(&body.topology, 0, device).unwrap(),
            sources: SourceViews {
                images: Tensor::random(
                    [2, 3, size as usize, size as usize],
                    Distribution::Uniform(0.0, 1.0),
                    device,
                ),
                cameras,
                skinning: vec![rest.clone(), rest],
                background: [0.0; 3],
            },
            vertices: body.num_vertices(),
        }
    }

    /// A loss that reaches every trainable parameter: every step's renders and the last
    /// state's vertices.
    fn test_loss(rec: &Reconstruction) -> Tensor<1> {
        rec.renders
            .iter()
            .map(|r| r.rgb.clone().mean())
            .reduce(|a, b| a + b)
            .expect("at least one step")
            + rec.last().xyz.clone().powi_scalar(2).mean()
    }

    /// `device` with autodiff, seeded, the 32-pixel fixture on it, and the tiny network for its
    /// two views with two feedback steps and no dropout.
    fn seeded_tiny(device: &Device) -> (Device, Fixture, Reconstructor) {
        let ad = device.clone().autodiff();
        // A fixed seed for the random weights and images: at some draws the tiny network's
        // Point Transformer starts with a whole ReLU layer dead, which zeroes every gradient
        // behind it (seen once on lavapipe in CI) and says nothing about the code.
        ad.seed(3);
        let fx = fixture(&ad, 32);
        let model = ReconstructorConfig::tiny(2)
            .with_iterations(2)
            .with_dropout(0.0)
            .init(fx.vertices, &ad)
            .unwrap();
        (ad, fx, model)
    }

    fn end_to_end(device: &Device) {
        let (_, fx, model) = seeded_tiny(device);
        let rec = model.forward(&fx.subject, &fx.mesh, &fx.sources).unwrap();
        assert_eq!(rec.states.len(), 2);
        assert_eq!(rec.renders[1].rgb.dims(), [2, 3, 32, 32]);
        assert_eq!(rec.last().faces.colors.dims(), [fx.mesh.num_gaussians(), 3]);
        let alpha = read(rec.renders[0].alpha.clone());
        assert!(
            alpha.iter().all(|a| a.is_finite()) && alpha.iter().any(|a| *a > 0.5),
            "the body is rendered"
        );

        let grads = test_loss(&rec).backward();
        let mut check = GradCheck {
            grads: &grads,
            path: Vec::new(),
            trainable: 0,
            missing: Vec::new(),
            zero: Vec::new(),
        };
        model.visit(&mut check);
        assert!(
            check.trainable > 50,
            "visited {} trainable tensors",
            check.trainable
        );
        assert!(
            check.missing.is_empty(),
            "no finite gradient reached: {:?}",
            check.missing
        );
        // An exactly-zero gradient is legitimate behind a ReLU that is dead for this input (tiny
        // random network, ~1K points), but it must stay rare.
        assert!(
            check.zero.len() * 10 <= check.trainable,
            "too many all-zero gradients: {:?}",
            check.zero
        );
    }

    /// The whole reconstruction's backward on wgpu (every custom op, the layers the feedback
    /// steps share, Burn's fusion) against Flex with the same weights and images: two views,
    /// two feedback steps, no dropout, two target views (one of the sources' pose, one of
    /// another) rendered beside the sources. Every trainable parameter's gradient agrees within 1e-3
    /// of its largest magnitude plus 1e-6 of the largest gradient (float summation order,
    /// through two steps of rendering and feedback; measured: within 3e-5 of each tensor's
    /// scale), and the last renders within 1e-4.
    #[test]
    fn gradients_on_wgpu_match_flex() {
        let Some(wgpu) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        let (_, fx_flex, model_flex) = seeded_tiny(&Device::flex());
        let wgpu = wgpu.autodiff();
        // `fork` keeps which parameters require a gradient; `to_device` does not.
        let model_wgpu = model_flex.clone().fork(&wgpu);
        let mut fx_wgpu = fixture(&wgpu, 32);
        fx_wgpu.sources.images = fx_flex.sources.images.clone().to_device(&wgpu);
        // Two target views: one of the sources' pose (rendered with them on wgpu, in one
        // rasterizer call, and after the feedback loop on Flex) and one of another pose (a call
        // of its own on wgpu).
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let mut pose = BodyPose::rest(body.num_joints());
        pose.joint_rotations[1] = Vec3::new(0.0, 0.0, 0.6);
        let targets = TargetViews {
            cameras: [Vec3::new(1.5, 0.5, 2.0), Vec3::new(-2.0, 0.0, 1.0)]
                .iter()
                .map(|eye| {
                    let k = fx_flex.sources.cameras[0].intrinsics;
                    Camera::look_at(*eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k, 32, 32).unwrap()
                })
                .collect(),
            skinning: vec![
                fx_flex.sources.skinning[0].clone(),
                body.skeleton.skinning_transforms(&pose).unwrap(),
            ],
        };
        let run = |model: &Reconstructor, fx: &Fixture| {
            let rec = model
                .forward_with_targets(&fx.subject, &fx.mesh, &fx.sources, &targets)
                .unwrap();
            assert_eq!(
                rec.renders[1].rgb.dims(),
                [4, 3, 32, 32],
                "sources, then targets"
            );
            let renders = read(rec.renders[1].rgb.clone());
            let grads = test_loss(&rec).backward();
            (renders, crate::test_grads::parameter_grads(model, &grads))
        };
        let (want_renders, want) = run(&model_flex, &fx_flex);
        let (got_renders, got) = run(&model_wgpu, &fx_wgpu);
        assert!(max_diff(&got_renders, &want_renders) <= 1e-4);
        assert_grads_close(&got, &want);
    }

    fn magnitude(v: &[f32]) -> f32 {
        v.iter().fold(0.0f32, |m, x| m.max(x.abs()))
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()))
    }

    /// Every parameter's gradient in `got` within 1e-3 of its largest magnitude in `want` plus
    /// 1e-6 of the largest gradient of all (float summation order through a reconstruction).
    fn assert_grads_close(got: &[(String, Vec<f32>)], want: &[(String, Vec<f32>)]) {
        assert_eq!(got.len(), want.len());
        assert!(want.len() > 50, "{} gradients compared", want.len());
        // Gradients that are zero in exact arithmetic (a softmax's bias, shifted alike for all
        // its inputs: the Point Transformer's logit biases, the fusion's key biases) are
        // rounding noise: they are held to the largest gradient's scale.
        let largest = want.iter().fold(0.0f32, |m, (_, v)| m.max(magnitude(v)));
        let mut worst = (0.0f32, String::new());
        for ((name, a), (name_b, b)) in got.iter().zip(want) {
            assert_eq!(name, name_b);
            let excess = max_diff(a, b) / (1e-3 * magnitude(b) + 1e-6 * largest);
            if excess > worst.0 {
                worst = (excess, name.clone());
            }
        }
        assert!(
            worst.0 <= 1.0,
            "{}: {:.2}× the tolerance (largest gradient {largest:.2e})",
            worst.1,
            worst.0
        );
    }

    /// The per-vertex stage (sampling and fusion) and the face stage run block after block,
    /// as on a device whose buffers cannot hold a whole stage (lavapipe at the paper preset),
    /// give the one-block reconstruction: in training, both steps' vertices and renders within
    /// 1e-5 and every parameter's gradient within [`assert_grads_close`]'s tolerance; at
    /// inference (where a CubeCL device fuses both branches in one pass per block) the last
    /// state within 1e-5.
    fn blocked_stages_match_one_block(device: &Device) {
        let (ad, fx, model) = seeded_tiny(device);
        let (v, f) = (fx.vertices, fx.mesh.num_gaussians());
        let d = model.visibility_embed.dims()[0];
        let blocks_of = |model: &Reconstructor, device: &Device| {
            let floats = model.buffer_floats;
            let per_vertex = model.fusion_floats_per_vertex(2, device);
            (
                v.div_ceil(rows_per_block(device, v, per_vertex, floats)),
                f.div_ceil(faces_per_block(device, f, 2 * d, floats)),
            )
        };
        let run = |model: &Reconstructor| {
            let rec = model.forward(&fx.subject, &fx.mesh, &fx.sources).unwrap();
            let values: Vec<Vec<f32>> = (0..2)
                .flat_map(|t| {
                    [
                        read(rec.states[t].xyz.clone()),
                        read(rec.states[t].faces.colors.clone()),
                        read(rec.renders[t].rgb.clone()),
                    ]
                })
                .collect();
            let grads = test_loss(&rec).backward();
            (values, crate::test_grads::parameter_grads(model, &grads))
        };
        let (want, want_grads) = run(&model);
        // Three blocks of vertices, and the faces (about twice as many) in blocks too. (A copy
        // made after the first run, whose parameters Burn initialised lazily.)
        let per_vertex = model.fusion_floats_per_vertex(2, &ad);
        let blocked = model.clone().with_buffer_floats(per_vertex * v.div_ceil(3));
        assert_eq!(blocks_of(&model, &ad), (1, 1));
        let (vertex_blocks, face_blocks) = blocks_of(&blocked, &ad);
        assert_eq!(vertex_blocks, 3);
        assert!(face_blocks >= 2, "{face_blocks} face blocks");
        let (got, got_grads) = run(&blocked);
        for (a, b) in got.iter().zip(&want) {
            assert!(
                max_diff(a, b) <= 1e-5 * (1.0 + magnitude(b)),
                "{}",
                max_diff(a, b)
            );
        }
        assert_grads_close(&got_grads, &want_grads);

        // Inference, without a graph.
        let (model, blocked) = (model.valid(), blocked.valid());
        let mut fx_plain = fixture(device, 32);
        fx_plain.sources.images = fx.sources.images.clone().inner();
        // A CubeCL device fuses both branches in one pass: twice the floats a vertex.
        let blocked =
            blocked.with_buffer_floats(model.fusion_floats_per_vertex(2, device) * v.div_ceil(3));
        assert_eq!(blocks_of(&blocked, device).0, 3);
        let last = |model: &Reconstructor| {
            let rec = model
                .forward(&fx_plain.subject, &fx_plain.mesh, &fx_plain.sources)
                .unwrap();
            [
                read(rec.last().xyz.clone()),
                read(rec.last().faces.colors.clone()),
            ]
        };
        for (a, b) in last(&blocked).iter().zip(&last(&model)) {
            assert!(
                max_diff(a, b) <= 1e-5 * (1.0 + magnitude(b)),
                "{}",
                max_diff(a, b)
            );
        }
    }

    lifegom_render::cpu_backend_tests!(blocked_stages => blocked_stages_match_one_block);

    #[test]
    fn blocked_stages_match_one_block_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            blocked_stages_match_one_block(&device);
        }
    }

    /// Records every trainable parameter that got no (finite, non-zero) gradient.
    struct GradCheck<'a> {
        grads: &'a burn::tensor::Gradients,
        path: Vec<String>,
        trainable: usize,
        missing: Vec<String>,
        zero: Vec<String>,
    }

    impl burn::module::ModuleVisitor for GradCheck<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let t = param.val();
            if !t.is_require_grad() {
                return; // frozen (e.g. the Point Transformer's batch norms)
            }
            self.trainable += 1;
            match t.grad(self.grads).map(read) {
                Some(g) if g.iter().all(|v| v.is_finite()) => {
                    if g.iter().all(|v| *v == 0.0) {
                        self.zero.push(self.path.join("."));
                    }
                }
                Some(g) => {
                    let bad = g.iter().filter(|v| !v.is_finite()).count();
                    self.missing.push(format!(
                        "{} ({bad} of {} non-finite)",
                        self.path.join("."),
                        g.len()
                    ));
                }
                None => self
                    .missing
                    .push(format!("{} (no gradient)", self.path.join("."))),
            }
        }
    }

    lifegom_render::cpu_backend_tests!(end_to_end => end_to_end);

    /// Inference on wgpu, where the fusion's source and rendered branches are one stacked pass
    /// (`fuse_branches`), equals Flex's two passes: the vertices and the renders of both
    /// feedback steps within float summation order (measured: 7e-9 and 8e-7 of their scale).
    #[test]
    fn stacked_branches_on_wgpu_match_flex() {
        let Some(wgpu) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        let flex = Device::flex();
        flex.seed(3);
        let fx_flex = fixture(&flex, 32);
        let model_flex = ReconstructorConfig::tiny(2)
            .with_iterations(2)
            .init(fx_flex.vertices, &flex)
            .unwrap();
        let model_wgpu = model_flex.clone().fork(&wgpu);
        let mut fx_wgpu = fixture(&wgpu, 32);
        fx_wgpu.sources.images = fx_flex.sources.images.clone().to_device(&wgpu);
        let run = |model: &Reconstructor, fx: &Fixture| {
            let rec = model.forward(&fx.subject, &fx.mesh, &fx.sources).unwrap();
            (0..2)
                .flat_map(|t| {
                    [
                        read(rec.states[t].xyz.clone()),
                        read(rec.renders[t].rgb.clone()),
                    ]
                })
                .collect::<Vec<_>>()
        };
        let want = run(&model_flex, &fx_flex);
        let got = run(&model_wgpu, &fx_wgpu);
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            lifegom_render::testing::assert_close_to_scale(a, b, 1e-4, &format!("part {i}"));
        }
    }

    /// Model code runs unchanged on wgpu (lavapipe on CI): the same reconstruction and backward,
    /// with visibility and rasterization in the GPU kernels.
    #[test]
    fn end_to_end_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            end_to_end(&device);
        }
    }

    #[test]
    fn mismatched_inputs_are_errors() {
        let device = Device::flex();
        let fx = fixture(&device, 32);
        let model = ReconstructorConfig::tiny(3)
            .with_iterations(1)
            .init(fx.vertices, &device)
            .unwrap();
        let err = model
            .forward(&fx.subject, &fx.mesh, &fx.sources)
            .unwrap_err()
            .to_string();
        assert!(err.contains("images"), "{err}");
        let model = ReconstructorConfig::tiny(2)
            .init(fx.vertices + 1, &device)
            .unwrap();
        assert!(
            model
                .forward(&fx.subject, &fx.mesh, &fx.sources)
                .unwrap_err()
                .to_string()
                .contains("subject")
        );
        assert!(
            ReconstructorConfig::tiny(2)
                .with_n_heads(7)
                .init(fx.vertices, &device)
                .is_err()
        );
        // Target views: a camera without its skinning, or of another image size.
        let model = ReconstructorConfig::tiny(2)
            .with_iterations(1)
            .init(fx.vertices, &device)
            .unwrap();
        let camera = fx.sources.cameras[0];
        let other_size = Camera::new(camera.intrinsics, camera.cam_from_world, 32, 16).unwrap();
        for targets in [
            TargetViews {
                cameras: vec![camera],
                skinning: vec![],
            },
            TargetViews {
                cameras: vec![other_size],
                skinning: vec![fx.sources.skinning[0].clone()],
            },
        ] {
            let err = model
                .forward_with_targets(&fx.subject, &fx.mesh, &fx.sources, &targets)
                .unwrap_err()
                .to_string();
            assert!(err.contains("targets"), "{err}");
        }
    }

    /// T = 3 with one view looking away from the body (it sees nothing) and every joint turned
    /// 180° in the other (a degenerate, self-intersecting pose): everything stays finite.
    #[test]
    fn off_screen_view_and_degenerate_pose_stay_finite() {
        let device = Device::ndarray().autodiff();
        let mut fx = fixture(&device, 32);
        let k = fx.sources.cameras[0].intrinsics;
        fx.sources.cameras[1] = Camera::look_at(
            Vec3::new(0.0, 0.1, 2.5),
            Vec3::new(0.0, 0.1, 5.0),
            Vec3::Y,
            k,
            32,
            32,
        )
        .unwrap();
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let twisted = BodyPose {
            joint_rotations: vec![Vec3::new(0.0, std::f32::consts::PI, 0.0); body.num_joints()],
        };
        fx.sources.skinning[0] = body.skeleton.skinning_transforms(&twisted).unwrap();
        let model = ReconstructorConfig::tiny(2)
            .with_iterations(3)
            .init(fx.vertices, &device)
            .unwrap();
        let rec = model.forward(&fx.subject, &fx.mesh, &fx.sources).unwrap();
        assert_eq!(rec.states.len(), 3);
        let away = read(rec.renders[2].alpha.clone().narrow(0, 1, 1));
        assert!(
            away.iter().all(|a| *a == 0.0),
            "the view looking away renders nothing"
        );
        for (t, state) in rec.states.iter().enumerate() {
            assert!(
                read(state.xyz.clone()).iter().all(|v| v.is_finite()),
                "xyz at step {t}"
            );
            assert!(
                read(state.faces.scales.clone())
                    .iter()
                    .all(|v| v.is_finite()),
                "scales at step {t}"
            );
        }
        let grads = rec
            .renders
            .iter()
            .map(|r| r.rgb.clone().mean())
            .reduce(|a, b| a + b)
            .unwrap()
            .backward();
        let g = read(model.vertex_embed.val().grad(&grads).unwrap());
        assert!(g.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn training_and_inference_meshes_share_the_low_res_topology() {
        let device = Device::flex();
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let cfg = ReconstructorConfig::tiny(2);
        let train = cfg
            .mesh(&body.topology, MeshPurpose::Training, &device)
            .unwrap();
        let test = cfg
            .mesh(&body.topology, MeshPurpose::Inference, &device)
            .unwrap();
        let f = body.topology.faces.len();
        assert_eq!(
            (train.num_gaussians(), test.num_gaussians()),
            (4 * f, 16 * f)
        );
        assert_eq!(train.subdivision.lowres, test.subdivision.lowres);
    }
}
