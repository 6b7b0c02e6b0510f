//! Pictures of the grids: the middle z slice of the density (grey) and of the speed of one or
//! more velocities (viridis), as labelled panels with colour bars in the grids' units. A video
//! of slices takes one [`SliceScale`] over all its frames, so frames can be compared; the
//! figure says which scale it uses.

use gausmoke_model::GridSpec;

use crate::text;
use crate::viridis::viridis;
use crate::visuals::Picture;

/// The middle z slice of a grid's density and of the speed of each of its velocities, row by
/// row from y = 0: `density[j * nx + i]` is cell (i, j, nz / 2).
#[derive(Debug, Clone, PartialEq)]
pub struct GridSlice {
    pub nx: usize,
    pub ny: usize,
    /// Which z layer, of how many.
    pub layer: [usize; 2],
    pub density: Vec<f32>,
    pub speeds: Vec<Vec<f32>>,
}

impl GridSlice {
    /// The middle z slice of `density` (`[nx, ny, nz]`, z fastest) and of the speed of each
    /// of `velocities` (`[nx, ny, nz, 3]`).
    pub fn middle(grid: &GridSpec, density: &[f32], velocities: &[&[f32]]) -> Self {
        let [nx, ny, nz] = grid.resolution();
        let k = nz / 2;
        let cells = || (0..ny).flat_map(move |j| (0..nx).map(move |i| (i * ny + j) * nz + k));
        let speed = |velocity: &[f32], c: usize| {
            (velocity[3 * c].powi(2) + velocity[3 * c + 1].powi(2) + velocity[3 * c + 2].powi(2))
                .sqrt()
        };
        Self {
            nx,
            ny,
            layer: [k, nz],
            density: cells().map(|c| density[c]).collect(),
            speeds: velocities
                .iter()
                .map(|v| cells().map(|c| speed(v, c)).collect())
                .collect(),
        }
    }
}

/// The top of the density's and of the speed's colour scales.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SliceScale {
    pub density: f32,
    pub speed: f32,
}

impl SliceScale {
    /// The largest density and speed over `slices` (tiny positive values when all are 0).
    pub fn over<'a>(slices: impl IntoIterator<Item = &'a GridSlice>) -> Self {
        let mut scale = Self {
            density: 1e-12,
            speed: 1e-12,
        };
        for slice in slices {
            scale.density = slice.density.iter().fold(scale.density, |m, &v| m.max(v));
            for speeds in &slice.speeds {
                scale.speed = speeds.iter().fold(scale.speed, |m, &v| m.max(v));
            }
        }
        scale
    }

    /// The note of a video's slices drawn on this one scale.
    pub fn video_note(&self) -> String {
        format!(
            "colour scales: one for the whole video (density 0-{:.3}, speed 0-{:.4})",
            self.density, self.speed
        )
    }
}

const MARGIN: i64 = 14;
const GAP: i64 = 14;
const BAR: i64 = 14;
const INK: [u8; 3] = [30, 30, 30];

/// A number for a colour bar's tick: three significant digits.
fn tick(v: f32) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e4).contains(&a) {
        return format!("{v:.2e}");
    }
    let decimals = (2 - a.log10().floor() as i32).max(0) as usize;
    format!("{v:.decimals$}")
}

/// A horizontal colour bar `width` wide at `(x, y)`, coloured by `colour(t)` for t in [0, 1],
/// with ticks at 0, half and `top`, and `title` under them.
fn colour_bar(
    picture: &mut Picture,
    (x, y): (i64, i64),
    width: i64,
    top: f32,
    title: &str,
    colour: impl Fn(f32) -> [u8; 3],
) {
    for dx in 0..width {
        let c = colour(dx as f32 / (width - 1).max(1) as f32);
        for dy in 0..BAR {
            picture.put(x + dx, y + dy, c);
        }
    }
    let line = text::line_height(text::LABEL);
    for (share, value) in [(0.0, 0.0), (0.5, 0.5 * top), (1.0, top)] {
        let at = x + ((width - 1) as f32 * share) as i64;
        for dy in BAR..BAR + 4 {
            picture.put(at, y + dy, INK);
        }
        let label = tick(value);
        let w = text::width(&label, text::LABEL);
        let left = (at - w / 2).clamp(x, x + width - w);
        text::draw(picture, left, y + BAR + 5, &label, INK, text::LABEL, false);
    }
    let w = text::width(title, text::LABEL);
    text::draw(
        picture,
        x + (width - w) / 2,
        y + BAR + 7 + line,
        title,
        INK,
        text::LABEL,
        false,
    );
}

