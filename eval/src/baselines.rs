//! Reconstructions without learning, to say what a trained model is worth (design.md §10.6).
//!
//! Both keep the canonical template (the subject's estimated shape) and the Gaussians' initial
//! geometry (the state a reconstructor starts from) and differ only in colour:
//!
//! - **Template, one colour** ([`template_one_colour`]): every Gaussian the mean colour of the
//!   source foreground, the best constant a template can have.
//! - **Projective texturing** ([`projective_texturing`]): each vertex of the subdivided mesh
//!   takes the colour of the source pixels it projects to, averaged over the views that see it
//!   (visibility from the triangle-ID raster, the test the reconstructor itself uses; pixels
//!   outside the source mask are not used); vertices no view sees take the mean of their seen
//!   neighbours, spread ring by ring over the mesh; each Gaussian takes the mean of its face's
//!   three corners. This is what "reading the photos" gives with no learning at all: a learned
//!   model that does not beat it has not learned to read them.

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_model::avatar::Avatar;
use lifegom_model::inputs::ModelInputs;
use lifegom_ops::sampling::project_points;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::readback;
use lifegom_render::skinning::skin_vertices;
use lifegom_render::visibility::rasterize_on_device;

use crate::error::EvalError;
use crate::evaluate::Reconstructed;

/// The avatar that keeps the template and the initial Gaussians, coloured `colors` `[F, 3]`.
fn template_avatar(mesh: &GomMesh, inputs: &ModelInputs, colors: Tensor<2>) -> Avatar {
    let device = colors.device();
    let mut params = GomParams::init(mesh.num_gaussians(), &device);
    params.colors = colors;
    Avatar::new(
        inputs.subject.canonical_vertices.clone(),
        params,
        inputs.subject.lbs_weights.clone(),
        inputs.subject.skeleton.clone(),
        mesh.clone(),
    )
}

/// Mean colour of the source foreground, `[3]`.
fn foreground_mean(inputs: &ModelInputs) -> Result<Tensor<1>, EvalError> {
    let mask = inputs.source_masks.clone();
    let count = readback::read::<f64, 1, _>("source mask area", mask.clone().sum())?[0].max(1.0);
    let fg = (inputs.sources.images.clone() * mask)
        .sum_dim(0)
        .sum_dim(2)
        .sum_dim(3)
        .reshape([3]);
    Ok(fg.div_scalar(count))
}

/// The template painted the mean source-foreground colour (module docs).
pub fn template_one_colour(
    mesh: &GomMesh,
    inputs: &ModelInputs,
    device: &Device,
) -> Result<Reconstructed, EvalError> {
    let start = std::time::Instant::now();
    let mean = foreground_mean(inputs)?;
    let colors = Tensor::<2>::zeros([mesh.num_gaussians(), 3], device) + mean.unsqueeze_dim(0);
    Ok(Reconstructed {
        avatar: template_avatar(mesh, inputs, colors),
        ms: start.elapsed().as_secs_f64() * 1e3,
    })
}

/// Bilinear sample of an `H×W` channel-planar image (`[C, H, W]` flattened) at pixel
/// coordinates `(x, y)` (pixel centres at integer + 0.5), clamped at the border.
fn bilinear(plane: &[f32], c: usize, w: usize, h: usize, x: f32, y: f32) -> f32 {
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (ax, ay) = (fx - x0, fy - y0);
    let at = |xi: f32, yi: f32| {
        let xi = (xi as i64).clamp(0, w as i64 - 1) as usize;
        let yi = (yi as i64).clamp(0, h as i64 - 1) as usize;
        plane[c * w * h + yi * w + xi]
    };
    (1.0 - ay) * ((1.0 - ax) * at(x0, y0) + ax * at(x0 + 1.0, y0))
        + ay * ((1.0 - ax) * at(x0, y0 + 1.0) + ax * at(x0 + 1.0, y0 + 1.0))
}

/// Fills the vertices without a colour from their neighbours, one ring per round; whatever the
/// rounds cannot reach (a component no view sees) takes `fallback`.
fn fill_unseen(
    colors: &mut [[f32; 3]],
    seen: &mut [bool],
    faces: &[[usize; 3]],
    fallback: [f32; 3],
) {
    let n = colors.len();
    let mut neighbours: Vec<Vec<usize>> = vec![Vec::new(); n];
    for f in faces {
        for k in 0..3 {
            neighbours[f[k]].push(f[(k + 1) % 3]);
            neighbours[f[k]].push(f[(k + 2) % 3]);
        }
    }
    for list in &mut neighbours {
        list.sort_unstable();
        list.dedup();
    }
    loop {
        let mut filled = Vec::new();
        for v in (0..n).filter(|&v| !seen[v]) {
            let known: Vec<usize> = neighbours[v].iter().copied().filter(|&u| seen[u]).collect();
            if !known.is_empty() {
                let mut c = [0.0; 3];
                for &u in &known {
                    for (ci, ui) in c.iter_mut().zip(colors[u]) {
                        *ci += ui / known.len() as f32;
                    }
                }
                filled.push((v, c));
            }
        }
        if filled.is_empty() {
            break;
        }
        for (v, c) in filled {
            colors[v] = c;
            seen[v] = true;
        }
    }
    for (c, s) in colors.iter_mut().zip(seen.iter()) {
        if !s {
            *c = fallback;
        }
    }
}

