//! What a loaded data set contains, in words and as a contact sheet (issue 7, item 3; the CLI
//! command itself belongs to `gausmoke-train`, the example `inspect` wraps this).

use std::fmt::Write as _;

use gausmoke_core::Camera;
use gausmoke_core::glam::Vec3;

use crate::dataset::{Aabb, Dataset};
use crate::image::Image;

/// A few lines: format, views (split, frame count, resolution, camera position), times,
/// background and box.
pub fn summary(ds: &Dataset) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "{:?} data set from {}", ds.format, ds.source.display());
    let _ = writeln!(
        s,
        "{} views, {} distinct times{}",
        ds.views.len(),
        ds.times.len(),
        match (ds.times.first(), ds.times.last()) {
            (Some(a), Some(b)) => format!(" in [{a}, {b}]"),
            _ => String::new(),
        }
    );
    for v in &ds.views {
        let (res, pos) = v
            .frames
            .first()
            .map(|f| {
                (
                    format!("{}x{}", f.camera.width(), f.camera.height()),
                    format!("{:.3}", f.camera.position()),
                )
            })
            .unwrap_or_else(|| ("-".into(), "-".into()));
        let _ = writeln!(
            s,
            "  {:<10} {:?}: {} frames at {res}, first camera at {pos}",
            v.name,
            v.split,
            v.frames.len()
        );
    }
    let _ = writeln!(s, "background {:?}", ds.background);
    match ds.bbox {
        Some(b) => {
            let _ = writeln!(s, "smoke box {:.3} .. {:.3}", b.min, b.max);
        }
        None => {
            let _ = writeln!(s, "no smoke box in this format");
        }
    }
    s
}

/// Rows = views, columns = first, middle and last loaded frame, with the smoke box's edges
/// drawn in red. `None` when no frame is loaded.
pub fn contact_sheet(ds: &Dataset) -> Option<Image> {
    let cell_w = ds
        .views
        .iter()
        .flat_map(|v| &v.frames)
        .map(|f| f.image.width())
        .max()?;
    let cell_h = ds
        .views
        .iter()
        .flat_map(|v| &v.frames)
        .map(|f| f.image.height())
        .max()?;
    let (sheet_w, sheet_h) = (cell_w as usize * 3, cell_h as usize * ds.views.len());
    let mut data = vec![0.0f32; sheet_w * sheet_h * 3];
    for (r, view) in ds.views.iter().enumerate() {
        let n = view.frames.len();
        if n == 0 {
            continue;
        }
        for (c, t) in [0, n / 2, n - 1].into_iter().enumerate() {
            let frame = &view.frames[t];
            let mut img = frame.image.data().to_vec();
            let (w, h) = (frame.image.width() as usize, frame.image.height() as usize);
            if let Some(b) = ds.bbox {
                draw_box(&mut img, w, h, &frame.camera, &b);
            }
            for y in 0..h {
                let dst = ((r * cell_h as usize + y) * sheet_w + c * cell_w as usize) * 3;
                data[dst..dst + w * 3].copy_from_slice(&img[y * w * 3..(y + 1) * w * 3]);
            }
        }
    }
    Image::from_vec(sheet_w as u32, sheet_h as u32, data)
}

fn draw_box(img: &mut [f32], w: usize, h: usize, cam: &Camera, b: &Aabb) {
    let corners = b.corners();
    let edges = [
        (0, 1),
        (2, 3),
        (4, 5),
        (6, 7),
        (0, 2),
        (1, 3),
        (4, 6),
        (5, 7),
        (0, 4),
        (1, 5),
        (2, 6),
        (3, 7),
    ];
    let samples = 4 * (w + h);
    for (a, e) in edges {
        let (p, q): (Vec3, Vec3) = (corners[a], corners[e]);
        for k in 0..=samples {
            let x = p.lerp(q, k as f32 / samples as f32);
            if let Some(px) = cam.project(x)
                && px.x >= 0.0
                && px.y >= 0.0
                && (px.x as usize) < w
                && (px.y as usize) < h
            {
                let i = (px.y as usize * w + px.x as usize) * 3;
                img[i..i + 3].copy_from_slice(&[1.0, 0.0, 0.0]);
            }
        }
    }
}
