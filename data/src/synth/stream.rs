//! Subjects that never repeat: one fresh synthetic subject for every training sample
//! (design.md §8.9).
//!
//! A fixed split of a few dozen subjects lets a reconstructor memorise its people instead of
//! reading their photos. A [`SubjectStream`] instead generates subject `i` of an unbounded
//! sequence on demand (shape, outfit, pose, cameras: [`generate_subject_frames`]) and renders
//! only the views its sample needs: the frame rule's N inputs and one target, chosen from the
//! subject's full camera layout exactly as a training split on disk would choose them. Every
//! random choice is a function of `(seed, i)`, so a training step's sample is reproducible and
//! `--resume` continues the same sequence.
//!
//! The frames go through the same preprocessing as frames read from disk
//! ([`prepare_view`]): a stream sample equals the sample read back from the subject written
//! with [`super::write_subject`] (tested below).

use lifegom_render::rng::Rng;
use lifegom_render::template::BodyTemplate;

use super::{SynthConfig, SynthSetting, TargetCamera, generate_subject_frames};
use crate::dataset::{Background, DataConfig, FrameRule, Sample, Split, prepare_view};
use crate::error::{DataError, Location, Result};
use crate::format::CanonicalBody;
use crate::preprocess::{FloatImage, Resampling, ResizeMode};

/// Stream key of the subjects' seed (kept apart from the on-disk split's subjects).
const SUBJECT_SEED: u64 = 0x5752_4541_4d00_0001;
/// Fork key of a sample's frame and background choices (kept apart from the subject's own).
const SAMPLE_CHOICES: u64 = 1;

/// A generated sample with the canonical body its subject's `canonical_joints.pkl` would hold.
#[derive(Debug, Clone)]
pub struct StreamSample {
    /// The subject's canonical body (estimated shape, template skinning and faces).
    pub canonical: CanonicalBody,
    /// The N inputs and the target, preprocessed.
    pub sample: Sample,
}

/// An unbounded, deterministic sequence of synthetic training samples (module docs).
#[derive(Debug, Clone)]
pub struct SubjectStream {
    template: BodyTemplate,
    synth: SynthConfig,
    rule: FrameRule,
    img_size: (u32, u32),
    resize: ResizeMode,
    background: Background,
    /// `[synthetic] seed`.
    seed: u64,
}

impl SubjectStream {
    /// A stream of training samples under `data`'s frame rule, image size and training
    /// background, with subjects drawn as `synth` describes (its `seed` and the run's pick the
    /// sequence: [`SubjectStream::sample`]).
    pub fn new(synth: &SynthConfig, data: &DataConfig) -> Result<Self> {
        let path = synth.template.path();
        let template = BodyTemplate::load(&path)
            .map_err(|e| DataError::render(Location::file(&path).field("template"), e))?;
        Ok(Self::with_template(template, synth, data))
    }

    /// [`SubjectStream::new`] with an already loaded template.
    pub fn with_template(template: BodyTemplate, synth: &SynthConfig, data: &DataConfig) -> Self {
        Self {
            template,
            synth: synth.clone(),
            rule: FrameRule {
                protocol: data.protocol,
                split: Split::Train,
                n_inputs: data.n_input_frames,
            },
            img_size: (data.img_size[0], data.img_size[1]),
            resize: data.resize,
            background: data.train_background,
            seed: synth.seed,
        }
    }

    /// The template every subject is shaped from.
    pub fn template(&self) -> &BodyTemplate {
        &self.template
    }

    /// The template in its own rest shape as a canonical body: the topology and skinning every
    /// subject of the stream shares.
    pub fn template_body(&self) -> CanonicalBody {
        let t = &self.template;
        CanonicalBody {
            joints: t.skeleton.rest_joints.clone(),
            vertices: t.vertices.clone(),
            weights: t.skin.to_dense(),
            faces: t.topology.faces.clone(),
            parents: t
                .skeleton
                .parents
                .iter()
                .map(|p| p.map_or(-1, |p| p as i32))
                .collect(),
        }
    }