/// Projective texturing of the template (module docs).
pub fn projective_texturing(
    mesh: &GomMesh,
    inputs: &ModelInputs,
    device: &Device,
) -> Result<Reconstructed, EvalError> {
    let _span = tracing::debug_span!("projective_texturing").entered();
    let start = std::time::Instant::now();
    let sources = &inputs.sources;
    let [n, _, h, w] = sources.images.dims();
    let f = mesh.num_gaussians();
    let vh = mesh.subdivision.highres.num_vertices;
    let faces_flat = mesh.highres_faces().clone();
    let faces_hr = faces_flat.clone().reshape([f, 3]);
    let mut posed_hr = Vec::with_capacity(n);
    let mut visible = Vec::with_capacity(n);
    for (camera, skinning) in sources.cameras.iter().zip(&sources.skinning) {
        let posed = skin_vertices(
            inputs.subject.canonical_vertices.clone(),
            inputs.subject.lbs_weights.clone(),
            skinning,
        )?;
        let hr = mesh.tables().apply(posed);
        let ids = rasterize_on_device(hr.clone(), faces_hr.clone(), camera)?;
        visible.push(readback::read::<i64, 1, _>(
            "visible vertices",
            ids.visible_vertices(faces_hr.clone(), vh),
        )?);
        posed_hr.push(hr);
    }
    let uv = readback::read::<f32, 3, _>(
        "projected vertices",
        project_points(Tensor::stack(posed_hr, 0), &sources.cameras)
            .map_err(lifegom_model::error::ModelError::from)?
            .uv,
    )?;
    let images = readback::read::<f32, 4, _>("source images", sources.images.clone())?;
    let masks = readback::read::<f32, 4, _>("source masks", inputs.source_masks.clone())?;
    let mean = readback::read::<f32, 1, _>("foreground mean", foreground_mean(inputs)?)?;
    let fallback = [mean[0], mean[1], mean[2]];

    let mut sum = vec![[0.0f32; 3]; vh];
    let mut count = vec![0u32; vh];
    for view in 0..n {
        let image = &images[view * 3 * h * w..(view + 1) * 3 * h * w];
        let mask = &masks[view * h * w..(view + 1) * h * w];
        for v in 0..vh {
            if visible[view][v] == 0 {
                continue;
            }
            let (x, y) = (uv[(view * vh + v) * 2], uv[(view * vh + v) * 2 + 1]);
            if !(x >= 0.0 && y >= 0.0 && x < w as f32 && y < h as f32) {
                continue;
            }
            if bilinear(mask, 0, w, h, x, y) < 0.5 {
                continue;
            }
            for (c, s) in sum[v].iter_mut().enumerate() {
                *s += bilinear(image, c, w, h, x, y);
            }
            count[v] += 1;
        }
    }
    let mut colors: Vec<[f32; 3]> = sum
        .iter()
        .zip(&count)
        .map(|(s, &k)| s.map(|v| v / k.max(1) as f32))
        .collect();
    let mut seen: Vec<bool> = count.iter().map(|&k| k > 0).collect();
    let faces: Vec<[usize; 3]> = readback::read::<i64, 1, _>("faces", faces_flat)?
        .chunks_exact(3)
        .map(|c| [c[0] as usize, c[1] as usize, c[2] as usize])
        .collect();
    fill_unseen(&mut colors, &mut seen, &faces, fallback);
    let colors = &colors;
    let face_colors: Vec<f32> = faces
        .iter()
        .flat_map(|t| (0..3).map(move |c| t.iter().map(|&v| colors[v][c]).sum::<f32>() / 3.0))
        .collect();
    let colors = Tensor::<2>::from_data(TensorData::new(face_colors, [f, 3]), device);
    Ok(Reconstructed {
        avatar: template_avatar(mesh, inputs, colors),
        ms: start.elapsed().as_secs_f64() * 1e3,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_interpolates_between_pixel_centres() {
        // 2×1 image, one channel: 0 at x=0.5, 1 at x=1.5.
        let plane = [0.0, 1.0];
        assert_eq!(bilinear(&plane, 0, 2, 1, 0.5, 0.5), 0.0);
        assert_eq!(bilinear(&plane, 0, 2, 1, 1.5, 0.5), 1.0);
        assert!((bilinear(&plane, 0, 2, 1, 1.0, 0.5) - 0.5).abs() < 1e-6);
        // Clamped beyond the border.
        assert_eq!(bilinear(&plane, 0, 2, 1, 9.0, 0.5), 1.0);
    }

    #[test]
    fn unseen_vertices_take_their_seen_neighbours_colour_ring_by_ring() {
        // A strip of triangles 0-1-2, 1-2-3, 2-3-4, and an isolated triangle 5-6-7.
        let faces = [[0, 1, 2], [1, 2, 3], [2, 3, 4], [5, 6, 7]];
        let mut colors = vec![[0.0; 3]; 8];
        colors[0] = [1.0, 0.0, 0.0];
        colors[1] = [0.0, 1.0, 0.0];
        let mut seen = vec![false; 8];
        seen[0] = true;
        seen[1] = true;
        fill_unseen(&mut colors, &mut seen, &faces, [0.5, 0.5, 0.5]);
        assert_eq!(colors[2], [0.5, 0.5, 0.0]); // ring 1: neighbours 0 and 1
        assert_eq!(colors[3], [0.0, 1.0, 0.0]); // ring 1: only 1 was seen
        assert_eq!(colors[4], [0.25, 0.75, 0.0]); // ring 2: neighbours 2 and 3
        assert!(seen[..5].iter().all(|&s| s), "the strip is reached");
        assert!(!seen[6], "the isolated triangle is not");
        assert_eq!(colors[6], [0.5, 0.5, 0.5]); // unreachable: the fallback
    }
}
