//! Generator → reader round trip on `configs/synthetic-tiny.toml`, plus the bad-data errors:
//! every corruption gives one error naming subject, frame and field, never a panic.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use glam::Vec3;
use lifegom_data::config::ConfigFile;
use lifegom_data::custom;
use lifegom_data::dataset::{Background, Dataset, Split};
use lifegom_data::format::Subject;
use lifegom_data::kinematics::KinematicTree;
use lifegom_data::pickle::{self, Value};
use lifegom_data::synth;
use lifegom_render::rng::Rng;

fn tiny_config() -> ConfigFile {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml");
    ConfigFile::load(&path).unwrap()
}

/// The tiny split, generated once per test binary.
fn tiny_split() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("lifegom-synth-tiny-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cfg = tiny_config();
        let s = cfg.synthetic.clone().unwrap();
        synth::generate_split(&s, &cfg.data, &dir, s.seed, &|| {}).unwrap();
        dir
    })
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let dst = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &dst);
        } else {
            std::fs::copy(&p, &dst).unwrap();
        }
    }
}

/// A private copy of training subject 0000, for corrupting.
fn scratch_subject(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lifegom-bad-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    copy_dir(&tiny_split().join("view3_train/0000"), &dir.join("0000"));
    dir.join("0000")
}

#[test]
fn generated_split_reads_back_with_the_official_rules() {
    let root = tiny_split();
    let cfg = tiny_config().with_root(root);
    let train = Dataset::open(&cfg.data, Split::Train).unwrap();
    assert_eq!(train.subjects.len(), 2);
    assert_eq!(train.len(), 2 * 48);
    let s = &train.subjects[0];
    assert_eq!(s.frames.len(), 64);
    assert_eq!(s.frames[0], "frame_000000");
    let j = s.canonical.num_joints();
    assert_eq!(j, 104);
    assert_eq!(s.mesh_infos[0].poses.len(), 3 * j);
    assert_eq!(s.canonical.weights.len(), s.canonical.vertices.len() * j);

    let mut rng = Rng::new(1);
    let sample = train.sample(50, &mut rng).unwrap();
    assert_eq!(sample.views.len(), 4);
    assert_eq!(sample.subject, "0001");
    assert_eq!(sample.frame_name, "scene_0001_frame_000018");
    let [w, h] = cfg.data.img_size;
    for v in &sample.views {
        assert_eq!(v.rgb.len(), (w * h * 3) as usize);
        assert_eq!(v.mask.len(), (w * h) as usize);
    }
    // Random background: the corner pixel of the target is the background colour.
    let t = sample.views.last().unwrap();
    for c in 0..3 {
        assert!((t.rgb[c] - sample.bgcolor[c]).abs() < 2.0 / 255.0);
    }
    assert_eq!(train.background, Background::Random);

    // Cameras see the body: the posed canonical joints project inside the mask.
    let subj = &train.subjects[0];
    let cam = &subj.cameras[20];
    let e = lifegom_data::dataset::fold_body_transform(
        &cam.e,
        subj.mesh_infos[20].rh,
        subj.mesh_infos[20].th,
    );
    let pelvis = subj.canonical.joints[0];
    let p = [pelvis.x, pelvis.y, pelvis.z, 1.0];
    let c: Vec<f32> = (0..3)
        .map(|i| (0..4).map(|k| e[i][k] * p[k]).sum())
        .collect();
    assert!((c[2] - 2.0).abs() < 0.4, "pelvis depth {}", c[2]);
    let k = cam.k;
    let (u, v) = (
        k[0][0] as f32 * c[0] / c[2] + k[0][2] as f32,
        k[1][1] as f32 * c[1] / c[2] + k[1][2] as f32,
    );
    let view =
        lifegom_data::dataset::load_view(subj, 20, [0.0; 3], (64, 64), Default::default()).unwrap();
    let mask_at = view.mask[(v as usize).min(63) * 64 + (u as usize).min(63)];
    assert!(
        mask_at > 0.5,
        "pelvis projects at ({u}, {v}) outside the mask"
    );

    let val = Dataset::open(&cfg.data, Split::Val).unwrap();
    assert_eq!((val.subjects.len(), val.len()), (1, 3));
    let mut rng = Rng::new(0);
    let idx = val.index(2, &mut rng).unwrap();
    assert_eq!((idx.inputs, idx.target), (vec![0, 1, 2], 5));
    let vs = val.sample(0, &mut rng).unwrap();
    assert_eq!(vs.bgcolor, [0.0; 3]);
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("view3_val_meta.json")).unwrap())
            .unwrap();
    assert_eq!(meta[0]["input_frames"], serde_json::json!([0, 1, 2]));
    assert_eq!(meta[0]["output_frame"], 3);
}

