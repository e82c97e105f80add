//! A picture of what was estimated, for a person to look at: the photo, the mask's edge, and the
//! landmarks joined as a skeleton (bright where the model calls them visible, dark where not).

use glam::Vec2;
use image::{Rgb, RgbImage};

use crate::person::Person;

/// BlazePose's skeleton: pairs of landmark indices.
const BONES: [(usize, usize); 35] = [
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 7),
    (0, 4),
    (4, 5),
    (5, 6),
    (6, 8),
    (9, 10),
    (11, 12),
    (11, 13),
    (13, 15),
    (15, 17),
    (15, 19),
    (15, 21),
    (17, 19),
    (12, 14),
    (14, 16),
    (16, 18),
    (16, 20),
    (16, 22),
    (18, 20),
    (11, 23),
    (12, 24),
    (23, 24),
    (23, 25),
    (24, 26),
    (25, 27),
    (26, 28),
    (27, 29),
    (28, 30),
    (29, 31),
    (30, 32),
    (27, 31),
    (28, 32),
];

/// Landmarks below this visibility are drawn dark.
const VISIBLE: f32 = 0.5;

/// The photo with the person's mask edge (yellow) and skeleton (left side cyan, right side
/// magenta; dark where not visible) drawn over it.
pub fn draw(photo: &RgbImage, person: &Person) -> RgbImage {
    let mut out = photo.clone();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    let mask = &person.pose.mask;
    let inside = |x: usize, y: usize| mask[y * w + x] >= 0.5;
    for y in 0..h {
        for x in 0..w {
            if !inside(x, y) {
                continue;
            }
            let edge = x == 0
                || y == 0
                || x + 1 == w
                || y + 1 == h
                || !inside(x - 1, y)
                || !inside(x + 1, y)
                || !inside(x, y - 1)
                || !inside(x, y + 1);
            if edge {
                out.put_pixel(x as u32, y as u32, Rgb([255, 230, 0]));
            }
        }
    }
    let lm = &person.pose.landmarks;
    // Odd landmarks are the person's left side in BlazePose's numbering.
    let colour = |a: usize, b: usize| {
        let visible = lm[a].visibility >= VISIBLE && lm[b].visibility >= VISIBLE;
        let left = |k: usize| !k.is_multiple_of(2);
        let right = |k: usize| k > 0 && k.is_multiple_of(2);
        let base = if left(a) && left(b) {
            [0u8, 230, 255]
        } else if right(a) && right(b) {
            [255, 60, 220]
        } else {
            [255, 255, 255]
        };
        Rgb(if visible { base } else { base.map(|c| c / 3) })
    };
    for (a, b) in BONES {
        line(&mut out, lm[a].pixel, lm[b].pixel, colour(a, b));
    }
    for (k, l) in lm.iter().enumerate() {
        dot(&mut out, l.pixel, colour(k, k));
    }
    out
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && x < i64::from(img.width()) && y < i64::from(img.height()) {
        img.put_pixel(x as u32, y as u32, c);
    }
}

fn line(img: &mut RgbImage, a: Vec2, b: Vec2, c: Rgb<u8>) {
    let steps = (b - a).abs().max_element().ceil().clamp(1.0, 1e5) as usize;
    for i in 0..=steps {
        let p = a + (b - a) * (i as f32 / steps as f32);
        put(img, p.x.round() as i64, p.y.round() as i64, c);
    }
}

fn dot(img: &mut RgbImage, p: Vec2, c: Rgb<u8>) {
    let (x, y) = (p.x.round() as i64, p.y.round() as i64);
    for dy in -2..=2 {
        for dx in -2..=2 {
            if dx * dx + dy * dy <= 5 {
                put(img, x + dx, y + dy, c);
            }
        }
    }
}
