//! The pickle reader against pickles written by Python's `pickle` module with real numpy arrays
//! (numpy 1.26 and 2.x, protocols 2, 4, 5), made by `tools/make_pickle_fixtures.py`. Expected
//! values are recomputed here from the formulas in that script.

use std::path::PathBuf;

use lifegom_data::pickle::{self, DType, Value};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/fixtures/pickle")
        .join(name)
}

fn array<'a>(v: &'a Value, key: &str) -> &'a lifegom_data::pickle::NdArray {
    v.get(key)
        .and_then(Value::as_array)
        .unwrap_or_else(|| panic!("`{key}` is not an array: {:?}", v.get(key)))
}

fn check(v: &Value) {
    let a = array(v, "f32");
    assert_eq!((a.dtype, a.shape.as_slice()), (DType::F32, &[3, 4][..]));
    assert_eq!(
        a.to_f64(),
        (0..12).map(|i| i as f64 * 0.5 - 1.0).collect::<Vec<_>>()
    );

    let a = array(v, "f64");
    assert_eq!((a.dtype, a.shape.as_slice()), (DType::F64, &[2, 3][..]));
    assert_eq!(
        a.to_f64(),
        (0..6).map(|i| i as f64 / 3.0).collect::<Vec<_>>()
    );

    let a = array(v, "i32");
    assert_eq!(a.dtype, DType::I32);
    assert_eq!(a.to_i64().unwrap(), vec![-3, -2, -1, 0, 1, 2]);

    let a = array(v, "i64");
    assert_eq!((a.dtype, a.shape.as_slice()), (DType::I64, &[2, 2][..]));
    assert_eq!(
        a.to_i64().unwrap(),
        (0..4).map(|i| i << 40).collect::<Vec<_>>()
    );

    let a = array(v, "u8");
    assert_eq!(a.dtype, DType::U8);
    assert_eq!(a.to_i64().unwrap(), (250..256).collect::<Vec<_>>());

    let a = array(v, "bool");
    assert_eq!(a.dtype, DType::Bool);
    assert_eq!(a.to_i64().unwrap(), vec![1, 0, 1]);

    // Fortran order comes back in C order.
    let a = array(v, "f64_fortran");
    assert_eq!(a.shape, vec![3, 4]);
    assert_eq!(a.to_f64(), (0..12).map(f64::from).collect::<Vec<_>>());
    let a = array(v, "i32_fortran_3d");
    assert_eq!(a.shape, vec![2, 3, 4]);
    assert_eq!(a.to_i64().unwrap(), (0..24).collect::<Vec<_>>());

    // Big endian.
    let a = array(v, "f32_big");
    assert_eq!(a.to_f64(), vec![0.0, 0.25, 0.5, 0.75, 1.0]);
    let a = array(v, "i64_big");
    assert_eq!(a.to_i64().unwrap(), vec![-2, -1, 0, 1]);

    // Corner cases.
    let a = array(v, "empty");
    assert_eq!((a.shape.as_slice(), a.len()), (&[0, 3][..], 0));
    let a = array(v, "zero_d");
    assert_eq!((a.shape.len(), a.to_f64()), (0, vec![3.5]));
    let a = array(v, "scalar_f32");
    assert_eq!((a.dtype, a.to_f64()), (DType::F32, vec![1.5]));
    let a = array(v, "scalar_i64");
    assert_eq!((a.dtype, a.to_i64().unwrap()), (DType::I64, vec![-7]));
    assert_eq!(
        v.get("py").unwrap(),
        &Value::List(vec![
            Value::Int(1),
            Value::Int(-2),
            Value::Int(1 << 40),
            Value::Float(2.5),
            Value::Str("text".into()),
            Value::None,
            Value::Bool(true),
            Value::Tuple(vec![Value::Int(1), Value::Int(2)]),
        ])
    );

    // The official file shapes.
    let cam = v
        .get("cameras")
        .and_then(|c| c.get("frame_000000"))
        .unwrap();
    let k = array(cam, "intrinsics");
    assert_eq!(k.shape, vec![3, 3]);
    assert!((k.to_f64()[0] - 819.2).abs() < 1e-4);
    let e = array(cam, "extrinsics");
    assert_eq!(e.to_f64()[11], 2.0);
    let info = v
        .get("mesh_infos")
        .and_then(|c| c.get("frame_000000"))
        .unwrap();
    assert_eq!(array(info, "poses").len(), 72);
    assert_eq!(array(info, "Rh").shape, vec![1, 3]);
    let cj = v.get("canonical_joints").unwrap();
    assert_eq!(array(cj, "faces").to_i64().unwrap(), vec![0, 1, 2, 2, 1, 3]);
    assert_eq!(array(cj, "weights").shape, vec![4, 24]);
}

#[test]
fn numpy1_and_numpy2_pickles_at_protocols_2_4_5() {
    for major in [1, 2] {
        for protocol in [2, 4, 5] {
            let path = fixture(&format!("np{major}_p{protocol}.pkl"));
            let v = pickle::load(&path).unwrap_or_else(|e| panic!("{e}"));
            check(&v);
        }
    }
}

#[test]
fn truncated_fixture_is_an_error_naming_the_file() {
    let bytes = std::fs::read(fixture("np2_p5.pkl")).unwrap();
    for cut in (0..bytes.len()).step_by(7) {
        assert!(
            pickle::reader::from_slice(&bytes[..cut]).is_err(),
            "cut {cut}"
        );
    }
    let dir = std::env::temp_dir().join(format!("lifegom-pickle-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("cut.pkl");
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let msg = pickle::load(&path).unwrap_err().to_string();
    assert!(
        msg.contains("cut.pkl") && msg.contains("truncated"),
        "{msg}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