#[test]
fn canonical_body_is_the_estimated_template_not_the_clothed_surface() {
    let s = Subject::load(
        &tiny_split().join("view3_train/0000"),
        KinematicTree::Stored,
    )
    .unwrap();
    let template = lifegom_render::template::BodyTemplate::load(
        lifegom_render::template::lowres_template_path(),
    )
    .unwrap();
    assert_eq!(s.canonical.vertices.len(), template.num_vertices());
    assert_eq!(s.canonical.faces, template.topology.faces);
    // The estimated shape is the template in some PCA shape: its offset from the neutral body
    // lies in the span of the basis (least squares leaves ~no residual).
    let basis = &template.shape_basis;
    let d: Vec<Vec3> = s
        .canonical
        .vertices
        .iter()
        .zip(&template.vertices)
        .map(|(a, b)| *a - *b)
        .collect();
    let coeffs: Vec<f32> = basis
        .vertex_deltas
        .iter()
        .map(|b| {
            let num: f32 = b.iter().zip(&d).map(|(x, y)| x.dot(*y)).sum();
            let den: f32 = b.iter().map(|x| x.length_squared()).sum();
            num / den
        })
        .collect();
    let (fit, _) = template.shaped(&coeffs).unwrap();
    let err = fit
        .iter()
        .zip(&s.canonical.vertices)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0f32, f32::max);
    assert!(
        err < 0.02,
        "canonical vertices are not a template shape (max residual {err} m)"
    );
    assert_eq!(s.canonical.parents.len(), 104);
    assert_eq!(s.mesh_infos[0].tpose_joints, s.canonical.joints);
}

#[test]
fn generation_is_deterministic_per_seed() {
    let cfg = tiny_config();
    let s = cfg.synthetic.clone().unwrap();
    let template = lifegom_render::template::BodyTemplate::load(s.template.path()).unwrap();
    let a = synth::generate_subject(&template, &s, 7, 1, "x", Some(3)).unwrap();
    let b = synth::generate_subject(&template, &s, 7, 1, "x", Some(3)).unwrap();
    let c = synth::generate_subject(&template, &s, 8, 1, "x", Some(3)).unwrap();
    assert_eq!(a.frames.len(), 6);
    assert!(
        a.frames
            .iter()
            .zip(&b.frames)
            .all(|(x, y)| x.rgb == y.rgb && x.mask == y.mask)
    );
    assert!(
        a.frames
            .iter()
            .zip(&b.frames)
            .all(|(x, y)| x.body == y.body)
    );
    // A multi-view subject is static: one body for every frame.
    assert!(a.frames.iter().all(|f| f.body == a.frames[0].body));
    assert_ne!(a.frames[0].rgb, c.frames[0].rgb);
    // Masks come from coverage: every lit pixel is inside the mask, and the body is in view.
    for f in &a.frames {
        let covered = f.mask.iter().filter(|&&m| m == 255).count();
        assert!(covered > 100, "{covered} pixels");
        for (p, &m) in f.mask.iter().enumerate() {
            if m == 0 {
                assert_eq!(&f.rgb[3 * p..3 * p + 3], &[0, 0, 0]);
            }
        }
        // Not cut by the border: the outer ring of pixels is empty.
        let w = 64;
        for i in 0..w {
            assert_eq!(f.mask[i], 0, "top row");
            assert_eq!(f.mask[(w - 1) * w + i], 0, "bottom row");
        }
    }
}

fn edit_pickle(path: &Path, edit: impl FnOnce(&mut Value)) {
    let mut v = pickle::load(path).unwrap();
    edit(&mut v);
    pickle::save(path, &v).unwrap();
}

