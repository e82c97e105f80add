//! Multi-source fusion (design.md §7.4): per vertex, the features sampled from the N views are fused
//! by two post-norm transformer layers with shared weights for the source and rendered branches.
//!
//! 1. **Across views**: self-attention over the N view tokens of each vertex (sequence length N,
//!    batch V). A vertex seen well in one view and occluded in another can borrow from the
//!    good view; the order of views does not matter (no positional encoding).
//! 2. **Into the vertex**: cross-attention whose single query is the vertex's current embedding
//!    (learned per vertex, updated by the feedback loop) and whose keys/values are the fused
//!    view tokens: one `d`-vector per vertex.
//!
//! Each layer is `x = LN₁(q + Dropout(MHA(q, k, v)))`, `out = LN₂(x + Dropout(FFN(x)))` with
//! `FFN = Linear → ReLU → Linear`, separate `W_q, W_k, W_v, W_o` with biases, scale `1/√d_k`
//! and no mask — the reference's `EncoderLayer`, written out here (rather than Burn's
//! `MultiHeadAttention`) so the parameter names map one-to-one onto the official state dict
//! (`multiview_embed.{0,1}.self_attn.W_{q,k,v,o}`, `feed_forward.fc{1,2}`, `norm{1,2}`).
//!
//! The attention core (scores, softmax, weighted values, for all heads) and each `LN(a + b)` run
//! as single custom ops with hand-written backwards ([`lifegom_ops::fusion`]): slice code on the
//! CPU backends, CubeCL kernels on the devices. Their test reference is the tensor-op
//! composition ([`FusionKernel::TensorOps`]).

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Dropout, DropoutConfig, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::{Device, Distribution, Int, Tensor, TensorData};
use lifegom_render::select::select_rows;
use lifegom_render::split::split_columns;

use crate::norm_folds::NormFolds;
use lifegom_ops::activation::Activation;
use lifegom_ops::dropout::{
    MaskSeed, draws_device_mask, dropout_with, drops_nothing, host_mask_seeds,
};
use lifegom_ops::fusion::{add_dropped_layer_norm, add_layer_norm, attention, attention_reference};

/// How the attention core and the residual LayerNorms are computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FusionKernel {
    /// Both as the custom ops of [`lifegom_ops::fusion`], which run slice code on the CPU
    /// backends and CubeCL kernels on the devices.
    Ops,
    /// Both as Burn tensor-op compositions (the reference in tests).
    TensorOps,
}

/// One post-norm attention layer.
#[derive(Config, Debug)]
pub struct AttentionLayerConfig {
    /// Token width.
    pub d_model: usize,
    /// Hidden width of the feed-forward block.
    pub d_ff: usize,
    /// Attention heads; must divide `d_model`.
    pub n_heads: usize,
    /// Dropout after attention and after the feed-forward block (training only).
    #[config(default = 0.1)]
    pub dropout: f64,
    /// LayerNorm epsilon.
    #[config(default = 1e-5)]
    pub layer_norm_eps: f64,
}

/// See [`AttentionLayerConfig`].
#[derive(Module, Debug)]
pub struct AttentionLayer {
    w_q: Linear,
    w_k: Linear,
    w_v: Linear,
    w_o: Linear,
    fc1: Linear,
    fc2: Linear,
    norm1: LayerNorm,
    norm2: LayerNorm,
    dropout: Dropout,
    n_heads: usize,
    layer_norm_eps: f64,
}

impl AttentionLayerConfig {
    /// Builds the layer with PyTorch-default initialisation (Burn's `Linear` default is the same
    /// kaiming-uniform with bound `1/√fan_in`).
    pub fn init(&self, device: &Device) -> AttentionLayer {
        assert!(
            self.n_heads > 0 && self.d_model.is_multiple_of(self.n_heads),
            "d_model {} must be divisible by n_heads {}",
            self.d_model,
            self.n_heads
        );
        let lin = |i, o| LinearConfig::new(i, o).init(device);
        AttentionLayer {
            w_q: lin(self.d_model, self.d_model),
            w_k: lin(self.d_model, self.d_model),
            w_v: lin(self.d_model, self.d_model),
            w_o: lin(self.d_model, self.d_model),
            fc1: lin(self.d_model, self.d_ff),
            fc2: lin(self.d_ff, self.d_model),
            norm1: LayerNormConfig::new(self.d_model)
                .with_epsilon(self.layer_norm_eps)
                .init(device),
            norm2: LayerNormConfig::new(self.d_model)
                .with_epsilon(self.layer_norm_eps)
                .init(device),
            dropout: DropoutConfig::new(self.dropout).init(),
            n_heads: self.n_heads,
            layer_norm_eps: self.layer_norm_eps,
        }
    }
}

/// What an [`AttentionLayer`] attends with.
#[derive(Debug, Clone)]
#[expect(
    clippy::large_enum_variant,
    reason = "built for one call and consumed by it, never stored"
)]
pub enum Attend<'r> {
    /// `query` `[B, Lq, D]` attends to `context` `[B, Lk, D]` (the fusion's second layer).
    Cross {
        /// The queries, and the residual the layer adds its attention to.
        query: Tensor<3>,
        /// The keys' and values' tokens.
        context: Tensor<3>,
    },
    /// `tokens` `[B, L, D]` attend to themselves (the fusion's first layer, across views).
    Within {
        /// The tokens.
        tokens: Tensor<3>,
        /// Rows known to repeat one value, whose `W_q`, `W_k`, `W_v` projections are then
        /// computed once: the same values as without, and the same gradients up to the order
        /// of their sums.
        repeats: Option<&'r RepeatedTokens>,
    },
}

/// How one call of an [`AttentionLayer`] computes, beside what it attends with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LayerRun {
    /// The attention core's and the residual LayerNorms' implementation (tests compare both).
    pub kernel: FusionKernel,
    /// The seeds of the two dropout masks: after attention, after the feed-forward block.
    pub masks: [MaskSeed; 2],
}

impl Default for LayerRun {
    /// The custom ops, with masks drawn from the device's RNG as the call goes.
    fn default() -> Self {
        Self {
            kernel: FusionKernel::Ops,
            masks: [MaskSeed::Device; 2],
        }
    }
}

