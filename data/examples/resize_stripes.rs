//! A picture of what shrinking does to fine detail: a zone plate (rings whose frequency rises
//! to the pixel limit) and fine stripes, shrunk 4× by the reference's `cv2.resize` rule and by
//! the default anti-aliased rule (design.md §8.3), shown at the original size side by side.
//!
//! ```text
//! cargo run --release -p lifegom-data --example resize_stripes -- docs/resize-stripes.png
//! ```

use lifegom_data::preprocess::{FloatImage, Kernel, ResizeMode, resize};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "resize-stripes.png".into());
    let n = 256u32;
    // Left half: a zone plate, cos(π r² / n); right half: stripes of period 3 px.
    let data: Vec<f32> = (0..n * n)
        .flat_map(|i| {
            let (x, y) = ((i % n) as f32, (i / n) as f32);
            let v = if x < n as f32 / 2.0 {
                let (dx, dy) = (x - n as f32 / 4.0, y - n as f32 / 2.0);
                0.5 + 0.5 * (std::f32::consts::PI * (dx * dx + dy * dy) / n as f32).cos()
            } else if (i % n).is_multiple_of(3) {
                1.0
            } else {
                0.0
            };
            [v * 255.0; 3]
        })
        .collect();
    let src = FloatImage {
        width: n,
        height: n,
        channels: 3,
        data,
    };
    let small = |mode| resize(&src, n / 4, n / 4, Kernel::Lanczos4, mode);
    let panels = [
        src.clone(),
        small(ResizeMode::Reference),
        small(ResizeMode::AntiAliased),
    ];
    let gap = 8u32;
    let (w, h) = (3 * n + 2 * gap, n);
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    for (k, p) in panels.iter().enumerate() {
        let f = n / p.width; // shown at the original size, each pixel a square
        for y in 0..n {
            for x in 0..n {
                let v = p.data[(((y / f) * p.width + x / f) * 3) as usize];
                let o = ((y * w + k as u32 * (n + gap) + x) * 3) as usize;
                rgb[o..o + 3].fill(v.round().clamp(0.0, 255.0) as u8);
            }
        }
    }
    image::save_buffer(&out, &rgb, w, h, image::ExtendedColorType::Rgb8)?;
    println!("wrote {out}: original | reference (cv2.resize) 4× smaller | anti-aliased 4× smaller");
    Ok(())
}