fn set_field(v: &mut Value, frame: Option<&str>, key: &str, new: Value) {
    let dict = match frame {
        Some(f) => match v {
            Value::Dict(items) => {
                &mut items
                    .iter_mut()
                    .find(|(k, _)| k.as_str() == Some(f))
                    .unwrap()
                    .1
            }
            _ => unreachable!(),
        },
        None => v,
    };
    if let Value::Dict(items) = dict {
        match items.iter_mut().find(|(k, _)| k.as_str() == Some(key)) {
            Some(slot) => slot.1 = new,
            None => items.push((Value::Str(key.into()), new)),
        }
    }
}

fn assert_error(dir: &Path, parts: &[&str]) {
    let msg = Subject::load(dir, KinematicTree::Stored)
        .and_then(|s| {
            (0..s.frames.len()).try_for_each(|f| {
                lifegom_data::dataset::load_view(&s, f, [0.0; 3], (32, 32), Default::default())
                    .map(|_| ())
            })
        })
        .unwrap_err()
        .to_string();
    for p in parts {
        assert!(msg.contains(p), "`{msg}` lacks `{p}`");
    }
}

#[test]
fn bad_data_errors_name_subject_frame_and_field() {
    let f3 = Some("frame_000003");
    let arr = |shape: Vec<usize>, v: Vec<f64>| {
        Value::Array(lifegom_data::pickle::NdArray::from_f64(shape, v).unwrap())
    };

    // NaN in a camera.
    let d = scratch_subject("nan");
    edit_pickle(&d.join("cameras.pkl"), |v| {
        let mut e = vec![0.0; 16];
        e[0] = f64::NAN;
        set_field(v, f3, "extrinsics", arr(vec![4, 4], e));
    });
    assert_error(
        &d,
        &[
            "subject `0000`",
            "frame `frame_000003`",
            "field `extrinsics`",
            "non-finite",
        ],
    );

    // Non-invertible extrinsics.
    let d = scratch_subject("singular");
    edit_pickle(&d.join("cameras.pkl"), |v| {
        let mut e = vec![0.0; 16];
        e[15] = 1.0;
        set_field(v, f3, "extrinsics", arr(vec![4, 4], e));
    });
    assert_error(
        &d,
        &["frame `frame_000003`", "extrinsics", "not invertible"],
    );

    // Inf in a pose, and a wrong joint count.
    let d = scratch_subject("pose");
    edit_pickle(&d.join("mesh_infos.pkl"), |v| {
        set_field(v, f3, "Th", arr(vec![3], vec![0.0, f64::INFINITY, 0.0]));
    });
    assert_error(&d, &["frame `frame_000003`", "field `Th`", "non-finite"]);
    let d = scratch_subject("joints");
    edit_pickle(&d.join("mesh_infos.pkl"), |v| {
        set_field(v, f3, "poses", arr(vec![72], vec![0.0; 72]));
    });
    assert_error(&d, &["frame `frame_000003`", "field `poses`", "104 joints"]);

    // Missing file, unreadable PNG, image/mask size mismatch.
    let d = scratch_subject("missing");
    std::fs::remove_file(d.join("masks/frame_000007.png")).unwrap();
    assert_error(
        &d,
        &[
            "subject `0000`",
            "frame `frame_000007`",
            "masks",
            "cannot read",
        ],
    );
    let d = scratch_subject("png");
    std::fs::write(d.join("images/frame_000002.png"), b"not a png").unwrap();
    assert_error(&d, &["frame `frame_000002`", "unreadable PNG"]);
    let d = scratch_subject("size");
    image::save_buffer(
        d.join("masks/frame_000005.png"),
        &[0u8; 16 * 8],
        16,
        8,
        image::ExtendedColorType::L8,
    )
    .unwrap();
    assert_error(
        &d,
        &["frame `frame_000005`", "size mismatch", "64×64", "16×8"],
    );

    // A uniform mask: empty, written 0/1 instead of 0/255, or with no background (inverted, or
    // a white image saved as the mask).
    let uniform_mask = |name: &str, value: u8| {
        let d = scratch_subject(name);
        image::save_buffer(
            d.join("masks/frame_000004.png"),
            &[value; 64 * 64],
            64,
            64,
            image::ExtendedColorType::L8,
        )
        .unwrap();
        d
    };
    let frame = ["subject `0000`", "frame `frame_000004`", "masks"];
    for (name, value) in [("empty", 0u8), ("binary", 1u8)] {
        let largest = format!("largest value is {value} of 255");
        let parts = [&frame[..], &["shows no person", &largest]].concat();
        assert_error(&uniform_mask(name, value), &parts);
    }
    let full = ["covers the whole image (100.0 % of its pixels)", "inverted"];
    assert_error(
        &uniform_mask("fullcover", 255),
        &[&frame[..], &full].concat(),
    );

    // A frame without a camera, and a missing pickle.
    let d = scratch_subject("nocam");
    edit_pickle(&d.join("cameras.pkl"), |v| {
        if let Value::Dict(items) = v {
            items.retain(|(k, _)| k.as_str() != Some("frame_000009"));
        }
    });
    assert_error(&d, &["frame `frame_000009`", "cameras.pkl", "no entry"]);
    let d = scratch_subject("nopkl");
    std::fs::remove_file(d.join("canonical_joints.pkl")).unwrap();
    assert_error(&d, &["subject `0000`", "canonical_joints.pkl"]);

    // Wrong joint count for the kinematic tree of the config (SMPL-X on Anny data).
    let d = scratch_subject("tree");
    let msg = Subject::load(&d, KinematicTree::Smplx)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("wrong joint count") && msg.contains("104") && msg.contains("55"),
        "{msg}"
    );
}