impl AttentionLayer {
    /// `x = LN₁(q + Dropout(MHA(q, k, v)))`, `out = LN₂(x + Dropout(FFN(x)))`: `[B, Lq, D]`.
    /// The layers are shared through `folds` with every other call on them (design.md §7.4).
    pub fn forward<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        input: Attend<'_>,
        run: LayerRun,
    ) -> Tensor<3> {
        let (query, attn) = self.multi_head_attention(folds, input, run.kernel);
        self.feed(folds, query, attn, run.kernel, run.masks)
    }

    /// `MHA(q, k, v)` after `W_o`, with the query the residual adds it to. Where products stack
    /// ([`NormFolds::stacked`]), the projections reading the same tokens are one product.
    fn multi_head_attention<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        input: Attend<'_>,
        kernel: FusionKernel,
    ) -> (Tensor<3>, Tensor<3>) {
        let (query, [q, k, v]) = match input {
            Attend::Cross { query, context } => {
                let qkv = self.project_cross(folds, query.clone(), context);
                (query, qkv)
            }
            Attend::Within {
                tokens,
                repeats: Some(repeats),
            } => {
                let qkv = self.project_repeated(folds, tokens.clone(), repeats);
                (tokens, qkv)
            }
            Attend::Within {
                tokens,
                repeats: None,
            } => {
                let d = tokens.dims()[2];
                let qkv = match self.stacked(folds, &[&self.w_q, &self.w_k, &self.w_v], &tokens) {
                    Some(layer) => split3(layer.forward(tokens.clone()), d),
                    None => self.project_cross(folds, tokens.clone(), tokens.clone()),
                };
                (tokens, qkv)
            }
        };
        let attn = folds.apply(&self.w_o, self.attend(q, k, v, kernel));
        (query, attn)
    }

    /// `W_q·query`, `W_k·context`, `W_v·context`, the last two as one product where they stack.
    fn project_cross<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        query: Tensor<3>,
        context: Tensor<3>,
    ) -> [Tensor<3>; 3] {
        let q = folds.apply(&self.w_q, query);
        match self.stacked(folds, &[&self.w_k, &self.w_v], &context) {
            Some(layer) => {
                let d = context.dims()[2];
                let mut kv = split_columns(layer.forward(context), &[d, d]).into_iter();
                let mut next = || kv.next().expect("two blocks");
                [q, next(), next()]
            }
            None => [
                q,
                folds.apply(&self.w_k, context.clone()),
                folds.apply(&self.w_v, context),
            ],
        }
    }

    /// The three projections of `tokens`, each distinct row of `repeats` computed once.
    fn project_repeated<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        tokens: Tensor<3>,
        repeats: &RepeatedTokens,
    ) -> [Tensor<3>; 3] {
        let [b, l, d] = tokens.dims();
        let rows = select_rows(tokens.reshape([b * l, d]), 0, repeats.computed.clone());
        match self.stacked(folds, &[&self.w_q, &self.w_k, &self.w_v], &rows) {
            // One product, one gather back to the tokens, one split (`Self::stacked`).
            Some(layer) => {
                split3(
                    select_rows(layer.forward(rows), 0, repeats.token_from_computed.clone())
                        .reshape([b, l, 3 * d]),
                    d,
                )
            }
            None => [&self.w_q, &self.w_k, &self.w_v].map(|layer| {
                select_rows(
                    folds.apply(layer, rows.clone()),
                    0,
                    repeats.token_from_computed.clone(),
                )
                .reshape([b, l, d])
            }),
        }
    }

    /// `layers` (which read the same input, like `x`'s) as one shared layer where products stack
    /// ([`NormFolds::stacked`]).
    fn stacked<'a, const D: usize>(
        &'a self,
        folds: &NormFolds<'a>,
        layers: &[&'a Linear],
        x: &Tensor<D>,
    ) -> Option<lifegom_ops::shared_linear::SharedLinear> {
        let name = match layers.len() {
            3 => "query, key, value",
            _ => "key, value",
        };
        folds.stacked(layers, name, &x.device())
    }
    /// The layer after its attention: `x = LN₁(query + Dropout(attn))`, then
    /// `LN₂(x + Dropout(FFN(x)))`.
    fn feed<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        query: Tensor<3>,
        attn: Tensor<3>,
        kernel: FusionKernel,
        masks: [MaskSeed; 2],
    ) -> Tensor<3> {
        let drawn = self.kernel_draws(&query.device(), kernel, masks);
        self.feed_drawn(folds, query, attn, kernel, masks, drawn)
    }

    /// Where [`Self::feed`]'s masks are drawn inside the LayerNorm's kernels
    /// ([`add_dropped_layer_norm`]), the draws and the slot of each: on a CubeCL device, for
    /// the masks Burn's dropout would draw there. One uniform draw per mask from the device's
    /// RNG, both in one launch.
    fn kernel_draws(
        &self,
        device: &Device,
        kernel: FusionKernel,
        masks: [MaskSeed; 2],
    ) -> [Option<(Tensor<1>, usize)>; 2] {
        let in_kernel = masks.map(|mask| {
            kernel == FusionKernel::Ops
                && mask == MaskSeed::Device
                && draws_device_mask(&self.dropout, device)
        });
        let draws = in_kernel
            .contains(&true)
            .then(|| Tensor::<1>::random([2], Distribution::Uniform(0.0, 1.0), device));
        [0, 1].map(|slot| {
            draws
                .clone()
                .filter(|_| in_kernel[slot])
                .map(|draws| (draws, slot))
        })
    }

    /// [`Self::feed`] with the masks listed in `drawn` drawn inside the LayerNorm's kernels, the
    /// others by [`dropout_with`].
    fn feed_drawn<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        query: Tensor<3>,
        attn: Tensor<3>,
        kernel: FusionKernel,
        masks: [MaskSeed; 2],
        drawn: [Option<(Tensor<1>, usize)>; 2],
    ) -> Tensor<3> {
        let [first, second] = drawn;
        let x = self.add_dropped_norm(&self.norm1, query, attn, masks[0], first, kernel);
        let ff = folds.apply(
            &self.fc2,
            folds.apply_with(&self.fc1, x.clone(), Activation::Relu),
        );
        self.add_dropped_norm(&self.norm2, x, ff, masks[1], second, kernel)
    }

    /// `LN(x + Dropout(r))`: with `drawn = Some((draws, slot))` the mask is drawn inside the
    /// LayerNorm's kernels from `draws[slot]`, else by [`dropout_with`] with `mask`.
    fn add_dropped_norm(
        &self,
        norm: &LayerNorm,
        x: Tensor<3>,
        r: Tensor<3>,
        mask: MaskSeed,
        drawn: Option<(Tensor<1>, usize)>,
        kernel: FusionKernel,
    ) -> Tensor<3> {
        match (drawn, &norm.beta) {
            (Some(drawn), Some(beta)) => add_dropped_layer_norm(
                x,
                r,
                norm.gamma.val(),
                beta.val(),
                drawn,
                1.0 - self.dropout.prob,
                self.layer_norm_eps,
            ),
            _ => self.add_norm(norm, x, dropout_with(&self.dropout, r, mask), kernel),
        }
    }

    /// Scaled dot-product attention of projected `q` `[B, Lq, D]` over `k`, `v` `[B, Lk, D]`,
    /// heads side by side in the channels; `[B, Lq, D]`.
    fn attend(&self, q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, kernel: FusionKernel) -> Tensor<3> {
        match kernel {
            FusionKernel::Ops => attention(q, k, v, self.n_heads),
            FusionKernel::TensorOps => attention_reference(q, k, v, self.n_heads),
        }
    }

    /// `norm(x + residual)`.
    fn add_norm(
        &self,
        norm: &LayerNorm,
        x: Tensor<3>,
        residual: Tensor<3>,
        kernel: FusionKernel,
    ) -> Tensor<3> {
        match (kernel, &norm.beta) {
            (FusionKernel::Ops, Some(beta)) => add_layer_norm(
                x,
                residual,
                norm.gamma.val(),
                beta.val(),
                self.layer_norm_eps,
            ),
            _ => norm.forward(x + residual),
        }
    }
}

