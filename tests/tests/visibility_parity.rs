//! Backend parity of the triangle-ID visibility rasterizer: one test body
//! ([`assert_triangle_id_parity`]) run on every backend against the checked CPU reference
//! (`rasterize_triangle_ids`, `f64` edge functions).
//!
//! The CPU backends run the reference itself, so they must agree exactly. The wgpu kernels work
//! in `f32`; a pixel centre within rounding of an edge or a depth tie may go to the other face.
//! So the wgpu run must agree exactly on the scenes whose coordinates are exact in `f32`
//! (half-integer grids), and elsewhere on all but a sliver of pixels, with matching depths where
//! the face matches. The wgpu runs need a Vulkan adapter (lavapipe on CI, see
//! `backend_parity.rs`).

#![allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; it is the reference here.

use burn::tensor::{Device, Int, Tensor, TensorData};
use glam::{Affine3A, Vec3};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::subdivision::Subdivision;
use lifegom_render::template::{BodyTemplate, lowres_template_path};
use lifegom_render::testing::{octahedron, pixel_camera, wgpu_test_device};
use lifegom_render::visibility::{
    ViewSet, rasterize_on_device, rasterize_triangle_ids, visibility_in_views, visible_vertices,
};
use lifegom_tests::{Rng, camera};

/// How closely a backend must follow the CPU reference on a scene.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Agreement {
    /// Every pixel's face id and depth bit for bit, every vertex's visibility.
    Exact,
    /// Face ids on all but `max(2, fraction · covered pixels)` pixels; depth within `depth`
    /// relative where the ids agree; visibility on all but as many vertices.
    Rounding { fraction: f64, depth: f32 },
}

/// A mesh, a camera and how closely `f32` kernels can follow the `f64` reference on it.
struct MeshScene {
    name: String,
    vertices: Vec<Vec3>,
    faces: Vec<[u32; 3]>,
    camera: Camera,
    gpu: Agreement,
}