#[test]
fn anny_data_from_other_tools_reads_with_the_templates_tree() {
    // Another tool's Anny data: the official layout without our extra `parents` entry.
    let d = scratch_subject("no-parents");
    let stored = Subject::load(&d, KinematicTree::Stored).unwrap();
    edit_pickle(&d.join("canonical_joints.pkl"), |v| {
        if let Value::Dict(items) = v {
            items.retain(|(k, _)| k.as_str() != Some("parents"));
        }
    });
    let msg = Subject::load(&d, KinematicTree::Stored)
        .unwrap_err()
        .to_string();
    for part in [
        "canonical_joints.pkl",
        "field `parents`",
        "missing",
        "\"anny\"",
    ] {
        assert!(msg.contains(part), "`{msg}` lacks `{part}`");
    }
    let anny = Subject::load(&d, KinematicTree::Anny).unwrap();
    assert_eq!(anny.canonical.parents, stored.canonical.parents);

    // A rig that is not Anny's is refused by the anny tree, naming the choice.
    let msg = Subject::load(&d, KinematicTree::Smpl)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("kinematic_tree = \"smpl\" has 24"), "{msg}");
}

fn json_subject(tag: &str) -> PathBuf {
    let src = Subject::load(
        &tiny_split().join("view3_train/0000"),
        KinematicTree::Stored,
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("lifegom-json-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    custom::write_subject(&src, synth::TemplateChoice::Lowres, &dir.join("me")).unwrap()
}

fn edit_json(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(path, serde_json::to_string(&v).unwrap()).unwrap();
}

#[test]
fn json_layout_reads_back_the_official_subject() {
    let official = Subject::load(
        &tiny_split().join("view3_train/0000"),
        KinematicTree::Stored,
    )
    .unwrap();
    let path = json_subject("round-trip");
    let json = custom::load_subject(&path).unwrap();
    assert_eq!(json.frames, official.frames);
    // serde_json parses decimals to within one ulp, not always to the written f64.
    for (a, b) in json.cameras.iter().zip(&official.cameras) {
        let close = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(p, q)| (p - q).abs() <= 1e-12);
        assert!(close(a.k.as_flattened(), b.k.as_flattened()), "{a:?} {b:?}");
        assert!(close(a.e.as_flattened(), b.e.as_flattened()), "{a:?} {b:?}");
        assert_eq!(a.distortion, b.distortion);
    }
    assert_eq!(json.canonical.faces, official.canonical.faces);
    assert_eq!(json.canonical.parents, official.canonical.parents);
    assert_eq!(json.canonical.weights, official.canonical.weights);
    // The body is rebuilt from fitted shape coefficients: equal to float rounding.
    let worst = |a: &[Vec3], b: &[Vec3]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (*x - *y).length())
            .fold(0.0f32, f32::max)
    };
    assert!(worst(&json.canonical.vertices, &official.canonical.vertices) < 1e-5);
    assert!(worst(&json.canonical.joints, &official.canonical.joints) < 1e-5);
    for (a, b) in json.mesh_infos.iter().zip(&official.mesh_infos) {
        // f32 values written as decimals come back exactly after the f64 → f32 rounding.
        assert_eq!((&a.poses, a.rh, a.th), (&b.poses, b.rh, b.th));
        assert!(worst(&a.tpose_joints, &b.tpose_joints) < 1e-5);
    }
    let view = |s: &Subject| {
        lifegom_data::dataset::load_view(s, 2, [1.0; 3], (32, 32), Default::default()).unwrap()
    };
    assert_eq!(view(&json).rgb, view(&official).rgb);
}