/// The two-layer fusion block.
#[derive(Config, Debug)]
pub struct FusionConfig {
    /// Feature width per view (1152 in the paper config).
    pub d_model: usize,
    /// Attention heads (6 in the paper config).
    #[config(default = 6)]
    pub n_heads: usize,
    /// Dropout (training only).
    #[config(default = 0.1)]
    pub dropout: f64,
}

/// See [`FusionConfig`].
#[derive(Module, Debug)]
pub struct Fusion {
    /// Self-attention across the views of one vertex.
    pub views: AttentionLayer,
    /// Cross-attention from the vertex embedding into the fused views.
    pub query: AttentionLayer,
}

impl FusionConfig {
    /// Builds the fusion block (feed-forward width = `d_model`, as in the reference).
    pub fn init(&self, device: &Device) -> Fusion {
        let layer = AttentionLayerConfig::new(self.d_model, self.d_model, self.n_heads)
            .with_dropout(self.dropout);
        Fusion {
            views: layer.init(device),
            query: layer.init(device),
        }
    }
}

impl Fusion {
    /// Fuses per-view features `[V, N, D]` into one `[V, D]` per vertex, queried by `embed`
    /// `[V, D]`: self-attention across each vertex's views, then cross-attention from its
    /// embedding into them. The layers are shared through `folds` with every other call on them
    /// (a reconstruction's feedback steps: one gradient product per layer on devices,
    /// design.md §7.4).
    pub fn forward<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        features: Tensor<3>,
        embed: Tensor<2>,
        run: FusionRun<'_>,
    ) -> Tensor<2> {
        let [v, _, d] = features.dims();
        let seeds = run.masks.seeds();
        if let Some(whole) = run.repeats.and_then(|r| r.whole.as_ref())
            && self.masks_are_identity(&seeds)
        {
            return self.fuse_whole_vertices(folds, features, embed, run, whole);
        }
        let layer = |masks| LayerRun {
            kernel: FusionKernel::Ops,
            masks,
        };
        let across_views = self.views.forward(
            folds,
            Attend::Within {
                tokens: features,
                repeats: run.repeats,
            },
            layer([seeds[0], seeds[1]]),
        );
        let into_vertex = Attend::Cross {
            query: embed.reshape([v, 1, d]),
            context: across_views,
        };
        self.query
            .forward(folds, into_vertex, layer([seeds[2], seeds[3]]))
            .reshape([v, d])
    }

    /// Whether none of the four masks drops anything (inference, or dropout 0): then a vertex
    /// whose tokens all repeat one value has an output that depends on nothing else of it but
    /// its embedding ([`Self::fuse_whole_vertices`]).
    fn masks_are_identity(&self, seeds: &[MaskSeed; 4]) -> bool {
        let layers = [&self.views, &self.views, &self.query, &self.query];
        seeds
            .iter()
            .zip(layers)
            .all(|(&seed, layer)| drops_nothing(&layer.dropout, seed))
    }

    /// [`Self::forward`] without dropout, where the vertices listed in `whole` have every token
    /// equal to the repeated value (hidden in every view).
    ///
    /// For such a vertex the self-attention across views sees N equal tokens, so its N outputs
    /// are one vector, the same for every such vertex. The cross-attention then has N equal keys:
    /// its softmax is uniform whatever the query, and its output after `W_o` is one constant `c`
    /// too. What is left per vertex is `x = LN₁(embed + c)` and the feed-forward block, 2·D² of
    /// the layer pair's 28·D² multiply-adds per vertex. The other vertices take the full path
    /// (their repeated tokens still projected once). Same values as the plain call up to the
    /// order of float sums: the constant comes from one vertex's rows instead of every one's.
    fn fuse_whole_vertices<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        features: Tensor<3>,
        embed: Tensor<2>,
        run: FusionRun<'_>,
        whole: &WholeVertices,
    ) -> Tensor<2> {
        let [_, _, d] = features.dims();
        let h = whole.repeated.dims()[0];
        let kernel = FusionKernel::Ops;
        let off = [MaskSeed::Off; 2];
        // One wholly repeated vertex stands for all: its views, then the constant attention.
        let first = whole.repeated.clone().slice(0..1);
        let tokens = select_rows(features.clone(), 0, first.clone());
        let across = self.views.forward(
            folds,
            Attend::Within {
                tokens,
                repeats: None,
            },
            LayerRun { kernel, masks: off },
        );
        let query = select_rows(embed.clone(), 0, first).reshape([1, 1, d]);
        let (_, constant) = self.query.multi_head_attention(
            folds,
            Attend::Cross {
                query,
                context: across,
            },
            kernel,
        );
        let repeated_embed =
            select_rows(embed.clone(), 0, whole.repeated.clone()).reshape([h, 1, d]);
        let repeated_out = self
            .query
            .feed(
                folds,
                repeated_embed,
                constant.repeat_dim(0, h),
                kernel,
                off,
            )
            .reshape([h, d]);
        let Some(kept) = &whole.kept else {
            return repeated_out;
        };
        let kept_count = kept.vertices.dims()[0];
        let kept_out = self.forward(
            folds,
            select_rows(features, 0, kept.vertices.clone()),
            select_rows(embed, 0, kept.vertices.clone()),
            FusionRun {
                masks: run.masks,
                repeats: kept.tokens.as_ref(),
            },
        );
        debug_assert_eq!(kept_out.dims(), [kept_count, d]);
        select_rows(
            Tensor::cat(vec![kept_out, repeated_out], 0),
            0,
            whole.vertex_from_stacked.clone(),
        )
    }

    /// The four dropout masks one training call of [`Self::forward`] on `device` would apply,
    /// as seeds drawn now from the device's RNG in the same order ([`MaskSeed::Off`] where a
    /// layer draws none: frozen, not training, no autodiff, dropout 0). `None` on a CubeCL
    /// device, where Burn draws the masks on the device. With them, a call on an inference copy
    /// of the weights ([`Module::valid`]) applies the same masks without building a graph, on
    /// any thread.
    pub fn draw_mask_seeds(&self, device: &Device) -> Option<[MaskSeed; 4]> {
        let (views, query) = (&self.views.dropout, &self.query.dropout);
        host_mask_seeds([views, views, query, query], device)
    }
}

