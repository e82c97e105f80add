//! From a dataset sample to the reconstructor's inputs (design.md §8.6 → §2).
//!
//! `lifegom-data` yields host-side [`Sample`]s: N source views and one target, each with its
//! image, mask, `K`, `E'` (body transform already folded in), axis-angle pose and the frame's
//! zero-pose joints. The reconstructor takes tensors: a [`CanonicalSubject`] (canonical low-res body with
//! skinning weights and skeleton) and [`SourceViews`]. This module is that one-way bridge.
//!
//! Skinning follows the reference (`body_pose_to_body_RTs` + `get_global_RTs`; design.md §4.4): the
//! posed global transforms `G_i` are built from the *frame's* zero-pose joints, the canonical
//! ones from the subject's `canonical_joints`, and `M_i = G_i · Trans(−J_i^cnl)`. Our
//! [`Skeleton::skinning_transforms`] gives `G_i · Trans(−J_i^frame)`, so the bridge appends
//! `Trans(J_i^frame − J_i^cnl)`, which is the identity when the two joint sets agree.

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Affine3A, Vec3};
use lifegom_data::dataset::{Dataset, Sample, View};
use lifegom_data::format::CanonicalBody;
use lifegom_data::kinematics::parents_as_options;
use lifegom_render::camera::Camera;
use lifegom_render::mesh::MeshTopology;
use lifegom_render::skeleton::{BodyPose, Skeleton};

use crate::error::{ModelError, Result};
use crate::reconstructor::{CanonicalSubject, SourceViews};

/// A subject's body as the model sees it, built once per subject from `canonical_joints.pkl`.
#[derive(Debug, Clone)]
pub struct SubjectRig {
    /// Subject name (for messages).
    pub name: String,
    /// Low-res topology (the template's faces).
    pub topology: MeshTopology,
    /// Canonical skeleton (joint heads of the subject's T-pose).
    pub skeleton: Skeleton,
    /// Dense skinning weights, row-major `V↓ × J`.
    pub weights: Vec<f32>,
    /// Canonical vertices, `V↓`.
    pub vertices: Vec<Vec3>,
}

fn invalid(what: &'static str, reason: String) -> ModelError {
    ModelError::InvalidInput { what, reason }
}

impl SubjectRig {
    /// Validates the canonical body and builds the skeleton (joints named `joint_<i>`).
    pub fn new(name: &str, canonical: &CanonicalBody) -> Result<Self> {
        let v = canonical.vertices.len();
        let j = canonical.joints.len();
        if canonical.weights.len() != v * j {
            return Err(invalid(
                "canonical weights",
                format!(
                    "subject {name}: {} weights for {v} vertices × {j} joints",
                    canonical.weights.len()
                ),
            ));
        }
        let parents = parents_as_options(&canonical.parents)
            .map_err(|e| invalid("canonical parents", format!("subject {name}: {e}")))?;
        let names = (0..j).map(|i| format!("joint_{i}")).collect();
        let skeleton = Skeleton::new(names, parents, canonical.joints.clone())?;
        Ok(Self {
            name: name.to_string(),
            topology: MeshTopology::new(canonical.faces.clone(), v)?,
            skeleton,
            weights: canonical.weights.clone(),
            vertices: canonical.vertices.clone(),
        })
    }

    /// The rigs of every subject of a split, checked to share one low-res topology (one
    /// model serves one template).
    pub fn for_split(dataset: &Dataset) -> Result<Vec<Self>> {
        let rigs = dataset
            .subjects
            .iter()
            .map(|s| Self::new(&s.name, &s.canonical))
            .collect::<Result<Vec<_>>>()?;
        let Some(first) = rigs.first() else {
            return Err(invalid("split", "the split has no subjects".into()));
        };
        for r in &rigs {
            if r.topology.faces != first.topology.faces || r.num_vertices() != first.num_vertices()
            {
                return Err(invalid(
                    "canonical vertices",
                    format!(
                        "subject {} has another low-res topology than {} ({} vs {} vertices): one model serves one template",
                        r.name,
                        first.name,
                        r.num_vertices(),
                        first.num_vertices()
                    ),
                ));
            }
        }
        Ok(rigs)
    }

    /// Number of low-res vertices.
    pub fn num_vertices(&self) -> usize {
        self.vertices.len()
    }

    /// The subject as tensors on `device`, with `canonical_vertices` as given by the sample
    /// (they equal [`Self::vertices`] for the reference datasets).
    pub fn subject(
        &self,
        canonical_vertices: &[[f32; 3]],
        device: &Device,
    ) -> Result<CanonicalSubject> {
        if canonical_vertices.len() != self.num_vertices() {
            return Err(invalid(
                "canonical_vertices",
                format!(
                    "subject {}: sample has {} vertices, the body {}",
                    self.name,
                    canonical_vertices.len(),
                    self.num_vertices()
                ),
            ));
        }
        let flat: Vec<f32> = canonical_vertices.iter().flatten().copied().collect();
        let j = self.skeleton.num_joints();
        Ok(CanonicalSubject {
            canonical_vertices: Tensor::from_data(
                TensorData::new(flat, [self.num_vertices(), 3]),
                device,
            ),
            lbs_weights: Tensor::from_data(
                TensorData::new(self.weights.clone(), [self.num_vertices(), j]),
                device,
            ),
            skeleton: self.skeleton.clone(),
        })
    }