#[test]
fn bad_json_subjects_name_file_frame_and_field() {
    let check = |tag: &str, edit: &dyn Fn(&mut serde_json::Value), parts: &[&str]| {
        let path = json_subject(tag);
        image::save_buffer(
            path.with_file_name("small_mask.png"),
            &[255u8; 4],
            2,
            2,
            image::ExtendedColorType::L8,
        )
        .unwrap();
        edit_json(&path, |v| edit(v));
        let msg = custom::load_subject(&path)
            .and_then(|s| {
                (0..s.frames.len()).try_for_each(|f| {
                    lifegom_data::dataset::load_view(&s, f, [0.0; 3], (32, 32), Default::default())
                        .map(|_| ())
                })
            })
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("subject.json") || msg.contains(".png"),
            "{msg}"
        );
        for p in parts {
            assert!(msg.contains(p), "{tag}: `{msg}` lacks `{p}`");
        }
    };
    check(
        "nan-pose",
        &|v| v["frames"][1]["poses"][7] = serde_json::Value::Null,
        &["frame_000001", "field `poses`", "non-finite"],
    );
    check(
        "joint-count",
        &|v| {
            let p = v["frames"][0]["poses"].as_array_mut().unwrap();
            p.truncate(p.len() - 3);
        },
        &["frame_000000", "field `poses`", "104 joints"],
    );
    check(
        "behind",
        &|v| {
            // Turn the camera around: the body ends up behind it.
            for row in 0..3 {
                for col in 0..4 {
                    let x = v["frames"][2]["extrinsics"][row][col].as_f64().unwrap();
                    if row != 1 {
                        v["frames"][2]["extrinsics"][row][col] = serde_json::json!(-x);
                    }
                }
            }
        },
        &["frame_000002", "field `extrinsics`", "behind the body"],
    );
    check(
        "camera-to-world",
        &|v| {
            // The inverse of E, as tools that store camera poses write it.
            let e = &v["frames"][1]["extrinsics"];
            let r = |i: usize, j: usize| e[i][j].as_f64().unwrap();
            let t = [r(0, 3), r(1, 3), r(2, 3)];
            let inv: Vec<Vec<f64>> = (0..4)
                .map(|i| match i {
                    3 => vec![0.0, 0.0, 0.0, 1.0],
                    _ => vec![
                        r(0, i),
                        r(1, i),
                        r(2, i),
                        -(0..3).map(|k| r(k, i) * t[k]).sum::<f64>(),
                    ],
                })
                .collect();
            v["frames"][1]["extrinsics"] = serde_json::json!(inv);
        },
        &["frame_000001", "field `extrinsics`", "world to camera"],
    );
    check(
        "missing-view",
        &|v| v["frames"][0]["image"] = serde_json::json!("nowhere.png"),
        &["nowhere.png", "frames[0].image", "is not a file"],
    );
    check(
        "mask-size",
        &|v| v["frames"][0]["mask"] = serde_json::json!("small_mask.png"),
        &["small_mask.png", "size mismatch"],
    );
    check(
        "format",
        &|v| v["format"] = serde_json::json!("something-else"),
        &["field `format`", "lifegom-subject-1"],
    );
}

