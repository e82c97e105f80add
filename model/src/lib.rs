//! # lifegom-model
//!
//! The LIFe-GoM reconstructor (design.md §2): from N source images with cameras and body poses,
//! predict a canonical T-pose Gaussians-on-Mesh, refined by T steps of learned feedback that
//! compare re-renders of the current avatar with the inputs; then render it in any pose.
//!
//! ```
//! use burn::tensor::{Device, Distribution, Tensor};
//! use glam::Vec3;
//! use lifegom_model::reconstructor::{ReconstructorConfig, SourceViews, CanonicalSubject};
//! use lifegom_render::{camera::{Camera, Intrinsics}, gom::GomMesh, skeleton::BodyPose};
//! use lifegom_render::template::{BodyTemplate, lowres_template_path};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let device = Device::flex();
//! let body = BodyTemplate::load(lowres_template_path())?;
//! let k = Intrinsics { fx: 25.6, fy: 25.6, cx: 16.0, cy: 16.0 };
//! let camera = Camera::look_at(Vec3::new(0.0, 0.1, 2.5), Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k, 32, 32)?;
//! let rest = body.skeleton.skinning_transforms(&BodyPose::rest(body.num_joints()))?;
//! let sources = SourceViews {
//!     images: Tensor::random([1, 3, 32, 32], Distribution::Uniform(0.0, 1.0), &device), // your photo
//!     cameras: vec![camera],
//!     skinning: vec![rest],
//!     background: [1.0; 3],
//! };
//! let subject = CanonicalSubject {
//!     canonical_vertices: body.vertex_tensor(&device),
//!     lbs_weights: body.skin.tensor(&device),
//!     skeleton: body.skeleton.clone(),
//! };
//! let model = ReconstructorConfig::tiny(1).with_iterations(1).init(body.num_vertices(), &device)?;
//! let avatar = model.reconstruct(&subject, &GomMesh::new(&body.topology, 0, &device)?, &sources)?;
//! let image = avatar.render(&BodyPose::rest(body.num_joints()), &camera)?;
//! assert_eq!(image.rgb().dims(), [32, 32, 3]);
//! # Ok(()) }
//! ```
//!
//! | module | concept |
//! |---|---|
//! | [`encoder`] | ResNet-18 feature pyramid + 1×1 rgb embedding (1152 channels), torchvision/official weight import |
//! | [`fusion`] | multi-source fusion: self-attention over views, cross-attention with a per-vertex query |
//! | [`norm_folds`] | frozen BatchNorms and the layers they follow, folded once per reconstruction |
//! | [`point_transformer`] | the Point Transformer encoder–decoder (its farthest point sampling and kNN: `lifegom_ops::knn`) |
//! | [`heads`] | update heads: residual vertex update, new embedding, per-face Gaussian parameters |
//! | [`reconstructor`] | the reconstructor: T steps of render → encode → fuse → update |
//! | [`avatar`] | the result: render in any pose and view, save/load, 3DGS `.ply` export |
//! | [`rig_export`] | the avatar's rig for other tools: rigged `.glb`, the Gaussians' rig in the `.ply` |
//! | [`checkpoint`] | import of the official LIFe-GoM PyTorch checkpoint (key map: design.md §11) |
//! | [`inputs`] | a `lifegom-data` sample → subject, source views and target (skinning per design.md §4.4) |
//! | [`trained`] | our trained-model files: weights + config + payload, written atomically |
//! | [`weights_file`] | SafeTensors or PyTorch: a weights file's format from its first bytes |
//!
//! The fused ops the layers call (projection and sampling, attention, shared products, the
//! Point Transformer's neighbourhood ops, …) are `lifegom_ops`: each picks its CPU or CubeCL path
//! itself.
//!
//! Model code has no backend generic: modules take a `burn::tensor::Device` and run on ndarray,
//! Flex and wgpu (CubeCL kernels for the rasterizer and visibility), with `.autodiff()` for training. Without trained
//! weights every network is randomly initialised; binaries say so when they print results.

pub mod avatar;
pub mod checkpoint;
pub mod encoder;
pub mod error;
pub mod fusion;
pub mod heads;
pub mod inputs;
pub mod norm_folds;
pub mod point_transformer;
pub mod reconstructor;
pub mod rig_export;
#[cfg(test)]
mod test_grads;
pub mod trained;
pub mod weights_file;
