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

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Dropout, DropoutConfig, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::activation::{relu, softmax};
use burn::tensor::{Device, Tensor};

use crate::dropout::dropout;

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
        }
    }
}

impl AttentionLayer {
    /// `query` `[B, Lq, D]` attends to `context` `[B, Lk, D]`; returns `[B, Lq, D]`.
    pub fn forward(&self, query: Tensor<3>, context: Tensor<3>) -> Tensor<3> {
        let [b, lq, d] = query.dims();
        let [_, lk, _] = context.dims();
        let h = self.n_heads;
        let dk = d / h;
        let heads = |t: Tensor<3>, l: usize| t.reshape([b, l, h, dk]).swap_dims(1, 2); // [B,H,L,dk]
        let q = heads(self.w_q.forward(query.clone()), lq);
        let k = heads(self.w_k.forward(context.clone()), lk);
        let v = heads(self.w_v.forward(context), lk);
        let scores = q.matmul(k.swap_dims(2, 3)) / (dk as f64).sqrt();
        let attn = softmax(scores, 3).matmul(v); // [B,H,Lq,dk]
        let attn = self.w_o.forward(attn.swap_dims(1, 2).reshape([b, lq, d]));
        let x = self.norm1.forward(query + dropout(&self.dropout, attn));
        let ff = self.fc2.forward(relu(self.fc1.forward(x.clone())));
        self.norm2.forward(x + dropout(&self.dropout, ff))
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
    /// `[V, D]`.
    pub fn forward(&self, features: Tensor<3>, embed: Tensor<2>) -> Tensor<2> {
        let [v, _, d] = features.dims();
        let across_views = self.views.forward(features.clone(), features);
        self.query
            .forward(embed.reshape([v, 1, d]), across_views)
            .reshape([v, d])
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::{Distribution, TensorData};

    use lifegom_render::testing::read;

    fn shapes_and_view_permutation(device: &Device) {
        let fusion = FusionConfig::new(24).with_n_heads(3).init(device);
        let feats = Tensor::<3>::random([5, 4, 24], Distribution::Normal(0.0, 1.0), device);
        let embed = Tensor::<2>::random([5, 24], Distribution::Normal(0.0, 1.0), device);
        let out = fusion.forward(feats.clone(), embed.clone());
        assert_eq!(out.dims(), [5, 24]);
        // Views are a set: permuting them leaves the fused vertex feature unchanged.
        let perm = Tensor::<1, burn::tensor::Int>::from_data(
            TensorData::new(vec![2i64, 0, 3, 1], [4]),
            device,
        );
        let out_perm = fusion.forward(feats.select(1, perm), embed);
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
        let out = layer.forward(q.clone(), c.clone());
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
        let grads = (fusion.forward(feats, embed.clone()).powi_scalar(2))
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