/// Frame `frame`'s slice as a figure: a title naming the frame and layer, a panel per field
/// labelled by `labels` (the density's, then each speed's), about 256 pixels across with +y
/// up, a grey bar under the density and one viridis bar under the speeds, both from 0 to
/// `scale`, and `note` (which scale this is, e.g. [`SliceScale::video_note`]) at the bottom.
pub fn figure(
    frame: usize,
    slice: &GridSlice,
    scale: &SliceScale,
    labels: &[&str],
    note: &str,
) -> Picture {
    let [k, nz] = slice.layer;
    let title = format!("frame {frame}: middle z slice (layer {k} of {nz}), +y up");
    let cell = (256 / slice.nx.max(slice.ny)).max(1) as i64;
    let (pw, ph) = (slice.nx as i64 * cell, slice.ny as i64 * cell);
    let panels = 1 + slice.speeds.len() as i64;
    let line = text::line_height(text::LABEL);
    let title_height = text::line_height(text::TITLE);
    let width = 2 * MARGIN + panels * pw + (panels - 1) * GAP;
    let panel_top = MARGIN + title_height + 8 + line + 4;
    let bar_top = panel_top + ph + 10;
    let height = bar_top + BAR + 7 + 2 * line + 10 + line + MARGIN;
    let mut picture = Picture::blank(width.max(1) as u32, height as u32, [255, 255, 255]);
    text::draw(
        &mut picture,
        MARGIN,
        MARGIN,
        &title,
        INK,
        text::TITLE,
        false,
    );
    let left_of = |p: i64| MARGIN + p * (pw + GAP);
    for (p, label) in labels.iter().enumerate().take(panels as usize) {
        text::draw(
            &mut picture,
            left_of(p as i64),
            panel_top - line - 4,
            label,
            INK,
            text::LABEL,
            false,
        );
    }
    let (nx, ny) = (slice.nx as i64, slice.ny as i64);
    for y in 0..ph {
        for x in 0..pw {
            let (i, j) = (x / cell, ny - 1 - y / cell);
            let at = (j * nx + i) as usize;
            let d = (slice.density[at] / scale.density).clamp(0.0, 1.0);
            let grey = (d * 255.0).round() as u8;
            picture.put(left_of(0) + x, panel_top + y, [grey, grey, grey]);
            for (p, speeds) in slice.speeds.iter().enumerate() {
                let colour = viridis(speeds[at] / scale.speed);
                picture.put(left_of(p as i64 + 1) + x, panel_top + y, colour);
            }
        }
    }
    colour_bar(
        &mut picture,
        (left_of(0), bar_top),
        pw,
        scale.density,
        "density (model units)",
        |t| {
            let g = (t * 255.0).round() as u8;
            [g, g, g]
        },
    );
    if !slice.speeds.is_empty() {
        let span = (panels - 1) * pw + (panels - 2) * GAP;
        colour_bar(
            &mut picture,
            (left_of(1), bar_top),
            span,
            scale.speed,
            "speed (world units / frame)",
            viridis,
        );
    }
    text::draw(
        &mut picture,
        MARGIN,
        height - MARGIN - line,
        note,
        [90, 90, 90],
        text::LABEL,
        false,
    );
    picture
}

#[cfg(test)]
mod tests {
    use gausmoke_core::glam::Vec3;

    use super::*;

    /// One scale over several slices is the largest of them; the figure draws each field in
    /// its panel with +y up, and its colour bars run from black to white and along viridis.
    #[test]
    fn slices_share_one_scale_and_are_drawn_with_their_bars() {
        let grid = GridSpec::new(Vec3::ZERO, Vec3::ONE, [4, 4, 4], 1).unwrap();
        let cells = 64;
        let mut density = vec![0.0f32; cells];
        // Cell (1, 3, 2): high up in the middle layer.
        density[(4 + 3) * 4 + 2] = 2.0;
        let mut velocity = vec![0.0f32; 3 * cells];
        velocity[3 * ((4 + 3) * 4 + 2) + 1] = 0.5;
        let first = GridSlice::middle(&grid, &density, &[&velocity]);
        assert_eq!(first.density[3 * 4 + 1], 2.0);
        assert_eq!(first.speeds[0][3 * 4 + 1], 0.5);
        let second = GridSlice::middle(&grid, &vec![1.0; cells], &[&vec![0.1; 3 * cells]]);
        let scale = SliceScale::over([&first, &second]);
        assert_eq!(scale.density, 2.0);
        assert_eq!(scale.speed, 0.5);
        // A 4x4 slice's panels are 256 pixels across: 64 pixels a cell.
        let picture = figure(
            3,
            &first,
            &scale,
            &["density", "speed"],
            "one scale for the whole video",
        );
        let at = |x: i64, y: i64| {
            let i = ((y * i64::from(picture.width) + x) * 3) as usize;
            [
                picture.pixels[i],
                picture.pixels[i + 1],
                picture.pixels[i + 2],
            ]
        };
        let line = text::line_height(text::LABEL);
        let panel_top = MARGIN + text::line_height(text::TITLE) + 8 + line + 4;
        // Cell (1, 3) is in the top row of the panels: white density, the top of viridis.
        assert_eq!(at(MARGIN + 96, panel_top + 32), [255, 255, 255]);
        assert_eq!(at(MARGIN + 256 + GAP + 96, panel_top + 32), viridis(1.0));
        assert_eq!(at(MARGIN + 96, panel_top + 224), [0, 0, 0]);
        // The bars' ends.
        let bar = panel_top + 256 + 10 + BAR / 2;
        assert_eq!(at(MARGIN, bar), [0, 0, 0]);
        assert_eq!(at(MARGIN + 255, bar), [255, 255, 255]);
        assert_eq!(at(MARGIN + 256 + GAP + 255, bar), viridis(1.0));
        assert_eq!(tick(0.5), "0.500");
        assert_eq!(tick(12.345), "12.3");
    }
}
