//! Text in pictures: DejaVu Sans, anti-aliased, at one of two sizes. The font is embedded by
//! the `dejavu` crate, so no font file or system library is involved.

use std::sync::OnceLock;

use ab_glyph::{Font, FontRef, PxScale, ScaleFont};

use crate::visuals::Picture;

/// The size of labels and tick labels, and of titles, in pixels (the font's height).
pub const LABEL: f32 = 15.0;
pub const TITLE: f32 = 18.0;

fn font() -> &'static FontRef<'static> {
    static FONT: OnceLock<FontRef<'static>> = OnceLock::new();
    FONT.get_or_init(|| {
        FontRef::try_from_slice(dejavu::sans::regular()).expect("DejaVu Sans parses")
    })
}

/// The height of a line of text at `size`, in pixels.
pub fn line_height(size: f32) -> i64 {
    let font = font().as_scaled(PxScale::from(size));
    (font.ascent() - font.descent()).ceil() as i64
}

/// The height of the font's tallest letters above the baseline at `size`, in pixels.
pub fn ascent(size: f32) -> i64 {
    font().as_scaled(PxScale::from(size)).ascent().round() as i64
}

/// Each glyph of `text` at `scale` with its pen position along the line, kerned, and the
/// pen's position after the last one (the line's advance).
fn layout(text: &str, scale: PxScale) -> (Vec<(ab_glyph::GlyphId, f32)>, f32) {
    let font = font().as_scaled(scale);
    let mut glyphs = Vec::with_capacity(text.len());
    let mut caret = 0.0f32;
    let mut previous = None;
    for c in text.chars() {
        let id = font.glyph_id(c);
        if let Some(p) = previous {
            caret += font.kern(p, id);
        }
        glyphs.push((id, caret));
        caret += font.h_advance(id);
        previous = Some(id);
    }
    (glyphs, caret)
}

/// The width of `text` at `size`, in pixels.
pub fn width(text: &str, size: f32) -> i64 {
    layout(text, PxScale::from(size)).1.ceil() as i64
}

/// Draws `text` at `size` with its top-left corner at `(x, y)`; `vertical` writes it bottom
/// to top with that corner at its bottom-left.
pub fn draw(
    picture: &mut Picture,
    x: i64,
    y: i64,
    text: &str,
    colour: [u8; 3],
    size: f32,
    vertical: bool,
) {
    let scale = PxScale::from(size);
    let ascent = font().as_scaled(scale).ascent();
    for (id, caret) in layout(text, scale).0 {
        let glyph = id.with_scale_and_position(scale, ab_glyph::point(caret, ascent));
        let Some(outline) = font().outline_glyph(glyph) else {
            continue;
        };
        let bounds = outline.px_bounds();
        outline.draw(|gx, gy, coverage| {
            let (u, v) = (
                bounds.min.x as i64 + gx as i64,
                bounds.min.y as i64 + gy as i64,
            );
            if vertical {
                picture.blend(x + v, y - u, colour, coverage);
            } else {
                picture.blend(x + u, y + v, colour, coverage);
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Text leaves anti-aliased ink inside the box its width and line height give.
    #[test]
    fn text_stays_inside_its_measured_box() {
        let mut picture = Picture::blank(200, 40, [255, 255, 255]);
        let (w, h) = (width("Frame 12 (dB)", LABEL), line_height(LABEL));
        draw(&mut picture, 5, 5, "Frame 12 (dB)", [0, 0, 0], LABEL, false);
        let mut inked = 0;
        let mut grey = 0;
        for y in 0..40i64 {
            for x in 0..200i64 {
                let at = ((y * 200 + x) * 3) as usize;
                let v = picture.pixels[at];
                if v < 255 {
                    inked += 1;
                    assert!(
                        (5..=5 + w).contains(&x) && (5..=5 + h).contains(&y),
                        "ink at ({x}, {y}) outside {w}x{h}"
                    );
                }
                if v > 0 && v < 255 {
                    grey += 1;
                }
            }
        }
        assert!(inked > 100 && grey > 20, "{inked} inked, {grey} partly");
        assert!(width("WWW", LABEL) > width("iii", LABEL));
    }
}