/// Where a [`Fusion`] call's four dropout masks come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FusionMasks {
    /// Drawn from the device's RNG as the call goes (Burn's training rule).
    #[default]
    Device,
    /// From [`Fusion::draw_mask_seeds`]: fixed before the call, so the call may run on
    /// inference weights and on any thread.
    Given([MaskSeed; 4]),
}

impl FusionMasks {
    /// The seed of each mask, in the order the layers apply them.
    fn seeds(self) -> [MaskSeed; 4] {
        match self {
            Self::Device => [MaskSeed::Device; 4],
            Self::Given(seeds) => seeds,
        }
    }
}

/// How one [`Fusion::forward`] call computes, beside its inputs.
#[derive(Debug, Clone, Copy, Default)]
pub struct FusionRun<'r> {
    /// Where its four dropout masks come from.
    pub masks: FusionMasks,
    /// The view tokens known to repeat one value, if any (a vertex hidden in a view has the
    /// visibility embedding as its token there): their first-layer projections are computed
    /// once, and vertices hidden in every view once for all where nothing is dropped
    /// (design.md §7.4).
    pub repeats: Option<&'r RepeatedTokens>,
}

/// Which of a `[V, N]` grid of view tokens repeat one value, so that the fusion's first layer
/// projects each distinct row once ([`FusionRun::repeats`]).
///
/// `computed` `[U]` lists the flat token indices (`vertex·N + view`) whose rows are projected:
/// every token that is its own, then one representative of the repeated ones.
/// `token_from_computed` `[V·N]` gives, for each token, the position in `computed` of the row
/// it takes. `whole` lists the vertices all of whose tokens repeat the value, which a call
/// without dropout computes once for all ([`Fusion`]'s `fuse_whole_vertices`).
#[derive(Debug, Clone)]
pub struct RepeatedTokens {
    computed: Tensor<1, Int>,
    token_from_computed: Tensor<1, Int>,
    whole: Option<Box<WholeVertices>>,
}

/// The vertices of a [`RepeatedTokens`] grid whose every token is the repeated value.
#[derive(Debug, Clone)]
struct WholeVertices {
    /// `[H]` their indices, ascending.
    repeated: Tensor<1, Int>,
    /// The other vertices; `None` when every vertex is wholly repeated.
    kept: Option<KeptVertices>,
    /// `[V]`: for each vertex, its row in `cat(kept, repeated)`.
    vertex_from_stacked: Tensor<1, Int>,
}

/// The vertices with a token of their own, and the repeated tokens among theirs.
#[derive(Debug, Clone)]
struct KeptVertices {
    /// `[S]` their indices, ascending.
    vertices: Tensor<1, Int>,
    /// Their `[S, N]` grid's repeated tokens (without wholly repeated vertices, by construction).
    tokens: Option<RepeatedTokens>,
}

impl RepeatedTokens {
    /// From a host mask over the flat tokens of `views` tokens per vertex: `repeated[t]` is
    /// true where token `t` holds the shared value. `None` when fewer than two tokens share it
    /// (nothing to save).
    ///
    /// # Panics
    ///
    /// If `views` is 0 or does not divide the mask's length.
    pub fn from_mask(repeated: &[bool], views: usize, device: &Device) -> Option<Self> {
        assert!(
            views > 0 && repeated.len().is_multiple_of(views),
            "{} tokens are not whole vertices of {views} views",
            repeated.len()
        );
        if repeated.iter().filter(|&&r| r).count() < 2 {
            return None;
        }
        let (computed, token_from_computed) = Self::token_tables(repeated);
        let whole_vertex = |vertex: &[bool]| vertex.iter().all(|&r| r);
        let (mut kept, mut whole): (Vec<usize>, Vec<usize>) = (Vec::new(), Vec::new());
        for (i, vertex) in repeated.chunks_exact(views).enumerate() {
            if whole_vertex(vertex) {
                whole.push(i);
            } else {
                kept.push(i);
            }
        }
        // A single wholly repeated vertex saves nothing over the full path.
        let whole = (whole.len() >= 2).then(|| {
            let mut vertex_from_stacked = vec![0i64; kept.len() + whole.len()];
            for (row, &vertex) in kept.iter().chain(&whole).enumerate() {
                vertex_from_stacked[vertex] = row as i64;
            }
            let kept = (!kept.is_empty()).then(|| {
                let kept_mask: Vec<bool> = kept
                    .iter()
                    .flat_map(|&i| repeated[i * views..(i + 1) * views].iter().copied())
                    .collect();
                KeptVertices {
                    vertices: index_tensor(kept.iter().map(|&i| i as i64).collect(), device),
                    tokens: Self::from_mask(&kept_mask, views, device),
                }
            });
            Box::new(WholeVertices {
                repeated: index_tensor(whole.iter().map(|&i| i as i64).collect(), device),
                kept,
                vertex_from_stacked: index_tensor(vertex_from_stacked, device),
            })
        });
        Some(Self {
            computed: index_tensor(computed, device),
            token_from_computed: index_tensor(token_from_computed, device),
            whole,
        })
    }

    /// `computed` and `token_from_computed` (type docs) of a flat mask.
    fn token_tables(repeated: &[bool]) -> (Vec<i64>, Vec<i64>) {
        let mut computed: Vec<i64> = Vec::with_capacity(repeated.len());
        let mut token_from_computed = vec![0i64; repeated.len()];
        for (token, _) in repeated.iter().enumerate().filter(|(_, r)| !**r) {
            token_from_computed[token] = computed.len() as i64;
            computed.push(token as i64);
        }
        let shared = computed.len() as i64;
        computed.push(repeated.iter().position(|&r| r).unwrap_or(0) as i64);
        for (token, _) in repeated.iter().enumerate().filter(|(_, r)| **r) {
            token_from_computed[token] = shared;
        }
        (computed, token_from_computed)
    }

    /// The number of rows projected, `U`.
    pub fn computed_rows(&self) -> usize {
        self.computed.dims()[0]
    }

