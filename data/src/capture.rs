//! Motion capture files: SMPL pose sequences as AIST++ ships them, read into a
//! [`PoseSequence`] that any `--motion` option plays.
//!
//! # Files
//!
//! - **`.pkl`**: a Python pickle of a dict (AIST++'s `motions/*.pkl`), read by [`crate::pickle`];
//! - **`.npz`**: numpy's zip of `.npy` arrays (`numpy.savez` or `savez_compressed`), one array per
//!   key, read here (`.npy` format versions 1–3, any byte order, C or Fortran order).
//!
//! The content is told apart by its first bytes (a zip starts with `PK`), not by the name.
//!
//! # Fields
//!
//! | key | shape | meaning |
//! |---|---|---|
//! | `smpl_poses` | `[N, 72]` or `[N, 24, 3]` | per frame, SMPL's 24 joint rotations, axis-angle, radians (joint 0 is the global orientation) |
//! | `smpl_trans` | `[N, 3]` (optional) | per frame, the body's translation, in the file's units |
//! | `smpl_scaling` | `[1]` or scalar (optional, default 1) | the file's units per metre: metres are `smpl_trans / smpl_scaling` (AIST++) |
//! | `fps` or `mocap_framerate` | scalar (optional, default 60: AIST++) | frames per second |
//!
//! Other keys (AIST++'s `smpl_loss`) are ignored. The sequence is named for SMPL
//! ([`SMPL_JOINT_NAMES`]); on an SMPL avatar it plays as it is, on an Anny avatar through
//! [`lifegom_render::retarget`]. Root translations are made relative to the first frame (the
//! avatar starts where it stands) and go into the `.glb` animation; the rendered GIFs follow the
//! body and do not move with it.
//!
//! Every error names the file and the key (and the frame, for a non-finite value).

use std::io::Read;
use std::path::Path;

use glam::Vec3;
use lifegom_render::motion::{MotionSource, PoseSequence, SMPL_JOINT_NAMES};
use lifegom_render::skeleton::BodyPose;

use crate::error::{DataError, Location, Result};
use crate::pickle::{self, DType, NdArray};

/// AIST++'s frame rate, used when a file does not state one.
pub const DEFAULT_FPS: f32 = 60.0;

/// Frames a file may hold: a day at 60 fps. Longer is a damaged length field, not a motion.
pub const MAX_FRAMES: usize = 60 * 60 * 60 * 24;

/// Largest `.npy` member of an `.npz` read into memory (a 1 GiB motion is not a motion).
const MAX_NPY_BYTES: u64 = 1 << 30;

/// Whether `path` names a capture file this module reads (by extension: `--motion` values are
/// told apart from the procedural names and the JSON pose files this way).
pub fn is_capture_file(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("pkl") || e.eq_ignore_ascii_case("npz"))
}

/// Parses a `--motion` value: a capture file ([`load`]) or what [`MotionSource`] parses (a
/// procedural name or a `lifegom-motion-1` file). Errors are one line naming the file.
pub fn parse_motion(value: &str) -> std::result::Result<MotionSource, String> {
    let path = Path::new(value);
    if is_capture_file(path) && path.exists() {
        return load(path)
            .map(MotionSource::File)
            .map_err(|e| e.to_string());
    }
    value.parse::<MotionSource>().map_err(|e| e.to_string())
}

/// Reads an SMPL capture sequence (module docs).
pub fn load(path: &Path) -> Result<PoseSequence> {
    let mut head = Vec::with_capacity(4);
    std::fs::File::open(path)
        .and_then(|f| f.take(4).read_to_end(&mut head))
        .map_err(|e| DataError::io(Location::file(path), e))?;
    let fields = if head.starts_with(b"PK") {
        read_npz(path)?
    } else {
        pickle_fields(path)?
    };
    from_fields(path, &fields)
}

/// The arrays of a pickled dict, by key.
fn pickle_fields(path: &Path) -> Result<Vec<(String, NdArray)>> {
    let value = pickle::load(path)?;
    let Some(items) = value.as_dict() else {
        return Err(DataError::invalid(
            Location::file(path),
            format!(
                "a motion pickle holds a dict (AIST++: smpl_poses, smpl_trans, smpl_scaling), not a {}",
                value.type_name()
            ),
        ));
    };
    Ok(items
        .iter()
        .filter_map(|(k, v)| Some((k.as_str()?.to_string(), v.to_array()?)))
        .collect())
}