fn scenes() -> Vec<MeshScene> {
    let rounding = Agreement::Rounding {
        fraction: 0.01,
        depth: 1e-5,
    };
    let mut scenes = Vec::new();

    // A regular grid with every vertex and edge on pixel centres or half-pixel lines: every
    // value is exact in f32, and every tie rule is exercised.
    let n = 6;
    let mut grid_v = Vec::new();
    for y in 0..=n {
        for x in 0..=n {
            grid_v.push(Vec3::new(x as f32 * 4.0 + 0.5, y as f32 * 4.0 + 0.5, 1.0));
        }
    }
    let id = |x: u32, y: u32| y * (n + 1) + x;
    let mut grid_f = Vec::new();
    for y in 0..n {
        for x in 0..n {
            let (a, b, c, d) = (id(x, y), id(x + 1, y), id(x + 1, y + 1), id(x, y + 1));
            if (x + y) % 2 == 0 {
                grid_f.extend([[a, b, c], [a, c, d]]);
            } else {
                grid_f.extend([[a, b, d], [b, c, d]]);
            }
        }
    }
    scenes.push(MeshScene {
        name: "half-integer grid (edges through pixel centres)".into(),
        vertices: grid_v,
        faces: grid_f,
        camera: pixel_camera(26, 26),
        gpu: Agreement::Exact,
    });

    // A closed mesh seen from outside: the back must stay hidden, no cracks.
    let (mesh, verts) = octahedron();
    let sub = Subdivision::new(&mesh, 3).expect("subdivision");
    let hv = sub.highres_vertices_cpu(&verts);
    for (k, eye) in [Vec3::new(0.2, 0.1, 4.0), Vec3::new(1.5, 2.0, 3.0)]
        .into_iter()
        .enumerate()
    {
        scenes.push(MeshScene {
            name: format!("subdivided octahedron, view {k}"),
            vertices: hv.clone(),
            faces: sub.highres.faces.clone(),
            camera: camera(eye, 64, 48, 60.0),
            gpu: rounding,
        });
    }

    // The body template from four sides, one of them close enough to clip.
    let body = BodyTemplate::load(lowres_template_path()).expect("template");
    for (k, eye) in [
        Vec3::new(0.0, 0.2, 3.0),
        Vec3::new(3.0, 0.5, 0.0),
        Vec3::new(-2.0, -0.5, -2.0),
        Vec3::new(0.05, 0.3, 0.15),
    ]
    .into_iter()
    .enumerate()
    {
        let k_cam = Intrinsics {
            fx: 90.0,
            fy: 90.0,
            cx: 40.0,
            cy: 48.0,
        };
        let cam =
            Camera::look_at(eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k_cam, 80, 96).expect("camera");
        scenes.push(MeshScene {
            name: format!("body template, view {k}"),
            vertices: body.vertices.clone(),
            faces: body.topology.faces.clone(),
            camera: cam,
            gpu: rounding,
        });
    }

    // The template subdivided twice (the model's high-res mesh), at a training resolution.
    let sub = Subdivision::new(&body.topology, 2).expect("subdivision");
    let cam = Camera::look_at(
        Vec3::new(0.8, 0.3, 2.4),
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::Y,
        Intrinsics {
            fx: 220.0,
            fy: 220.0,
            cx: 80.0,
            cy: 96.0,
        },
        160,
        192,
    )
    .expect("camera");
    scenes.push(MeshScene {
        name: "body template subdivided twice".into(),
        vertices: sub.highres_vertices_cpu(&body.vertices),
        faces: sub.highres.faces.clone(),
        camera: cam,
        gpu: rounding,
    });

    // Triangles crossing the near plane: one and two corners behind, one on the camera plane.
    let cam = Camera::new(
        Intrinsics {
            fx: 20.0,
            fy: 20.0,
            cx: 16.0,
            cy: 16.0,
        },
        Affine3A::IDENTITY,
        32,
        32,
    )
    .expect("camera");
    scenes.push(MeshScene {
        name: "near-plane clipping".into(),
        vertices: vec![
            Vec3::new(-1.0, -0.5, 2.0),
            Vec3::new(1.0, -0.5, 2.0),
            Vec3::new(0.0, 0.5, -3.0),
            Vec3::new(-1.0, 0.5, -2.0),
            Vec3::new(1.0, 0.5, -2.0),
            Vec3::new(0.0, 0.2, 1.0),
            Vec3::new(0.0, 1.0, 0.0),
        ],
        faces: vec![[0, 1, 2], [3, 4, 5], [0, 1, 6]],
        camera: cam,
        // Clipped corners sit at z = 1e-3, so `1/z` spans 1000 to 0.5 and the f32
        // interpolation loses about three digits of relative depth.
        gpu: Agreement::Rounding {
            fraction: 0.01,
            depth: 1e-3,
        },
    });

    // A seeded soup of overlapping triangles at random depths, with degenerate faces (a
    // repeated index, three collinear corners) mixed in.
    let mut rng = Rng::new(7);
    let mut soup_v = Vec::new();
    let mut soup_f = Vec::new();
    for t in 0..60u32 {
        let z = rng.range_f32(1.0, 3.0);
        for _ in 0..3 {
            soup_v.push(Vec3::new(
                rng.range_f32(-0.6, 0.6) * z,
                rng.range_f32(-0.6, 0.6) * z,
                z + rng.range_f32(-0.3, 0.3),
            ));
        }
        soup_f.push([3 * t, 3 * t + 1, 3 * t + 2]);
    }
    soup_f.push([0, 0, 1]);
    let base = soup_v.len() as u32;
    soup_v.extend([
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(0.1, 0.1, 1.0),
        Vec3::new(0.2, 0.2, 1.0),
    ]);
    soup_f.push([base, base + 1, base + 2]);
    scenes.push(MeshScene {
        name: "random overlapping triangles".into(),
        vertices: soup_v,
        faces: soup_f,
        camera: Camera::new(
            Intrinsics {
                fx: 40.0,
                fy: 40.0,
                cx: 28.5,
                cy: 21.5,
            },
            Affine3A::IDENTITY,
            57,
            43,
        )
        .expect("camera"),
        gpu: rounding,
    });

    // Tiny images and no faces at all.
    let cover = vec![
        Vec3::new(-1.5, -1.5, 1.5),
        Vec3::new(4.5, -1.5, 1.5),
        Vec3::new(-1.5, 4.5, 1.5),
    ];
    scenes.push(MeshScene {
        name: "1×1 image".into(),
        vertices: cover.clone(),
        faces: vec![[0, 1, 2]],
        camera: pixel_camera(1, 1),
        gpu: Agreement::Exact,
    });
    scenes.push(MeshScene {
        name: "no faces".into(),
        vertices: cover,
        faces: Vec::new(),
        camera: pixel_camera(5, 3),
        gpu: Agreement::Exact,
    });
    scenes
}