    /// Name of subject `index` (`p` + nine digits: never a name of an on-disk split).
    pub fn subject_name(index: u64) -> String {
        format!("p{index:09}")
    }

    /// Frames per subject: the training ring and its targets, or the training sequence.
    fn num_frames(&self) -> usize {
        self.synth.train_frames()
    }

    /// Whether a sample takes its target from another camera than its sources' (multi-frame
    /// with [`TargetCamera::Others`]): then it is drawn in the validation layout.
    fn targets_other_cameras(&self) -> bool {
        self.synth.setting == SynthSetting::MultiFrame
            && self.synth.stream_target_camera == TargetCamera::Others
    }

    /// The generator seed of the subjects of run seed `seed`.
    fn subject_seed(&self, seed: u64) -> u64 {
        Rng::new(self.seed).fork(SUBJECT_SEED).fork(seed).next_u64()
    }

    /// Sample `index` of the sequence of run seed `seed`: subject `index`, its inputs and
    /// target picked by the frame rule, composited on the training background.
    pub fn sample(&self, seed: u64, index: u64) -> Result<StreamSample> {
        let _span = tracing::debug_span!("generate_subject", index).entered();
        let name = Self::subject_name(index);
        let subject_seed = self.subject_seed(seed);
        let mut rng = Rng::new(subject_seed).fork(index).fork(SAMPLE_CHOICES);
        let (inputs, target, layout) = if self.targets_other_cameras() {
            // The validation layout: N inputs from the sources' camera, then the targets.
            let n = self.rule.n_inputs;
            let target = n + rng.below(self.synth.val_target_views.max(1));
            ((0..n).collect::<Vec<_>>(), target, Some(n))
        } else {
            let num_frames = self.num_frames();
            let s = rng.below(self.rule.samples_per_subject(num_frames).max(1));
            let (inputs, target) = self.rule.frames(s, num_frames, &mut rng);
            (inputs, target, None)
        };
        let bg = self.background.draw(&mut rng);
        let wanted: Vec<usize> = inputs.iter().copied().chain([target]).collect();
        let subject = generate_subject_frames(
            &self.template,
            &self.synth,
            subject_seed,
            index as usize,
            &name,
            layout,
            Some(&wanted),
        )?;
        let views = wanted
            .iter()
            .map(|&f| {
                let frame_name = format!("frame_{f:06}");
                let frame = subject
                    .frames
                    .iter()
                    .find(|r| r.name == frame_name)
                    .ok_or_else(|| {
                        DataError::invalid(
                            Location::default().subject(&name).frame(&frame_name),
                            "the generator did not render a frame the rule picked",
                        )
                    })?;
                let (w, h) = (frame.camera.width, frame.camera.height);
                Ok(prepare_view(
                    &frame.name,
                    FloatImage::from_rgb8(w, h, &frame.rgb),
                    FloatImage::mask_from_l8(w, h, &frame.mask),
                    &frame.frame_camera(),
                    &subject.mesh_info(frame),
                    bg,
                    Resampling {
                        size: self.img_size,
                        mode: self.resize,
                    },
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        let canonical = subject.canonical_body(&self.template);
        Ok(StreamSample {
            sample: Sample {
                frame_name: format!("scene_{name}_frame_{target:06}"),
                subject: name,
                views,
                bgcolor: bg.map(|c| c / 255.0),
                canonical_vertices: canonical.vertices.iter().map(|v| v.to_array()).collect(),
            },
            canonical,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::Protocol;
    use crate::format::Subject;
    use crate::kinematics::KinematicTree;
    use crate::synth::{
        Shading, ShapeEstimate, SynthSetting, TemplateChoice, generate_subject, write_subject,
    };

    fn configs(size: u32) -> (SynthConfig, DataConfig) {
        let synth = SynthConfig {
            setting: SynthSetting::MultiView,
            sequence_frames: 30,
            max_turn_deg: 180.0,
            template: TemplateChoice::Lowres,
            train_subjects: 1,
            val_subjects: 0,
            image_size: size,
            source_views: 16,
            target_views: 48,
            val_target_views: 3,
            camera_radius: 2.0,
            camera_radius_range: None,
            stream_variety: None,
            stream_target_camera: TargetCamera::Sources,
            camera_pitch_deg: -8.0,
            focal_factor: 0.8,
            shape_estimate: ShapeEstimate::Noisy,
            shape_noise: 0.2,
            shading: Shading::Albedo,
            supersample: 1,
            held_out_subjects: 0,
            held_out_scale: 4,
            seed: 0,
        };
        let data = DataConfig {
            root: "unused".into(),
            protocol: Protocol::ThumanView3,
            kinematic_tree: KinematicTree::Stored,
            train_dir: "train".into(),
            train_split: "train.json".into(),
            val_dir: "val".into(),
            val_split: "val.json".into(),
            val_subjects: None,
            img_size: [size / 2, size / 2],
            n_input_frames: 3,
            train_background: Background::Random,
            test_background: Background::Fixed([0, 0, 0]),
            resize: ResizeMode::default(),
            held_out_dir: None,
            held_out_split: None,
        };
        (synth, data)
    }

    /// Every view of `sample` equals the same frame of `subject` read from disk over `bg` at
    /// `size`: a stream sample is the written subject read back.
    fn assert_views_read_back(subject: &Subject, sample: &Sample, bg: [f32; 3], size: (u32, u32)) {
        for view in &sample.views {
            let f = subject
                .frames
                .iter()
                .position(|n| *n == view.frame)
                .unwrap();
            let read =
                crate::dataset::load_view(subject, f, bg, size, ResizeMode::default()).unwrap();
            assert_eq!(&read, view, "frame {}", view.frame);
        }
    }

    /// A stream sample is exactly what the reader gives for the same subject written to disk:
    /// same views (pixels, masks, cameras, poses), canonical body and background.
    #[test]
    fn stream_sample_equals_the_written_subject_read_back() {
        let (synth, data) = configs(48);
        let stream = SubjectStream::new(&synth, &data).unwrap();
        let got = stream.sample(7, 3).unwrap();
        let dir = std::env::temp_dir().join(format!("lifegom-stream-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let name = SubjectStream::subject_name(3);
        let seed = stream.subject_seed(7);
        let full = generate_subject(stream.template(), &synth, seed, 3, &name, None).unwrap();
        write_subject(stream.template(), &full, &dir).unwrap();
        let subject = Subject::load(&dir.join(&name), KinematicTree::Stored).unwrap();
        assert_eq!(subject.canonical, got.canonical);
        assert_eq!(got.sample.views.len(), 4);
        let bg = got.sample.bgcolor.map(|c| c * 255.0);
        assert_views_read_back(&subject, &got.sample, bg, (24, 24));
        let _ = std::fs::remove_dir_all(&dir);
        // Inputs follow the THuman view3 training rule: ring frames 5 or 6 apart; the target is
        // one of the 48 in-gap views.
        let idx: Vec<usize> = got
            .sample
            .views
            .iter()
            .map(|v| v.frame["frame_".len()..].parse().unwrap())
            .collect();
        for pair in idx[..3].windows(2) {
            assert!(matches!((pair[1] + 16 - pair[0]) % 16, 5 | 6), "{idx:?}");
        }
        assert!((16..64).contains(&idx[3]), "{idx:?}");
    }

    /// The multi-frame setting streams too: a sample is N frames of one person's sequence and
    /// another frame as the target, equal to the written subject read back.
    #[test]
    fn multi_frame_stream_samples_equal_the_written_sequence() {
        let (mut synth, mut data) = configs(32);
        synth.setting = SynthSetting::MultiFrame;
        synth.sequence_frames = 9;
        data.protocol = Protocol::Aistpp;
        data.n_input_frames = 5;
        data.train_background = Background::Fixed([255, 255, 255]);
        let stream = SubjectStream::new(&synth, &data).unwrap();
        let got = stream.sample(3, 2).unwrap();
        assert_eq!(got.sample.views.len(), 6);
        assert_eq!(got.sample.bgcolor, [1.0; 3]);
        let dir = std::env::temp_dir().join(format!("lifegom-stream-mf-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let name = SubjectStream::subject_name(2);
        let seed = stream.subject_seed(3);
        let full = generate_subject(stream.template(), &synth, seed, 2, &name, None).unwrap();
        assert_eq!(full.frames.len(), 9);
        write_subject(stream.template(), &full, &dir).unwrap();
        let subject = Subject::load(&dir.join(&name), KinematicTree::Stored).unwrap();
        assert_views_read_back(&subject, &got.sample, [255.0; 3], (16, 16));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// With `stream_target_camera = "others"` a multi-frame sample is the validation layout:
    /// the N evenly spaced inputs from the sources' camera, and a target seen from one of the
    /// other cameras, equal to the subject written in that layout and read back.
    #[test]
    fn multi_frame_targets_from_other_cameras_are_the_validation_layout() {
        let (mut synth, mut data) = configs(32);
        synth.setting = SynthSetting::MultiFrame;
        synth.sequence_frames = 9;
        synth.val_target_views = 6;
        synth.stream_target_camera = TargetCamera::Others;
        data.protocol = Protocol::Aistpp;
        data.n_input_frames = 5;
        data.train_background = Background::Fixed([255, 255, 255]);
        let stream = SubjectStream::new(&synth, &data).unwrap();
        let name = SubjectStream::subject_name(4);
        let seed = stream.subject_seed(5);
        let full = generate_subject(stream.template(), &synth, seed, 4, &name, Some(5)).unwrap();
        assert_eq!(full.frames.len(), 11);
        let dir = std::env::temp_dir().join(format!("lifegom-stream-oc-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        write_subject(stream.template(), &full, &dir).unwrap();
        let subject = Subject::load(&dir.join(&name), KinematicTree::Stored).unwrap();
        let mut targets = std::collections::BTreeSet::new();
        for draw in 0..2 {
            // The same index and seed: the same person, inputs and target.
            let got = stream.sample(5, 4).unwrap();
            assert_eq!(got.sample.views.len(), 6, "draw {draw}");
            let idx: Vec<usize> = got
                .sample
                .views
                .iter()
                .map(|v| v.frame["frame_".len()..].parse().unwrap())
                .collect();
            assert_eq!(idx[..5], [0, 1, 2, 3, 4], "the validation layout's inputs");
            assert!((5..11).contains(&idx[5]), "a target of the layout: {idx:?}");
            targets.insert(idx[5]);
            assert_views_read_back(&subject, &got.sample, [255.0; 3], (16, 16));
        }
        // The inputs share one camera; every target of the layout has another.
        let centre = |f: usize| full.frames[f].camera.center();
        for f in 1..5 {
            assert!((centre(f) - centre(0)).length() < 1e-4, "input {f}");
        }
        for &t in &targets {
            assert!((centre(t) - centre(0)).length() > 0.5, "target {t}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Same index, same sample; another index or seed, another person.
    #[test]
    fn samples_are_deterministic_and_distinct() {
        let (synth, data) = configs(32);
        let stream = SubjectStream::new(&synth, &data).unwrap();
        let s0 = stream.sample(1, 0).unwrap();
        assert_eq!(s0.sample, stream.sample(1, 0).unwrap().sample);
        let next = stream.sample(1, 1).unwrap();
        assert_ne!(s0.canonical.vertices, next.canonical.vertices);
        let other_run = stream.sample(2, 0).unwrap();
        assert_ne!(s0.canonical.vertices, other_run.canonical.vertices);
        let sum = |s: &StreamSample| s.sample.views[0].rgb.iter().sum::<f32>();
        assert_ne!(sum(&s0), sum(&next));
    }
}