/// A subject written at 4× the training size and shrunk by the loader (the default
/// anti-aliased resize) is the subject rendered at the training size with 4 × 4 supersampling,
/// up to the 8-bit rounding of each; the reference's `cv2.resize` rule aliases it.
#[test]
fn a_subject_written_at_four_times_the_size_shrinks_to_the_supersampled_render() {
    use lifegom_data::preprocess::{FloatImage, Kernel, ResizeMode, resize};
    let cfg = tiny_config();
    let s = cfg.synthetic.clone().unwrap();
    let template = lifegom_render::template::BodyTemplate::load(s.template.path()).unwrap();
    let size = 48;
    let native = synth::SynthConfig {
        image_size: size,
        supersample: 4,
        ..s.clone()
    };
    let large = synth::SynthConfig {
        image_size: 4 * size,
        supersample: 1,
        ..s.clone()
    };
    let a = synth::generate_subject(&template, &native, 7, 1, "x", Some(3)).unwrap();
    let b = synth::generate_subject(&template, &large, 7, 1, "x", Some(3)).unwrap();
    let psnr = |x: &[f32], y: &[f32]| {
        let mse = x
            .iter()
            .zip(y)
            .map(|(p, q)| f64::from(p - q).powi(2))
            .sum::<f64>()
            / x.len() as f64;
        10.0 * (255.0f64 * 255.0 / mse).log10()
    };
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        let want = FloatImage::from_rgb8(size, size, &fa.rgb);
        let big = FloatImage::from_rgb8(4 * size, 4 * size, &fb.rgb);
        let shrunk = |mode| resize(&big, size, size, Kernel::Lanczos4, mode);
        let (aa, cv) = (
            psnr(&shrunk(ResizeMode::AntiAliased).data, &want.data),
            psnr(&shrunk(ResizeMode::Reference).data, &want.data),
        );
        eprintln!(
            "{}: shrunk 4x vs supersampled: anti-aliased {aa:.1} dB, reference {cv:.1} dB",
            fa.name
        );
        assert!(aa > 60.0, "{}: anti-aliased shrink at {aa:.1} dB", fa.name);
        assert!(
            cv < aa - 10.0,
            "{}: reference {cv:.1} dB, anti-aliased {aa:.1}",
            fa.name
        );
    }
}