fn faces_tensor(faces: &[[u32; 3]], device: &Device) -> Tensor<2, Int> {
    let flat: Vec<i64> = faces.iter().flatten().map(|&v| i64::from(v)).collect();
    Tensor::from_data(TensorData::new(flat, [faces.len(), 3]), device)
}

fn vertices_tensor(vertices: &[Vec3], device: &Device) -> Tensor<2> {
    let flat: Vec<f32> = vertices.iter().flat_map(|v| v.to_array()).collect();
    Tensor::from_data(TensorData::new(flat, [vertices.len(), 3]), device)
}

fn ints<const D: usize>(t: Tensor<D, Int>) -> Vec<i64> {
    t.into_data().iter::<i64>().collect()
}

/// The one test body: `scene` rasterized on `device` against the CPU reference.
fn assert_triangle_id_parity(scene: &MeshScene, device: &Device, agreement: Agreement) {
    let want = rasterize_triangle_ids(&scene.vertices, &scene.faces, &scene.camera)
        .unwrap_or_else(|e| panic!("{}: {e}", scene.name));
    let want_vis = visible_vertices(&want, &scene.faces, scene.vertices.len());

    let faces = faces_tensor(&scene.faces, device);
    let got = rasterize_on_device(
        vertices_tensor(&scene.vertices, device),
        faces.clone(),
        &scene.camera,
    )
    .unwrap_or_else(|e| panic!("{}: {e}", scene.name));
    let (w, h) = (scene.camera.width as usize, scene.camera.height as usize);
    assert_eq!(got.face_ids.dims(), [h, w], "{}", scene.name);
    assert_eq!(got.depth.dims(), [h, w], "{}", scene.name);
    let got_vis = ints(got.visible_vertices(faces, scene.vertices.len()));
    let ids = ints(got.face_ids);
    let depth: Vec<f32> = got.depth.into_data().iter::<f32>().collect();

    let mut id_mismatch = 0usize;
    for (p, (&g, &e)) in ids.iter().zip(&want.face_ids).enumerate() {
        let (gd, ed) = (depth[p], want.depth[p]);
        if g != i64::from(e) {
            id_mismatch += 1;
            continue;
        }
        let depth_ok = match agreement {
            Agreement::Exact => gd.to_bits() == ed.to_bits(),
            Agreement::Rounding { .. } if e < 0 => gd == f32::INFINITY,
            Agreement::Rounding { depth, .. } => (gd - ed).abs() <= depth * ed,
        };
        assert!(
            depth_ok,
            "{}: pixel ({}, {}) face {e}: depth {gd} vs reference {ed}",
            scene.name,
            p % w,
            p / w
        );
    }
    let vis_mismatch = got_vis
        .iter()
        .zip(&want_vis)
        .filter(|(g, e)| (**g == 1) != **e)
        .count();
    assert!(
        got_vis.iter().all(|&v| v == 0 || v == 1),
        "{}: visibility must be 0/1",
        scene.name
    );
    let covered = want.face_ids.iter().filter(|&&f| f >= 0).count();
    let allowed = match agreement {
        Agreement::Exact => 0,
        Agreement::Rounding { fraction, .. } => ((fraction * covered as f64) as usize).max(2),
    };
    eprintln!(
        "{}: {covered} covered pixels, {id_mismatch} face-id and {vis_mismatch} vertex \
         mismatches (allowed {allowed})",
        scene.name
    );
    assert!(
        id_mismatch <= allowed,
        "{}: {id_mismatch} of {} pixels differ from the reference (allowed {allowed})",
        scene.name,
        ids.len()
    );
    assert!(
        vis_mismatch <= allowed,
        "{}: {vis_mismatch} vertices' visibility differs from the reference (allowed {allowed})",
        scene.name
    );
}