    /// Canonical-to-posed transforms of a view (module docs), one per joint.
    pub fn skinning(&self, view: &View) -> Result<Vec<Affine3A>> {
        let j = self.skeleton.num_joints();
        if view.tpose_joints.len() != j {
            return Err(invalid(
                "tpose_joints",
                format!(
                    "subject {} frame {}: {} joints, the skeleton has {j}",
                    self.name,
                    view.frame,
                    view.tpose_joints.len()
                ),
            ));
        }
        let pose = BodyPose::from_flat(&view.poses).map_err(|e| {
            invalid(
                "poses",
                format!("subject {} frame {}: {e}", self.name, view.frame),
            )
        })?;
        let frame_joints: Vec<Vec3> = view.tpose_joints.iter().map(|p| Vec3::from(*p)).collect();
        let frame_skeleton = self.skeleton.with_rest_joints(frame_joints.clone())?;
        let posed = frame_skeleton.skinning_transforms(&pose).map_err(|e| {
            invalid(
                "poses",
                format!("subject {} frame {}: {e}", self.name, view.frame),
            )
        })?;
        Ok(posed
            .into_iter()
            .zip(frame_joints.iter().zip(&self.skeleton.rest_joints))
            .map(|(m, (frame, cnl))| m * Affine3A::from_translation(*frame - *cnl))
            .collect())
    }

    /// The camera of a view at the sample's image size.
    pub fn camera(&self, view: &View, width: u32, height: u32) -> Result<Camera> {
        Camera::from_matrices(view.k, view.e, width, height).map_err(|e| {
            invalid(
                "camera",
                format!("subject {} frame {}: {e}", self.name, view.frame),
            )
        })
    }
}

/// A sample as model inputs: the subject, the N sources, and the target view (for supervision
/// and evaluation).
#[derive(Debug, Clone)]
pub struct ModelInputs {
    /// The subject's canonical body.
    pub subject: CanonicalSubject,
    /// The N source views.
    pub sources: SourceViews,
    /// Target camera.
    pub target_camera: Camera,
    /// Target skinning transforms.
    pub target_skinning: Vec<Affine3A>,
    /// Target image, `[3, H, W]`, composited over the sample background.
    pub target_rgb: Tensor<3>,
    /// Target mask, `[1, H, W]`.
    pub target_mask: Tensor<3>,
    /// Source masks, `[N, 1, H, W]`.
    pub source_masks: Tensor<4>,
}

/// Image `[H·W·3]` (HWC) to a `[3, H, W]` tensor.
fn chw(rgb: &[f32], h: usize, w: usize, device: &Device) -> Tensor<3> {
    Tensor::<3>::from_data(TensorData::new(rgb.to_vec(), [h, w, 3]), device).permute([2, 0, 1])
}

/// Converts a sample (N sources + target) for `body`, at image size `width × height`.
pub fn model_inputs(
    body: &SubjectRig,
    sample: &Sample,
    width: u32,
    height: u32,
    device: &Device,
) -> Result<ModelInputs> {
    let (h, w) = (height as usize, width as usize);
    let Some((target, sources)) = sample.views.split_last() else {
        return Err(invalid(
            "sample",
            format!("{}: no views", sample.frame_name),
        ));
    };
    for view in &sample.views {
        if view.rgb.len() != h * w * 3 || view.mask.len() != h * w {
            return Err(invalid(
                "sample",
                format!(
                    "{} frame {}: image has {} values and mask {}, expected {}x{}",
                    sample.frame_name,
                    view.frame,
                    view.rgb.len(),
                    view.mask.len(),
                    w,
                    h
                ),
            ));
        }
    }
    let images = Tensor::stack(
        sources.iter().map(|v| chw(&v.rgb, h, w, device)).collect(),
        0,
    );
    let masks = Tensor::stack(
        sources
            .iter()
            .map(|v| Tensor::<3>::from_data(TensorData::new(v.mask.clone(), [1, h, w]), device))
            .collect(),
        0,
    );
    Ok(ModelInputs {
        subject: body.subject(&sample.canonical_vertices, device)?,
        sources: SourceViews {
            images,
            cameras: sources
                .iter()
                .map(|v| body.camera(v, width, height))
                .collect::<Result<_>>()?,
            skinning: sources
                .iter()
                .map(|v| body.skinning(v))
                .collect::<Result<_>>()?,
            background: sample.bgcolor,
        },
        target_camera: body.camera(target, width, height)?,
        target_skinning: body.skinning(target)?,
        target_rgb: chw(&target.rgb, h, w, device),
        target_mask: Tensor::from_data(TensorData::new(target.mask.clone(), [1, h, w]), device),
        source_masks: masks,
    })
}
