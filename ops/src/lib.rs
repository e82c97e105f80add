//! # lifegom-ops
//!
//! The fused ops of the LIFe-GoM network, each a Burn backend extension (design.md §1.4): the
//! paper's layers (`lifegom-model`) call these functions on plain tensors, and each op runs as
//! slice code on the CPU backends and as CubeCL kernels on GPU devices, with a hand-written
//! backward for autodiff and glue for Burn's kernel fusion.
//!
//! An op is laid out as the rasterizer's are (`lifegom-render`): `mod.rs` holds the public
//! function and the reference it is tested against, `op.rs` the extension trait with its autodiff
//! and fusion glue, `cube.rs` the kernels; the parity tests live with the op.
//!
//! | module | op |
//! |---|---|
//! | [`activation`] | the activations the products end with, and a ReLU with a one-launch backward |
//! | [`linear_op`] | Burn's `Linear` on the CPU backends as one product with its bias |
//! | [`shared_linear`] | a layer the feedback passes share: one weight gradient for all passes on devices |
//! | [`split_k`] | weight gradients over many rows as chunked products and a sum on devices |
//! | [`handoff`] | a gradient one backward node hands to another, which adds it in its own launch |
//! | [`frozen_affine`] | a frozen BatchNorm as a per-channel `(scale, shift)` |
//! | [`gemm_conv`] | the encoder's convolutions as patch columns and one product on devices |
//! | [`conv_norm`] | a convolution and its BatchNorm as one shared product on devices |
//! | [`channel_norm`] | a per-channel affine map (and ReLU) over NCHW maps on devices |
//! | [`sampling`] | projection of posed vertices and torch-exact bilinear feature sampling |
//! | [`dropout`] | the fusion layers' dropout, with masks drawn on the host on CPU backends |
//! | [`fusion`] | the fusion layers' attention core and residual LayerNorms |
//! | [`knn`] | farthest point sampling and kNN on the host, the Point Transformer's hierarchy |
//! | [`grouping`] | the Point Transformer's offsets `p_j − p_i`, one op on devices |
//! | [`vector_attention`] | the Point Transformer layer's positional encoding, relation and aggregation |
//! | [`neighbour_max`] | the Point Transformer's max over each point's neighbours |
//! | [`interpolation`] | the Point Transformer's transition-up interpolation, one op on devices |

pub mod activation;
pub mod channel_norm;
pub mod conv_norm;
pub mod dropout;
pub mod frozen_affine;
pub mod fusion;
pub mod gemm_conv;
pub mod grouping;
pub mod handoff;
pub mod interpolation;
mod inverse;
pub mod knn;
mod lanes;
pub mod linear_op;
pub mod neighbour_max;
pub mod sampling;
pub mod shared_linear;
pub mod split_k;
pub mod vector_attention;