#[test]
fn cpu_backends_run_the_reference_exactly() {
    for device in [
        Device::ndarray(),
        Device::flex(),
        Device::ndarray().autodiff(),
        Device::flex().autodiff(),
    ] {
        for scene in scenes() {
            assert_triangle_id_parity(&scene, &device, Agreement::Exact);
        }
    }
}

#[test]
fn wgpu_matches_the_cpu_reference() {
    let Some(device) = wgpu_test_device() else {
        return;
    };
    for scene in scenes() {
        assert_triangle_id_parity(&scene, &device, scene.gpu);
        // The autodiff wrapper forwards to the same kernels.
        assert_triangle_id_parity(&scene, &device.clone().autodiff(), scene.gpu);
    }
}

/// What the strict CPU entry point rejects, the op skips: out-of-range indices and non-finite
/// corners cover nothing, on every backend, and the other faces are unaffected.
#[test]
fn bad_faces_cover_nothing_on_every_backend() {
    let cam = pixel_camera(12, 12);
    let vertices = vec![
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::new(10.0, 1.0, 1.0),
        Vec3::new(1.0, 10.0, 1.0),
        Vec3::new(f32::NAN, 2.0, 1.0),
        Vec3::new(11.0, 11.0, 0.5),
    ];
    // Face 1 has a NaN corner, face 2 an index past the list; face 3 is in front of face 0.
    let faces = vec![[0, 1, 2], [0, 3, 1], [0, 1, 99], [1, 4, 2]];
    let clean_vertices: Vec<Vec3> = vertices
        .iter()
        .map(|v| if v.is_finite() { *v } else { Vec3::ZERO })
        .collect();
    let clean_faces = vec![[0, 1, 2], [0, 0, 0], [0, 0, 0], [1, 4, 2]];
    let want = rasterize_triangle_ids(&clean_vertices, &clean_faces, &cam).expect("reference");
    assert!(want.face_ids.contains(&0) && want.face_ids.contains(&3));
    let mut devices = vec![Device::ndarray(), Device::flex().autodiff()];
    devices.extend(wgpu_test_device());
    for device in devices {
        let got = rasterize_on_device(
            vertices_tensor(&vertices, &device),
            faces_tensor(&faces, &device),
            &cam,
        )
        .expect("shapes are valid");
        let ids = ints(got.face_ids.clone());
        let want_ids: Vec<i64> = want.face_ids.iter().map(|&f| i64::from(f)).collect();
        assert_eq!(ids, want_ids, "{device:?}");
        let vis = ints(got.visible_vertices(faces_tensor(&faces, &device), 5));
        assert_eq!(vis, [1, 1, 1, 0, 1], "{device:?}");
    }
}

#[test]
fn shape_errors_name_the_input() {
    let device = Device::ndarray();
    let cam = pixel_camera(4, 4);
    let v = Tensor::<2>::zeros([3, 2], &device);
    let f = faces_tensor(&[[0, 1, 2]], &device);
    let err = rasterize_on_device(v, f.clone(), &cam)
        .unwrap_err()
        .to_string();
    assert!(err.contains("vertices"), "{err}");
    let v = Tensor::<2>::zeros([3, 3], &device);
    let f4 = Tensor::<2, Int>::zeros([1, 4], &device);
    let err = rasterize_on_device(v, f4, &cam).unwrap_err().to_string();
    assert!(err.contains("faces"), "{err}");
}