/// The arrays of an `.npz`, by key (member name without `.npy`), in the archive's order.
pub fn read_npz(path: &Path) -> Result<Vec<(String, NdArray)>> {
    let file = std::fs::File::open(path).map_err(|e| DataError::io(Location::file(path), e))?;
    let bad = |member: &str, reason: String| {
        DataError::invalid(Location::file(path).field(member.to_string()), reason)
    };
    let mut archive = zip::ZipArchive::new(file).map_err(|e| {
        DataError::invalid(Location::file(path), format!("not a readable .npz: {e}"))
    })?;
    let mut out = Vec::new();
    for i in 0..archive.len() {
        let mut member = archive.by_index(i).map_err(|e| {
            DataError::invalid(Location::file(path), format!("zip member {i}: {e}"))
        })?;
        let name = member
            .name()
            .map_err(|e| DataError::invalid(Location::file(path), format!("zip member {i}: {e}")))?
            .to_string();
        let Some(key) = name.strip_suffix(".npy") else {
            continue;
        };
        if member.size() > MAX_NPY_BYTES {
            return Err(bad(
                key,
                format!(
                    "{} bytes, more than the {MAX_NPY_BYTES} a motion may take",
                    member.size()
                ),
            ));
        }
        let mut bytes = Vec::new();
        (&mut member)
            .take(MAX_NPY_BYTES + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| bad(key, format!("cannot decompress: {e}")))?;
        out.push((key.to_string(), parse_npy(&bytes).map_err(|r| bad(key, r))?));
    }
    Ok(out)
}

/// Parses one `.npy` array (format versions 1–3).
fn parse_npy(bytes: &[u8]) -> std::result::Result<NdArray, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy array (no \\x93NUMPY magic)".into());
    }
    let (header_len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => {
            return Err(format!(
                ".npy format version {v} is not supported (1 to 3 are)"
            ));
        }
    };
    let end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or("truncated .npy header")?;
    let header =
        std::str::from_utf8(&bytes[start..end]).map_err(|_| "the .npy header is not text")?;
    let descr = dict_value(header, "descr").ok_or("the .npy header has no `descr`")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let (order, code) = match descr.as_bytes().first() {
        Some(b'<' | b'>' | b'|' | b'=') => (descr.as_bytes()[0], &descr[1..]),
        _ => (b'|', descr),
    };
    let dtype = DType::from_code(code)
        .ok_or_else(|| format!("dtype `{descr}` is not a number type lifegom reads"))?;
    let fortran = match dict_value(header, "fortran_order").map(str::trim) {
        Some("True") => true,
        Some("False") => false,
        _ => return Err("the .npy header has no `fortran_order`".into()),
    };
    let shape_text = dict_value(header, "shape").ok_or("the .npy header has no `shape`")?;
    let shape = shape_text
        .trim()
        .trim_start_matches('(')
        .trim_end_matches(')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("shape `{shape_text}`"))
        })
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let elements = pickle::reader::decode_array(&bytes[end..], dtype, order, &shape, fortran)?;
    Ok(NdArray {
        dtype,
        shape,
        elements,
    })
}

/// The text of `key`'s value in the `.npy` header's Python dict literal (up to the next key
/// or the closing brace; a tuple's commas are kept).
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header
        .find(&format!("'{key}'"))
        .or_else(|| header.find(&format!("\"{key}\"")))?;
    let rest = &header[at + key.len() + 2..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')')? + 1
    } else {
        rest.find([',', '}']).unwrap_or(rest.len())
    };
    Some(&rest[..end])
}