/// The held-out family (design.md §8.11) is written at `held_out_scale` times the size into its
/// own folder and split file, and reads back through the validation rules at the config's size;
/// its people are not the validation split's.
#[test]
fn held_out_subjects_are_written_large_and_read_at_the_configs_size() {
    let dir = std::env::temp_dir().join(format!("lifegom-held-out-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut cfg = tiny_config().with_root(&dir);
    cfg.data.held_out_dir = Some("held_out".into());
    cfg.data.held_out_split = Some("held_out.json".into());
    let s = synth::SynthConfig {
        train_subjects: 0,
        val_subjects: 1,
        held_out_subjects: 2,
        ..cfg.synthetic.clone().unwrap()
    };
    s.validate(&cfg.data, Path::new("tiny.toml")).unwrap();
    let summary = synth::generate_split(&s, &cfg.data, &dir, s.seed, &|| {}).unwrap();
    assert_eq!(summary.held_out, ["held_000", "held_001"]);
    let png = image::open(dir.join("held_out/held_000/images/frame_000000.png")).unwrap();
    assert_eq!(png.width(), 4 * s.image_size);

    let held = cfg.data.held_out().unwrap();
    let set = Dataset::open(&held, Split::Val).unwrap();
    assert_eq!(set.subjects.len(), 2);
    let mut rng = Rng::new(0);
    let sample = set.sample(0, &mut rng).unwrap();
    let [w, h] = cfg.data.img_size;
    assert!(
        sample
            .views
            .iter()
            .all(|v| v.rgb.len() == (w * h * 3) as usize)
    );
    // Every view sees the person: the shrunk mask covers a few percent of the image.
    for v in &sample.views {
        let cover = v.mask.iter().sum::<f32>() / v.mask.len() as f32;
        assert!((0.02..0.6).contains(&cover), "mask cover {cover}");
    }
    let val = Dataset::open(&cfg.data, Split::Val).unwrap();
    let other = val.sample(0, &mut Rng::new(0)).unwrap();
    assert_ne!(other.views[0].rgb, sample.views[0].rgb);

    // Half a pair is one clear error naming the field.
    let mut half = cfg.data.clone();
    half.held_out_split = None;
    let err = half
        .validate(Path::new("tiny.toml"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("held_out_dir"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The stream's variety (design.md §8.11) draws a camera distance, a light, prints and a template
/// inset per subject from a fork of its own: the person, pose and camera azimuths stay the ones
/// drawn without it.
#[test]
fn stream_variety_moves_the_camera_the_light_and_the_template_but_keeps_the_person() {
    let s = tiny_config().synthetic.unwrap();
    let template = lifegom_render::template::BodyTemplate::load(s.template.path()).unwrap();
    let varied = synth::SynthConfig {
        camera_radius_range: Some([2.5, 2.5]),
        shading: synth::Shading::RandomLight,
        ..s.clone()
    };
    let a = synth::generate_subject(&template, &s, 7, 1, "x", Some(3)).unwrap();
    let b = synth::generate_subject(&template, &varied, 7, 1, "x", Some(3)).unwrap();
    assert_eq!(a.est_joints, b.est_joints);
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        assert_eq!(fa.body, fb.body);
        let distance = |f: &synth::RenderedFrame| {
            let c = f.camera.cam_from_world;
            (Vec3::from(c.inverse().translation) - synth::LOOK_AT).length()
        };
        assert!((distance(fa) - 2.0).abs() < 1e-3 && (distance(fb) - 2.5).abs() < 1e-3);
        // Farther: the person covers less of the picture; shaded: other colours.
        let cover = |f: &synth::RenderedFrame| f.mask.iter().map(|&m| u64::from(m)).sum::<u64>();
        assert!(cover(fb) < cover(fa));
    }
    let albedo = synth::SynthConfig {
        camera_radius_range: Some([2.5, 2.5]),
        ..s.clone()
    };
    let c = synth::generate_subject(&template, &albedo, 7, 1, "x", Some(3)).unwrap();
    assert_eq!(c.frames[0].mask, b.frames[0].mask);
    assert_ne!(c.frames[0].rgb, b.frames[0].rgb);
    // `[synthetic.stream_variety]` draws the same for its share of the subjects and nothing
    // for the others.
    let stream = |share: f32| synth::SynthConfig {
        stream_variety: Some(synth::StreamVariety {
            camera_radius: [2.5, 2.5],
            shading: synth::Shading::RandomLight,
            share,
            prints: synth::StreamPrints::Split,
            template_inset: [0.0; 2],
            template_inset_subjects: synth::InsetSubjects::Varied,
        }),
        ..s.clone()
    };
    let all = synth::generate_subject(&template, &stream(1.0), 7, 1, "x", Some(3)).unwrap();
    let none = synth::generate_subject(&template, &stream(0.0), 7, 1, "x", Some(3)).unwrap();
    assert_eq!(all.frames[0].mask, b.frames[0].mask);
    assert_ne!(all.frames[0].rgb, a.frames[0].rgb);
    assert_eq!(none.frames[0].rgb, a.frames[0].rgb);
    // `prints = "more"` re-draws garments after the camera and the light: the same silhouettes,
    // other colours on most people (each of two garments at even odds).
    let more = synth::SynthConfig {
        stream_variety: stream(1.0).stream_variety.map(|v| synth::StreamVariety {
            prints: synth::StreamPrints::More,
            ..v
        }),
        ..s.clone()
    };
    let mut reprinted = 0;
    for index in 0..8 {
        let split =
            synth::generate_subject(&template, &stream(1.0), 7, index, "x", Some(3)).unwrap();
        let extra = synth::generate_subject(&template, &more, 7, index, "x", Some(3)).unwrap();
        assert_eq!(split.frames[0].mask, extra.frames[0].mask);
        reprinted += usize::from(split.frames[0].rgb != extra.frames[0].rgb);
    }
    assert!(reprinted >= 3, "{reprinted} of 8 re-printed");
    // `template_inset` moves the model's template inward, drawn last: the pictures, the joints
    // and the pose stay; every vertex moves inward along its normal, by the depth or, on thin
    // parts, by less.
    let inset = |least: f32, most: f32| synth::SynthConfig {
        stream_variety: stream(1.0).stream_variety.map(|v| synth::StreamVariety {
            template_inset: [least, most],
            ..v
        }),
        ..s.clone()
    };
    let deep = synth::generate_subject(&template, &inset(0.02, 0.02), 7, 1, "x", Some(3)).unwrap();
    assert_eq!(deep.est_joints, all.est_joints);
    for (fd, fa) in deep.frames.iter().zip(&all.frames) {
        assert_eq!((&fd.rgb, &fd.mask, &fd.body), (&fa.rgb, &fa.mask, &fa.body));
    }
    let normals = synth::body::vertex_normals(&all.est_vertices, &template.topology.faces);
    let depths: Vec<f32> = all
        .est_vertices
        .iter()
        .zip(&deep.est_vertices)
        .zip(&normals)
        .map(|((a, d), n)| {
            assert!((*a - *d).cross(*n).length() < 1e-5, "moved off its normal");
            (*a - *d).dot(*n)
        })
        .collect();
    assert!(depths.iter().all(|&d| (-1e-6..=0.02 + 1e-6).contains(&d)));
    let full = depths.iter().filter(|&&d| d > 0.02 - 1e-5).count();
    // 943 of the low-res template's 1,229 at 2 cm: hands, feet and the face hold the others.
    assert!(
        full * 10 > depths.len() * 7,
        "{full} of {} at full depth",
        depths.len()
    );
    // The share without variety keeps its template unless the inset is for all subjects; then
    // it moves as a varied one's, its pictures still the split's.
    let plain = |subjects| {
        let cfg = synth::SynthConfig {
            stream_variety: inset(0.02, 0.02)
                .stream_variety
                .map(|v| synth::StreamVariety {
                    share: 0.0,
                    template_inset_subjects: subjects,
                    ..v
                }),
            ..s.clone()
        };
        synth::generate_subject(&template, &cfg, 7, 1, "x", Some(3)).unwrap()
    };
    let kept = plain(synth::InsetSubjects::Varied);
    let moved = plain(synth::InsetSubjects::All);
    assert_eq!(kept.est_vertices, none.est_vertices);
    assert_eq!(moved.est_vertices, deep.est_vertices);
    for (fm, fn_) in moved.frames.iter().zip(&none.frames) {
        assert_eq!(
            (&fm.rgb, &fm.mask, &fm.body),
            (&fn_.rgb, &fn_.mask, &fn_.body)
        );
    }
    // A negative depth puts the template outside the body, each vertex by the full depth.
    let loose =
        synth::generate_subject(&template, &inset(-0.02, -0.02), 7, 1, "x", Some(3)).unwrap();
    for ((a, l), n) in all
        .est_vertices
        .iter()
        .zip(&loose.est_vertices)
        .zip(&normals)
    {
        assert!((*l - *a - *n * 0.02).length() < 1e-6, "{a} → {l} along {n}");
    }
    for (fl, fa) in loose.frames.iter().zip(&all.frames) {
        assert_eq!((&fl.rgb, &fl.mask), (&fa.rgb, &fa.mask));
    }
    let flat = synth::generate_subject(&template, &inset(0.0, 0.0), 7, 1, "x", Some(3)).unwrap();
    assert_eq!(flat.est_vertices, all.est_vertices);
    for (least, most) in [(0.03, 0.01), (-0.06, 0.0), (0.0, 0.06)] {
        let err = inset(least, most)
            .validate(&tiny_config().data, Path::new("tiny.toml"))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("synthetic.stream_variety.template_inset"),
            "{err}"
        );
    }
    assert!(
        inset(-0.02, 0.03)
            .validate(&tiny_config().data, Path::new("tiny.toml"))
            .is_ok()
    );
    let bad = synth::SynthConfig {
        camera_radius_range: Some([3.0, 2.0]),
        ..s.clone()
    };
    let cfg = tiny_config();
    let err = bad
        .validate(&cfg.data, Path::new("tiny.toml"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("camera_radius_range"), "{err}");
    // Targets from other cameras are a multi-frame choice; the multi-view split refuses it.
    let bad = synth::SynthConfig {
        stream_target_camera: synth::TargetCamera::Others,
        ..s
    };
    let err = bad
        .validate(&cfg.data, Path::new("tiny.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("tiny.toml") && err.contains("synthetic.stream_target_camera"),
        "{err}"
    );
}