/// `visibility_in_views` (every view in one set of launches on a CubeCL device) gives, view for
/// view, the flags of one view at a time on the same device: a vertex visible when
/// `visible_vertices` marks it, a face when its three corners are. The body template is posed
/// differently per view (each view's copy moved and scaled), seen from four sides, one close
/// enough to clip; `lowres` covers part of the vertices.
fn assert_views_at_once_match_one_at_a_time(device: &Device) {
    let body = BodyTemplate::load(lowres_template_path()).expect("template");
    let k_cam = Intrinsics {
        fx: 90.0,
        fy: 90.0,
        cx: 40.0,
        cy: 48.0,
    };
    let eyes = [
        Vec3::new(0.0, 0.2, 3.0),
        Vec3::new(3.0, 0.5, 0.0),
        Vec3::new(-2.0, -0.5, -2.0),
        Vec3::new(0.05, 0.3, 0.15),
    ];
    let cameras: Vec<Camera> = eyes
        .iter()
        .map(|&eye| {
            Camera::look_at(eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k_cam, 80, 96).expect("camera")
        })
        .collect();
    let posed: Vec<Vec<Vec3>> = (0..cameras.len())
        .map(|k| {
            let (shift, scale) = (
                Vec3::new(0.03 * k as f32, -0.02 * k as f32, 0.0),
                1.0 + 0.05 * k as f32,
            );
            body.vertices.iter().map(|&v| v * scale + shift).collect()
        })
        .collect();
    let n = cameras.len();
    let rows = body.vertices.len();
    let side_by_side: Vec<f32> = (0..rows)
        .flat_map(|v| posed.iter().flat_map(move |p| p[v].to_array()))
        .collect();
    let faces = faces_tensor(&body.topology.faces, device);
    let lowres = rows / 3;
    let views = ViewSet {
        cameras: cameras.clone(),
        lowres,
    };
    let got = visibility_in_views(
        Tensor::from_data(TensorData::new(side_by_side, [rows, 3 * n]), device),
        faces.clone(),
        &views,
    )
    .expect("valid views");
    assert_eq!(got.vertices.dims(), [lowres, n]);
    let num_faces = body.topology.faces.len();
    assert_eq!(got.faces.dims(), [num_faces, n]);
    let floats = |t: Tensor<2>| t.into_data().iter::<f32>().collect::<Vec<_>>();
    let (vertex_flags, face_flags) = (floats(got.vertices), floats(got.faces));
    let mut seen = [0usize; 2];
    for (k, camera) in cameras.iter().enumerate() {
        let ids = rasterize_on_device(vertices_tensor(&posed[k], device), faces.clone(), camera)
            .expect("valid view");
        let visible = ints(ids.visible_vertices(faces.clone(), rows));
        for v in 0..lowres {
            assert_eq!(
                vertex_flags[v * n + k],
                visible[v] as f32,
                "vertex {v}, view {k}"
            );
        }
        for (f, corners) in body.topology.faces.iter().enumerate() {
            let want = corners.iter().all(|&c| visible[c as usize] == 1);
            assert_eq!(
                face_flags[f * n + k],
                f32::from(u8::from(want)),
                "face {f}, view {k}"
            );
            seen[usize::from(want)] += 1;
        }
    }
    assert!(
        seen[0] > 0 && seen[1] > 0,
        "visible and hidden faces both occur: {seen:?}"
    );
}

#[test]
fn views_at_once_match_one_at_a_time() {
    let mut devices = vec![Device::ndarray(), Device::flex(), Device::flex().autodiff()];
    devices.extend(
        wgpu_test_device()
            .into_iter()
            .flat_map(|d| [d.clone(), d.autodiff()]),
    );
    for device in &devices {
        assert_views_at_once_match_one_at_a_time(device);
    }
}

/// A call without views, with cameras of two sizes, or with vertices that are not `3n` wide is
/// an error naming the input.
#[test]
fn views_at_once_name_bad_input() {
    let device = Device::ndarray();
    let faces = faces_tensor(&[[0, 1, 2]], &device);
    let views = |cameras: Vec<Camera>| ViewSet { cameras, lowres: 3 };
    let err = visibility_in_views(
        Tensor::zeros([3, 3], &device),
        faces.clone(),
        &views(vec![]),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("cameras"), "{err}");
    let two_sizes = views(vec![pixel_camera(4, 4), pixel_camera(4, 5)]);
    let err = visibility_in_views(Tensor::zeros([3, 6], &device), faces.clone(), &two_sizes)
        .unwrap_err()
        .to_string();
    assert!(err.contains("cameras") && err.contains("size"), "{err}");
    let two = views(vec![pixel_camera(4, 4), pixel_camera(4, 4)]);
    let err = visibility_in_views(Tensor::zeros([3, 3], &device), faces, &two)
        .unwrap_err()
        .to_string();
    assert!(err.contains("vertices"), "{err}");
}