    /// The number of vertices whose every token is the repeated value, where a call without
    /// dropout computes them once for all (0 when fewer than two).
    pub fn whole_vertices(&self) -> usize {
        self.whole.as_ref().map_or(0, |w| w.repeated.dims()[0])
    }
}

/// `t` `[.., 3d]` as its three `[.., d]` column blocks.
fn split3(t: Tensor<3>, d: usize) -> [Tensor<3>; 3] {
    let mut blocks = split_columns(t, &[d, d, d]).into_iter();
    let mut next = || blocks.next().expect("three blocks");
    [next(), next(), next()]
}

fn index_tensor(values: Vec<i64>, device: &Device) -> Tensor<1, Int> {
    let n = values.len();
    Tensor::<1, Int>::from_data(TensorData::new(values, [n]), device)
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::Distribution;

    use lifegom_ops::activation::relu;

    use lifegom_render::testing::read;

    /// Two passes of the block through one set of folds (as the feedback steps run it), without
    /// dropout: the output of the second and every parameter's gradient, on `device`.
    fn two_folded_passes(fusion: &Fusion, device: &Device) -> Vec<(String, Vec<f32>)> {
        let mut rng = lifegom_render::rng::Rng::new(17);
        let mut draw = |shape: [usize; 3]| {
            let values: Vec<f32> = (0..shape.iter().product::<usize>())
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            Tensor::<3>::from_data(TensorData::new(values, shape), device)
        };
        let feats = draw([7, 3, 24]);
        let embed = draw([1, 7, 24]).reshape([7, 24]);
        let folds = NormFolds::new();
        let first = fusion.forward(&folds, feats.clone(), embed.clone(), FusionRun::default());
        let again = feats * 0.5 + first.clone().unsqueeze_dim::<3>(1);
        let out = fusion.forward(&folds, again, embed, FusionRun::default());
        let grads = (out.clone() * out.clone().sin()).sum().backward();
        let mut all = vec![("output".to_string(), read(out))];
        all.extend(crate::test_grads::parameter_grads(fusion, &grads));
        all
    }

    /// On lavapipe, where the query, key and value (and the second layer's key and value) are
    /// one stacked product split in one launch, two folded passes equal Flex's separate
    /// products: the output and every parameter's gradient.
    #[test]
    fn stacked_projections_match_flex_wgpu() {
        let Some(device) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        let flex = Device::flex().autodiff();
        let fusion = FusionConfig::new(24)
            .with_n_heads(3)
            .with_dropout(0.0)
            .init(&flex);
        let device = device.autodiff();
        let on_wgpu = fusion.clone().fork(&device);
        let want = two_folded_passes(&fusion, &flex);
        let got = two_folded_passes(&on_wgpu, &device);
        assert_eq!(want.len(), got.len());
        assert!(want.len() > 10, "every projection takes a gradient");
        let largest = |v: &[f32]| v.iter().fold(0f32, |m, x| m.max(x.abs()));
        // Gradients that are zero in exact arithmetic (the key biases: a shift of every key
        // leaves each softmax as it was) are rounding noise on both devices: a floor of a
        // millionth of the largest gradient holds them.
        let floor = 1e-6 * want.iter().map(|(_, v)| largest(v)).fold(0f32, f32::max);
        for ((name, b), (_, a)) in want.iter().zip(&got) {
            let diff = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
            let tolerance = 1e-4 * largest(b) + floor;
            assert!(
                diff <= tolerance,
                "{name}: max diff {diff:.2e}, tolerance {tolerance:.2e}"
            );
        }
    }

    fn shapes_and_view_permutation(device: &Device) {
        let fusion = FusionConfig::new(24).with_n_heads(3).init(device);
        let feats = Tensor::<3>::random([5, 4, 24], Distribution::Normal(0.0, 1.0), device);
        let embed = Tensor::<2>::random([5, 24], Distribution::Normal(0.0, 1.0), device);
        let out = fusion.forward(
            &NormFolds::new(),
            feats.clone(),
            embed.clone(),
            FusionRun::default(),
        );
        assert_eq!(out.dims(), [5, 24]);
        // Views are a set: permuting them leaves the fused vertex feature unchanged.
        let perm = Tensor::<1, burn::tensor::Int>::from_data(
            TensorData::new(vec![2i64, 0, 3, 1], [4]),
            device,
        );
        let out_perm = fusion.forward(
            &NormFolds::new(),
            feats.select(1, perm),
            embed,
            FusionRun::default(),
        );
        for (a, b) in read(out).iter().zip(read(out_perm)) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
    }

    /// A single head over a single view is a plain MLP-like map: check against a hand-computed
    /// attention (softmax over one key is 1, so the output is LN-layers of W_o·W_v·x).
    fn single_view_attention_is_value_projection(device: &Device) {
        let layer = AttentionLayerConfig::new(4, 4, 1)
            .with_dropout(0.0)
            .init(device);
        let q = Tensor::<3>::random([2, 1, 4], Distribution::Normal(0.0, 1.0), device);
        let c = Tensor::<3>::random([2, 1, 4], Distribution::Normal(0.0, 1.0), device);
        let cross = Attend::Cross {
            query: q.clone(),
            context: c.clone(),
        };
        let out = layer.forward(&NormFolds::new(), cross, LayerRun::default());
        let attn = layer.w_o.forward(layer.w_v.forward(c));
        let x = layer.norm1.forward(q + attn);
        let expect = layer
            .norm2
            .forward(x.clone() + layer.fc2.forward(relu(layer.fc1.forward(x))));
        for (a, b) in read(out).iter().zip(read(expect)) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    fn gradients_reach_every_parameter(device: &Device) {
        let ad = device.clone().autodiff();
        let fusion = FusionConfig::new(12)
            .with_n_heads(2)
            .with_dropout(0.0)
            .init(&ad);
        let feats = Tensor::<3>::random([3, 2, 12], Distribution::Normal(0.0, 1.0), &ad);
        let embed =
            Tensor::<2>::random([3, 12], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let grads = (fusion
            .forward(
                &NormFolds::new(),
                feats,
                embed.clone(),
                FusionRun::default(),
            )
            .powi_scalar(2))
        .sum()
        .backward();
        assert!(embed.grad(&grads).is_some());
        for layer in [&fusion.views, &fusion.query] {
            for lin in [
                &layer.w_q, &layer.w_k, &layer.w_v, &layer.w_o, &layer.fc1, &layer.fc2,
            ] {
                let g = lin
                    .weight
                    .val()
                    .grad(&grads)
                    .expect("every linear gets a gradient");
                assert!(read(g).iter().all(|v| v.is_finite()));
            }
        }
    }

    /// The custom ops give the tensor-op compositions' outputs and gradients (inputs and every
    /// parameter) up to float summation order, for self-attention over views (Lq = Lk) and the
    /// single-query cross-attention.
    fn host_ops_equal_tensor_ops(device: &Device) {
        let ad = device.clone().autodiff();
        // Widths (d, heads) of 24/4 and of 160/2, whose 80 channels per head are more than the
        // CubeCL kernels' threads per cube; 17 keys run as tensor ops on a device.
        for (d, heads, lq, lk) in [
            (24, 4, 3, 3),
            (24, 4, 1, 3),
            (24, 4, 1, 5),
            (160, 2, 2, 4),
            (24, 4, 1, 17),
        ] {
            let layer = AttentionLayerConfig::new(d, 24, heads)
                .with_dropout(0.0)
                .init(&ad);
            let b = 150; // more than one rayon task of the kernels
            let q =
                Tensor::<3>::random([b, lq, d], Distribution::Normal(0.0, 1.0), &ad).require_grad();
            let c =
                Tensor::<3>::random([b, lk, d], Distribution::Normal(0.0, 1.0), &ad).require_grad();
            let w = Tensor::<3>::random([b, lq, d], Distribution::Normal(0.0, 1.0), &ad);
            let run = |kernel| {
                let input = Attend::Cross {
                    query: q.clone(),
                    context: c.clone(),
                };
                let out = layer.forward(
                    &NormFolds::new(),
                    input,
                    LayerRun {
                        kernel,
                        ..LayerRun::default()
                    },
                );
                let grads = (out.clone() * w.clone()).sum().backward();
                (out, grads)
            };
            let (out_ops, g_ops) = run(FusionKernel::Ops);
            let (out_ref, g_ref) = run(FusionKernel::TensorOps);
            let close = |a: Tensor<3>, b: Tensor<3>, what: &str| {
                let (a, b) = (read(a), read(b));
                let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                for (i, (x, y)) in a.iter().zip(&b).enumerate() {
                    assert!(
                        (x - y).abs() <= 1e-5 * scale,
                        "{what}[{i}] (Lq {lq}, Lk {lk}): ops {x} vs tensor ops {y}"
                    );
                }
            };
            close(out_ops, out_ref, "output");
            close(
                q.grad(&g_ops).expect("query gradient"),
                q.grad(&g_ref).expect("query gradient"),
                "query gradient",
            );
            close(
                c.grad(&g_ops).expect("context gradient"),
                c.grad(&g_ref).expect("context gradient"),
                "context gradient",
            );
            let params = |g: &burn::tensor::Gradients| {
                let mut all: Vec<f32> = Vec::new();
                for lin in [
                    &layer.w_q, &layer.w_k, &layer.w_v, &layer.w_o, &layer.fc1, &layer.fc2,
                ] {
                    all.extend(read(lin.weight.val().grad(g).expect("weight gradient")));
                    let bias = lin.bias.as_ref().expect("biases").val();
                    all.extend(read(bias.grad(g).expect("bias gradient")));
                }
                for norm in [&layer.norm1, &layer.norm2] {
                    all.extend(read(norm.gamma.val().grad(g).expect("gamma gradient")));
                    let beta = norm.beta.as_ref().expect("beta").val();
                    all.extend(read(beta.grad(g).expect("beta gradient")));
                }
                all
            };
            let (a, b) = (params(&g_ops), params(&g_ref));
            let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
            for (i, (x, y)) in a.iter().zip(&b).enumerate() {
                assert!(
                    (x - y).abs() <= 1e-5 * scale,
                    "parameter gradient {i} (Lq {lq}, Lk {lk}): ops {x} vs tensor ops {y}"
                );
            }
        }
    }

    lifegom_render::cpu_backend_tests!(host_ops => host_ops_equal_tensor_ops);

    /// On wgpu the residual LayerNorm and the attention core run as the ops' CubeCL kernels
    /// ([`FusionKernel::Ops`] on a CubeCL device).
    #[test]
    fn device_ops_equal_tensor_ops_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            host_ops_equal_tensor_ops(&device);
        }
    }

    /// On wgpu, a training call's masks drawn inside the LayerNorm kernels from draws `[a, b]`
    /// (`AttentionLayer`'s `feed_drawn`) give the output and gradients of the tensor-op
    /// composition with the host's masks ([`lifegom_ops::dropout::kernel_mask`]): `a`'s after the
    /// attention, `b`'s after the feed-forward block, each on the residual branch.
    #[test]
    fn masks_drawn_in_kernels_wgpu() {
        let Some(device) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let (b, l, d) = (40, 3, 24);
        let keep = 0.75;
        let layer = AttentionLayerConfig::new(d, 32, 3)
            .with_dropout(1.0 - keep)
            .init(&ad);
        let mut rng = lifegom_render::rng::Rng::new(23);
        let mut draw = |shape: [usize; 3]| {
            let values: Vec<f32> = (0..shape.iter().product::<usize>())
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            Tensor::<3>::from_data(TensorData::new(values, shape), &ad).require_grad()
        };
        let (q, c, w) = (draw([b, l, d]), draw([b, l, d]), draw([b, l, d]).detach());
        let draws = [0.375f32, 0.8125];
        let mask = |draw: f32| {
            let values = lifegom_ops::dropout::kernel_mask(b * l * d, keep, draw);
            Tensor::<3>::from_data(TensorData::new(values, [b, l, d]), &ad)
        };
        let folds = NormFolds::new();
        let kernel = FusionKernel::Ops;
        let drawn = Tensor::<1>::from_floats(draws, &ad);
        let cross = || Attend::Cross {
            query: q.clone(),
            context: c.clone(),
        };
        let (_, attn) = layer.multi_head_attention(&folds, cross(), kernel);
        let got = layer.feed_drawn(
            &folds,
            q.clone(),
            attn,
            kernel,
            [MaskSeed::Device; 2],
            [Some((drawn.clone(), 0)), Some((drawn, 1))],
        );
        let (_, attn) = layer.multi_head_attention(&NormFolds::new(), cross(), kernel);
        let x = layer.norm1.forward(q.clone() + attn * mask(draws[0]));
        let ff = layer.fc2.forward(relu(layer.fc1.forward(x.clone())));
        let want = layer.norm2.forward(x + ff * mask(draws[1]));
        let gradients = |out: Tensor<3>| {
            let grads = (out.clone() * w.clone()).sum().backward();
            let mut all = vec![read(out)];
            all.extend([&q, &c].map(|t| read(t.grad(&grads).expect("an input's gradient"))));
            all
        };
        let (got, want) = (gradients(got), gradients(want));
        for (what, (a, e)) in ["output", "∂query", "∂context"]
            .iter()
            .zip(got.iter().zip(&want))
        {
            let scale = e.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
            for (i, (x, y)) in a.iter().zip(e).enumerate() {
                assert!((x - y).abs() <= 1e-4 * scale, "{what}[{i}]: {x} vs {y}");
            }
        }
        let dropped = read(mask(draws[0])).iter().filter(|&&m| m == 0.0).count();
        assert!(
            dropped > 0,
            "the mask drops some of the {} elements",
            b * l * d
        );
    }

    /// A training call with given mask seeds computes the same on an inference copy of the
    /// weights as on the tracked ones (what `Reconstructor::fuse_branches` runs on a second
    /// thread), and the masks are applied. That the seeds equal what a sequential run draws is
    /// `tests/dropout_order.rs` (its own binary: the device RNG is process-wide).
    fn given_masks_on_inference_weights(device: &Device) {
        let ad = device.clone().autodiff();
        let fusion = FusionConfig::new(12)
            .with_n_heads(2)
            .with_dropout(0.3)
            .init(&ad);
        let features = Tensor::<3>::random([40, 3, 12], Distribution::Normal(0.0, 1.0), &ad);
        let embed = Tensor::<2>::random([40, 12], Distribution::Normal(0.0, 1.0), &ad);
        let masks = fusion.draw_mask_seeds(&ad).expect("a host device");
        assert!(
            masks.iter().all(|m| matches!(m, MaskSeed::Given(_))),
            "a training call draws four masks"
        );
        let given = FusionRun {
            masks: FusionMasks::Given(masks),
            repeats: None,
        };
        let tracked =
            read(fusion.forward(&NormFolds::new(), features.clone(), embed.clone(), given));
        let inference = fusion.valid();
        let copy = read(inference.forward(
            &NormFolds::new(),
            features.clone().inner(),
            embed.clone().inner(),
            given,
        ));
        assert_eq!(tracked, copy);
        let unmasked = read(inference.forward(
            &NormFolds::new(),
            features.inner(),
            embed.inner(),
            FusionRun::default(),
        ));
        assert_ne!(copy, unmasked, "the masks were applied");
        // Off the autodiff device, and on frozen (inference) layers, no mask is drawn.
        assert_eq!(fusion.draw_mask_seeds(device), Some([MaskSeed::Off; 4]));
        assert_eq!(inference.draw_mask_seeds(&ad), Some([MaskSeed::Off; 4]));
    }

    lifegom_render::cpu_backend_tests!(given_masks => given_masks_on_inference_weights);

    /// Projecting repeated tokens once (`FusionRun::repeats`) against the plain call, in training
    /// (dropout on, the same masks): output, and the gradients of the per-view features, of the
    /// shared value, of the vertex embeddings and of the first layer's projections. The tokens
    /// are blended as the reconstructor blends them (`f·vis + e·(1 − vis)`), with vertices
    /// hidden in some views, in every view, and in none.
    fn repeated_tokens_equal_dense(device: &Device) {
        let ad = device.clone().autodiff();
        let (v, n, d) = (40usize, 3usize, 12usize);
        let fusion = FusionConfig::new(d)
            .with_n_heads(2)
            .with_dropout(0.3)
            .init(&ad);
        let f = Tensor::<3>::random([v, n, d], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let e = Tensor::<1>::random([d], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        let embed = Tensor::<2>::random([v, d], Distribution::Normal(0.0, 1.0), &ad).require_grad();
        // Vertex i: hidden in every view when i % 4 == 0, visible everywhere when i % 4 == 1,
        // else hidden in the views below i % 3.
        let visible: Vec<bool> = (0..v * n)
            .map(|t| {
                let (i, view) = (t / n, t % n);
                match i % 4 {
                    0 => false,
                    1 => true,
                    _ => view >= i % 3,
                }
            })
            .collect();
        let vis = Tensor::<3>::from_data(
            TensorData::new(
                visible.iter().map(|&x| f32::from(u8::from(x))).collect(),
                [v, n, 1],
            ),
            &ad,
        );
        let hidden: Vec<bool> = visible.iter().map(|x| !x).collect();
        let repeats = RepeatedTokens::from_mask(&hidden, n, &ad).expect("repeated tokens");
        assert_eq!(
            repeats.computed_rows(),
            visible.iter().filter(|&&x| x).count() + 1
        );
        let masks = FusionMasks::Given(fusion.draw_mask_seeds(&ad).expect("a host device"));
        let w = Tensor::<2>::random([v, d], Distribution::Normal(0.0, 1.0), &ad);
        let run = |repeated: bool| {
            // Built per run: a backward consumes the graph it walks.
            let tokens = f.clone() * vis.clone()
                + e.clone().reshape([1, 1, d]) * (vis.ones_like() - vis.clone());
            let out = fusion.forward(
                &NormFolds::new(),
                tokens.clone(),
                embed.clone(),
                FusionRun {
                    masks,
                    repeats: repeated.then_some(&repeats),
                },
            );
            let g = (out.clone() * w.clone()).sum().backward();
            let mut all = vec![
                read(out),
                read(f.grad(&g).expect("feature gradient")),
                read(e.grad(&g).expect("shared-value gradient")),
                read(embed.grad(&g).expect("embedding gradient")),
            ];
            for lin in [&fusion.views.w_q, &fusion.views.w_k, &fusion.views.w_v] {
                all.push(read(lin.weight.val().grad(&g).expect("weight gradient")));
                let bias = lin.bias.as_ref().expect("biases").val();
                all.push(read(bias.grad(&g).expect("bias gradient")));
            }
            all
        };
        let (got, want) = (run(true), run(false));
        let names = [
            "output", "d f", "d e", "d embed", "d W_q", "d b_q", "d W_k", "d b_k",
        ];
        let max_abs = |t: &[f32]| t.iter().fold(0f32, |m, x| m.max(x.abs()));
        for (k, (a, b)) in got.iter().zip(&want).enumerate() {
            if k == 7 {
                // The key bias's gradient is zero in exact arithmetic (a softmax does not see a
                // shift shared by all keys): both sides hold rounding noise, held to the scale
                // of the key weights' gradient.
                let noise = 1e-5 * max_abs(&want[6]);
                assert!(
                    max_abs(a) <= noise && max_abs(b) <= noise,
                    "d b_k: {a:?} vs {b:?}"
                );
                continue;
            }
            let scale = max_abs(b).max(1e-3);
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(
                    (x - y).abs() <= 2e-6 * scale,
                    "{}[{i}]: repeated {x} vs plain {y}",
                    names.get(k).unwrap_or(&"d W_v / d b_v")
                );
            }
        }
    }

    lifegom_render::cpu_backend_tests!(repeated_tokens => repeated_tokens_equal_dense);

    /// Without dropout, vertices hidden in every view computed once for all
    /// (`fuse_whole_vertices`) against the plain call: inference on the plain device, and a
    /// dropout-0 training call on autodiff, where the gradients of the features, the shared
    /// value, the embeddings and every weight must agree too. Some vertices are hidden in every
    /// view, some in a few, some in none; then every vertex is hidden.
    fn whole_vertices_equal_dense(device: &Device) {
        let (v, n, d) = (30usize, 3usize, 12usize);
        // Vertex i: hidden in every view when i % 3 == 0, in the first view when i % 3 == 1.
        let partly: Vec<bool> = (0..v * n)
            .map(|t| match (t / n) % 3 {
                0 => true,
                1 => t % n == 0,
                _ => false,
            })
            .collect();
        let everywhere = vec![true; v * n];
        for (hidden, whole) in [(&partly, v / 3), (&everywhere, v)] {
            for ad in [device.clone(), device.clone().autodiff()] {
                let fusion = FusionConfig::new(d)
                    .with_n_heads(2)
                    .with_dropout(if ad.is_autodiff() { 0.0 } else { 0.3 })
                    .init(&ad);
                let masks = fusion.draw_mask_seeds(&ad).expect("a host device");
                assert_eq!(masks, [MaskSeed::Off; 4], "no mask: inference or dropout 0");
                let repeats = RepeatedTokens::from_mask(hidden, n, &ad).expect("repeats");
                assert_eq!(repeats.whole_vertices(), whole);
                let tracked = |t: Tensor<3>| {
                    if ad.is_autodiff() {
                        t.require_grad()
                    } else {
                        t
                    }
                };
                let normal = Distribution::Normal(0.0, 1.0);
                let f = tracked(Tensor::<3>::random([v, n, d], normal, &ad));
                let e = tracked(Tensor::<3>::random([1, 1, d], normal, &ad));
                let embed = tracked(Tensor::<3>::random([v, 1, d], normal, &ad));
                let vis = Tensor::<3>::from_data(
                    TensorData::new(
                        hidden.iter().map(|&x| f32::from(u8::from(!x))).collect(),
                        [v, n, 1],
                    ),
                    &ad,
                );
                let w = Tensor::<2>::random([v, d], Distribution::Normal(0.0, 1.0), &ad);
                let run = |repeated: bool| {
                    let tokens =
                        f.clone() * vis.clone() + e.clone() * (vis.ones_like() - vis.clone());
                    let masks = FusionMasks::Given(masks);
                    let query = embed.clone().reshape([v, d]);
                    let out = fusion.forward(
                        &NormFolds::new(),
                        tokens,
                        query,
                        FusionRun {
                            masks,
                            repeats: repeated.then_some(&repeats),
                        },
                    );
                    let mut all = vec![read(out.clone())];
                    if ad.is_autodiff() {
                        let g = (out * w.clone()).sum().backward();
                        all.push(read(e.grad(&g).expect("shared-value gradient")));
                        all.push(read(embed.grad(&g).expect("embedding gradient")));
                        if whole < v {
                            all.push(read(f.grad(&g).expect("feature gradient")));
                        }
                        for layer in [&fusion.views, &fusion.query] {
                            // With every vertex wholly hidden, each attention's keys are equal
                            // and its W_q gradient is zero in exact arithmetic (a softmax over
                            // equal scores does not move with the query): rounding noise on
                            // both sides, not compared.
                            let w_q = (whole < v).then_some(&layer.w_q);
                            for lin in w_q
                                .into_iter()
                                .chain([&layer.w_o, &layer.w_v, &layer.fc1, &layer.fc2])
                            {
                                all.push(read(lin.weight.val().grad(&g).expect("weight")));
                            }
                            all.push(read(layer.norm1.gamma.val().grad(&g).expect("gamma")));
                        }
                    }
                    all
                };
                let (got, want) = (run(true), run(false));
                assert_eq!(got.len(), want.len());
                for (k, (a, b)) in got.iter().zip(&want).enumerate() {
                    let scale = b.iter().fold(1e-3f32, |m, x| m.max(x.abs()));
                    for (i, (x, y)) in a.iter().zip(b).enumerate() {
                        assert!(
                            (x - y).abs() <= 1e-5 * scale,
                            "part {k}[{i}] ({whole} of {v} wholly hidden, autodiff {}): \
                             shortcut {x} vs plain {y}",
                            ad.is_autodiff()
                        );
                    }
                }
            }
        }
    }

    lifegom_render::cpu_backend_tests!(whole_vertices => whole_vertices_equal_dense);

    #[test]
    fn repeated_tokens_index_tables() {
        let device = Device::flex();
        assert!(RepeatedTokens::from_mask(&[false, true, false], 1, &device).is_none());
        let r = RepeatedTokens::from_mask(&[true, false, true, true, false], 1, &device).unwrap();
        let ints = |t: Tensor<1, Int>| t.into_data().convert::<i64>().to_vec::<i64>().unwrap();
        assert_eq!(ints(r.computed.clone()), [1, 4, 0]);
        assert_eq!(ints(r.token_from_computed.clone()), [2, 0, 2, 2, 1]);
        // One view per vertex: vertices 0, 2 and 3 are wholly repeated, 1 and 4 kept.
        let whole = r.whole.as_ref().expect("three wholly repeated vertices");
        assert_eq!(ints(whole.repeated.clone()), [0, 2, 3]);
        let kept = whole.kept.as_ref().expect("kept vertices");
        assert_eq!(ints(kept.vertices.clone()), [1, 4]);
        assert!(kept.tokens.is_none(), "the kept vertices repeat nothing");
        assert_eq!(ints(whole.vertex_from_stacked.clone()), [2, 0, 3, 4, 1]);
        // Two views: vertex 0 is wholly repeated, vertex 1 half; one whole vertex saves nothing.
        let r = RepeatedTokens::from_mask(&[true, true, true, false], 2, &device).unwrap();
        assert_eq!(r.whole_vertices(), 0);
    }

    #[test]
    fn fusion_ndarray() {
        let d = Device::ndarray();
        shapes_and_view_permutation(&d);
        single_view_attention_is_value_projection(&d);
        gradients_reach_every_parameter(&d);
    }

    #[test]
    fn fusion_flex() {
        let d = Device::flex();
        shapes_and_view_permutation(&d);
        single_view_attention_is_value_projection(&d);
        gradients_reach_every_parameter(&d);
    }
}
