//! A picture of what `[synthetic.stream_variety] prints = "more"` changes (design.md §8.11):
//! the first view of stream subjects drawn with the split's prints (top row) and with the extra
//! prints (bottom row), the same people, cameras and lights; only re-drawn garments differ.
//!
//! ```text
//! cargo run --release -p lifegom-data --example stream_prints -- configs/prints-trial.toml docs/stream-prints.png
//! ```

use std::path::Path;

use lifegom_data::config::ConfigFile;
use lifegom_data::synth::{self, StreamPrints};
use lifegom_render::template::BodyTemplate;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let config = args
        .next()
        .unwrap_or_else(|| "configs/prints-trial.toml".into());
    let out = args.next().unwrap_or_else(|| "stream-prints.png".into());
    let file = ConfigFile::load(Path::new(&config))?;
    let more = file
        .synthetic
        .ok_or_else(|| format!("{config}: no [synthetic] table"))?;
    let variety = more
        .stream_variety
        .ok_or_else(|| format!("{config}: no [synthetic.stream_variety] table"))?;
    let split = synth::SynthConfig {
        stream_variety: Some(synth::StreamVariety {
            prints: StreamPrints::Split,
            ..variety
        }),
        ..more.clone()
    };
    let template = BodyTemplate::load(more.template.path())?;
    // Subjects whose garments the extra prints re-draw, from the first 40 of the stream.
    let (columns, mut pairs) = (8, Vec::new());
    for index in 0..40 {
        let draw = |cfg| {
            synth::generate_subject_frames(&template, cfg, more.seed, index, "x", None, Some(&[0]))
        };
        let (a, b) = (draw(&split)?, draw(&more)?);
        let (fa, fb) = (&a.frames[0], &b.frames[0]);
        if fa.rgb != fb.rgb {
            pairs.push((fa.rgb.clone(), fb.rgb.clone()));
        }
        if pairs.len() == columns {
            break;
        }
    }
    let n = more.image_size;
    let (w, h) = (columns as u32 * n, 2 * n);
    let mut rgb = vec![255u8; (w * h * 3) as usize];
    for (c, (top, bottom)) in pairs.iter().enumerate() {
        for (r, img) in [top, bottom].into_iter().enumerate() {
            for y in 0..n {
                let src = (y * n * 3) as usize;
                let dst = (((r as u32 * n + y) * w + c as u32 * n) * 3) as usize;
                rgb[dst..dst + (n * 3) as usize].copy_from_slice(&img[src..src + (n * 3) as usize]);
            }
        }
    }
    image::save_buffer(&out, &rgb, w, h, image::ExtendedColorType::Rgb8)?;
    println!(
        "wrote {out}: {} stream subjects, the split's prints (top) and the extra prints (bottom)",
        pairs.len()
    );
    Ok(())
}