fn from_fields(path: &Path, fields: &[(String, NdArray)]) -> Result<PoseSequence> {
    let at = |key: &str| Location::file(path).field(key.to_string());
    let get = |key: &str| fields.iter().find(|(k, _)| k == key).map(|(_, a)| a);
    let keys: Vec<&str> = fields.iter().map(|(k, _)| k.as_str()).collect();
    let poses = get("smpl_poses").ok_or_else(|| {
        DataError::invalid(
            at("smpl_poses"),
            format!("missing: an SMPL motion (AIST++) has `smpl_poses` [frames, 72]; the file has {keys:?}"),
        )
    })?;
    let joints = SMPL_JOINT_NAMES.len();
    let frames = match poses.shape.as_slice() {
        [n, w] if *w == 3 * joints => *n,
        [n, j, 3] if *j == joints => *n,
        s => {
            return Err(DataError::invalid(
                at("smpl_poses"),
                format!("shape {s:?}: an SMPL sequence is [frames, 72] or [frames, 24, 3]"),
            ));
        }
    };
    if frames == 0 || frames > MAX_FRAMES {
        return Err(DataError::invalid(
            at("smpl_poses"),
            format!("{frames} frames: a motion has 1 to {MAX_FRAMES}"),
        ));
    }
    let values = poses.to_f32();
    let mut sequence = Vec::with_capacity(frames);
    for (k, frame) in values.chunks_exact(3 * joints).enumerate() {
        if let Some(i) = frame.iter().position(|v| !v.is_finite()) {
            return Err(DataError::invalid(
                at("smpl_poses").frame(format!("{k}")),
                format!("value {i} (joint {}) is {}", i / 3, frame[i]),
            ));
        }
        sequence.push(BodyPose {
            joint_rotations: frame.chunks_exact(3).map(Vec3::from_slice).collect(),
        });
    }

    let scalar = |key: &str| -> Result<Option<f64>> {
        let Some(a) = get(key) else { return Ok(None) };
        match a.to_f64().as_slice() {
            [v] if v.is_finite() => Ok(Some(*v)),
            v => Err(DataError::invalid(
                at(key),
                format!(
                    "expected one finite number, found {} values {:?}",
                    v.len(),
                    a.shape
                ),
            )),
        }
    };
    let scaling = scalar("smpl_scaling")?.unwrap_or(1.0);
    if scaling <= 0.0 {
        return Err(DataError::invalid(
            at("smpl_scaling"),
            format!("{scaling}: units per metre must be > 0"),
        ));
    }
    let fps = match scalar("fps")? {
        Some(f) => Some(f),
        None => scalar("mocap_framerate")?,
    }
    .map_or(DEFAULT_FPS, |f| f as f32);
    if !(fps.is_finite() && fps > 0.0) {
        return Err(DataError::invalid(at("fps"), format!("{fps}: must be > 0")));
    }
    let root_translations = match get("smpl_trans") {
        None => None,
        Some(t) => {
            if t.shape != [frames, 3] {
                return Err(DataError::invalid(
                    at("smpl_trans"),
                    format!(
                        "shape {:?}, the poses have {frames} frames: [frames, 3] expected",
                        t.shape
                    ),
                ));
            }
            let metres: Vec<Vec3> = t
                .to_f64()
                .chunks_exact(3)
                .map(|c| {
                    Vec3::new(
                        (c[0] / scaling) as f32,
                        (c[1] / scaling) as f32,
                        (c[2] / scaling) as f32,
                    )
                })
                .collect();
            if let Some(k) = metres.iter().position(|v| !v.is_finite()) {
                return Err(DataError::invalid(
                    at("smpl_trans").frame(format!("{k}")),
                    "non-finite translation",
                ));
            }
            let first = metres[0];
            Some(metres.into_iter().map(|v| v - first).collect())
        }
    };
    Ok(PoseSequence {
        source: path.to_path_buf(),
        fps,
        joint_names: Some(SMPL_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect()),
        poses: sequence,
        root_translations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pickle::Value;

    fn fixture(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/fixtures/capture")
            .join(name)
    }

    /// The two fixtures (written by numpy and Python's pickle, `tools/capture-fixture`) hold
    /// the same motion: 30 frames at 60 fps of a left-knee bend and a walk forward, in AIST++'s
    /// units (`smpl_scaling` 90).
    #[test]
    fn aist_pickle_and_npz_read_the_same_motion() {
        let pkl = load(&fixture("aist_like.pkl")).unwrap();
        let npz = load(&fixture("aist_like.npz")).unwrap();
        for seq in [&pkl, &npz] {
            assert_eq!(seq.len(), 30);
            assert_eq!(seq.fps, 60.0);
            assert_eq!(seq.num_joints(), 24);
            let knee = seq.poses()[29].joint_rotations[4];
            assert!((knee.x - 1.0).abs() < 1e-6, "{knee}");
            let t = seq.root_translations.as_ref().unwrap();
            assert_eq!(t[0], Vec3::ZERO);
            // 0.9 units a frame in AIST++ units (90 per metre) → 1 cm a frame.
            assert!((t[29].z - 0.29).abs() < 1e-5, "{}", t[29]);
        }
        assert_eq!(pkl.poses(), npz.poses());
    }

    #[test]
    fn bad_capture_files_name_the_file_and_key() {
        let dir = std::env::temp_dir().join(format!("lifegom-capture-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |name: &str, value: &Value| {
            let path = dir.join(name);
            pickle::save(&path, value).unwrap();
            path
        };
        let arr =
            |shape: Vec<usize>, v: Vec<f64>| Value::Array(NdArray::from_f64(shape, v).unwrap());
        let dict = |items: Vec<(&str, Value)>| {
            Value::Dict(
                items
                    .into_iter()
                    .map(|(k, v)| (Value::Str(k.into()), v))
                    .collect(),
            )
        };
        let cases = [
            ("list.pkl", Value::List(vec![]), "holds a dict"),
            (
                "none.pkl",
                dict(vec![("smpl_trans", arr(vec![1, 3], vec![0.0; 3]))]),
                "`smpl_poses`",
            ),
            (
                "shape.pkl",
                dict(vec![("smpl_poses", arr(vec![2, 71], vec![0.0; 142]))]),
                "[2, 71]",
            ),
            (
                "nan.pkl",
                dict(vec![(
                    "smpl_poses",
                    arr(vec![2, 72], {
                        let mut v = vec![0.0; 144];
                        v[72 + 13] = f64::NAN;
                        v
                    }),
                )]),
                "frame `1`",
            ),
            (
                "trans.pkl",
                dict(vec![
                    ("smpl_poses", arr(vec![2, 72], vec![0.0; 144])),
                    ("smpl_trans", arr(vec![3, 3], vec![0.0; 9])),
                ]),
                "`smpl_trans`",
            ),
            (
                "scale.pkl",
                dict(vec![
                    ("smpl_poses", arr(vec![1, 72], vec![0.0; 72])),
                    ("smpl_scaling", arr(vec![1], vec![0.0])),
                ]),
                "`smpl_scaling`",
            ),
        ];
        for (name, value, want) in cases {
            let path = write(name, &value);
            let err = load(&path).unwrap_err().to_string();
            assert!(err.contains(name), "{name}: {err}");
            assert!(err.contains(want), "{name}: {err}");
        }
        let junk = dir.join("junk.npz");
        std::fs::write(&junk, b"PK\x03\x04 not really a zip").unwrap();
        let err = load(&junk).unwrap_err().to_string();
        assert!(err.contains("junk.npz"), "{err}");
        let err = parse_motion(dir.join("absent.pkl").to_str().unwrap()).unwrap_err();
        assert!(err.contains("absent.pkl"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn npy_headers_of_every_version_and_order_parse() {
        let mut v1 = b"\x93NUMPY\x01\x00".to_vec();
        let header = "{'descr': '>f8', 'fortran_order': True, 'shape': (2, 3), }";
        let mut h = header.to_string();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        v1.extend((h.len() as u16).to_le_bytes());
        v1.extend(h.as_bytes());
        // Fortran order: column by column.
        for x in [0.0f64, 3.0, 1.0, 4.0, 2.0, 5.0] {
            v1.extend(x.to_be_bytes());
        }
        let a = parse_npy(&v1).unwrap();
        assert_eq!(a.shape, [2, 3]);
        assert_eq!(a.to_f64(), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        assert!(parse_npy(&v1[..20]).is_err());
        assert!(parse_npy(b"not numpy at all").is_err());
    }
}
