//! 3D convolution on host slices by im2col and matrix products (the `gemm` crate), for the CPU
//! backends: the forward pass, its adjoint (the gradient with respect to the input, which is
//! also the transposed convolution) and the gradient with respect to the weights.
//!
//! One image (batch 1), no dilation, no groups: what the U-Net uses. With `K = C_in k^3` and
//! `N` output cells, the input unfolds into `Col [K, N]` (`im2col`) and
//!
//! * forward: `Y [C_out, N] = W [C_out, K] Col`;
//! * weight gradient: `dW = dY Col^T`;
//! * adjoint: `dCol = W^T dY`, folded back onto the input (`col2im`).
//!
//! `N` is processed in tiles of about 256 KiB of `Col`, so `Col` never exists whole (at 64^3
//! with 16 channels it would be 450 MB) and each tile stays in cache from `im2col` to the
//! product. Tiles are the parallel unit (one `gemm` per tile, on one thread); every sum runs
//! in an order fixed by the shapes alone, so results are bit-for-bit reproducible on any
//! number of threads.

use rayon::prelude::*;

/// Shapes of one convolution: `input [C_in, D, H, W]`, `weight [C_out, C_in, k...]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvGeometry {
    pub channels_in: usize,
    pub channels_out: usize,
    pub input: [usize; 3],
    pub kernel: [usize; 3],
    pub stride: [usize; 3],
    pub padding: [usize; 3],
}

impl ConvGeometry {
    /// Output cells per axis.
    pub fn output(&self) -> [usize; 3] {
        [0, 1, 2]
            .map(|a| (self.input[a] + 2 * self.padding[a] - self.kernel[a]) / self.stride[a] + 1)
    }

    pub fn input_cells(&self) -> usize {
        self.input.iter().product()
    }

    pub fn output_cells(&self) -> usize {
        self.output().iter().product()
    }

    /// Rows of `Col`: `C_in * kd * kh * kw`.
    pub fn patch(&self) -> usize {
        self.channels_in * self.kernel.iter().product::<usize>()
    }

    fn check(&self) {
        for a in 0..3 {
            assert!(
                self.kernel[a] >= 1
                    && self.stride[a] >= 1
                    && self.input[a] + 2 * self.padding[a] >= self.kernel[a],
                "convolution geometry {self:?} is empty"
            );
        }
    }

    /// Output cells per tile: a `Col` tile of about 256 KiB, so that it stays in a core's
    /// cache between being written by `im2col` and read by the product.
    fn tile(&self) -> usize {
        (TILE_FLOATS / self.patch().max(1)).max(MIN_TILE_CELLS)
    }

    /// Whether the gradient with respect to the input is itself a stride-1 convolution of the
    /// output gradient (with the kernel flipped and its channel axes swapped).
    fn adjoint_is_a_convolution(&self) -> bool {
        (0..3).all(|a| self.stride[a] == 1 && self.padding[a] < self.kernel[a])
    }

    /// The stride-1 convolution that computes the adjoint: from the output grid back to the
    /// input grid, padded by `k - 1 - p`.
    fn flipped(&self) -> ConvGeometry {
        ConvGeometry {
            channels_in: self.channels_out,
            channels_out: self.channels_in,
            input: self.output(),
            kernel: self.kernel,
            stride: [1; 3],
            padding: [0, 1, 2].map(|a| self.kernel[a] - 1 - self.padding[a]),
        }
    }
}

/// Floats in one `Col` tile (256 KiB).
const TILE_FLOATS: usize = 1 << 16;
/// Fewest output cells per tile, so that each product still has a long side.
const MIN_TILE_CELLS: usize = 64;
/// Tiles whose weight-gradient products one task sums before the partial sums are added in
/// order. A constant, so the order of every sum is the same on any number of threads.
const TILES_PER_PARTIAL: usize = 8;
/// Tiles of `W^T dY` formed at once by the general adjoint (about 16 MiB).
const ADJOINT_BATCH_TILES: usize = 64;

/// A matrix view into a slice: element `(r, c)` at `offset + r * row_stride + c * col_stride`.
#[derive(Clone, Copy)]
struct View<'a> {
    data: &'a [f32],
    offset: usize,
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a> View<'a> {
    fn row_major(data: &'a [f32], rows: usize, cols: usize) -> Self {
        Self {
            data,
            offset: 0,
            rows,
            cols,
            row_stride: cols,
            col_stride: 1,
        }
    }

    fn transpose(self) -> Self {
        Self {
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            ..self
        }
    }

    /// Columns `start..start + len`.
    fn columns(self, start: usize, len: usize) -> Self {
        Self {
            offset: self.offset + start * self.col_stride,
            cols: len,
            ..self
        }
    }

    /// Whether every element lies inside the slice.
    fn in_bounds(&self) -> bool {
        self.rows == 0
            || self.cols == 0
            || self.offset + (self.rows - 1) * self.row_stride + (self.cols - 1) * self.col_stride
                < self.data.len()
    }
}

/// `dst[:, columns] (= or +=) lhs rhs`, where `dst` is row-major `[rows, dst_cols]` and the
/// product is written into its columns `column..column + rhs.cols`.
fn matmul_into(
    dst: &mut [f32],
    dst_cols: usize,
    column: usize,
    lhs: View,
    rhs: View,
    accumulate: bool,
) {
    let (m, k, n) = (lhs.rows, lhs.cols, rhs.cols);
    assert_eq!(k, rhs.rows, "inner dimensions");
    assert!(
        lhs.in_bounds() && rhs.in_bounds(),
        "operands inside their slices"
    );
    assert!(
        m == 0 || n == 0 || (m - 1) * dst_cols + column + n <= dst.len(),
        "destination inside its slice"
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            for r in 0..m {
                dst[r * dst_cols + column..r * dst_cols + column + n].fill(0.0);
            }
        }
        return;
    }
    // SAFETY: the asserts above keep every index of the three matrices inside their slices;
    // `dst` is borrowed mutably and does not alias `lhs` or `rhs`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr().add(column),
            1,
            dst_cols as isize,
            accumulate,
            lhs.data.as_ptr().add(lhs.offset),
            lhs.col_stride as isize,
            lhs.row_stride as isize,
            rhs.data.as_ptr().add(rhs.offset),
            rhs.col_stride as isize,
            rhs.row_stride as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// For patch row `row = ((c kd + a) kh + b) kw + e` and output cells `start..start + len`:
/// calls `visit(t, count, i, step)` for every run of cells `t..t + count` (tile positions)
/// whose taps fall inside the input, at input indices `i, i + step, ...` (one run per output
/// row: a row's taps are evenly spaced along the input's x axis).
fn for_each_run(
    g: &ConvGeometry,
    row: usize,
    start: usize,
    len: usize,
    mut visit: impl FnMut(usize, usize, usize, usize),
) {
    let [kd, kh, kw] = g.kernel;
    let [d, h, w] = g.input;
    let [_, oh, ow] = g.output();
    let [sz, sy, sx] = g.stride;
    let [pz, py, px] = g.padding;
    let e = row % kw;
    let b = (row / kw) % kh;
    let a = (row / (kw * kh)) % kd;
    let c = row / (kw * kh * kd);
    let base = c * d * h * w;
    // Output x with its tap inside the input: x sx + e - px in [0, w).
    let x_first = if px > e { (px - e).div_ceil(sx) } else { 0 };
    let x_end = if w + px > e {
        (w - 1 + px - e) / sx + 1
    } else {
        0
    };
    let end = start + len;
    let mut n = start;
    while n < end {
        let (z, y, x0) = (n / (oh * ow), (n / ow) % oh, n % ow);
        let x1 = ow.min(x0 + (end - n));
        let iz = (z * sz + a).wrapping_sub(pz);
        let iy = (y * sy + b).wrapping_sub(py);
        let (xs, xe) = (x0.max(x_first), x1.min(x_end));
        if iz < d && iy < h && xs < xe {
            let ix = xs * sx + e - px;
            visit(
                n - start + xs - x0,
                xe - xs,
                base + (iz * h + iy) * w + ix,
                sx,
            );
        }
        n += x1 - x0;
    }
}

/// `Col` rows for output cells `start..start + len`, `[K, len]` row-major.
fn im2col(g: &ConvGeometry, x: &[f32], start: usize, len: usize, col: &mut Vec<f32>) {
    // Every entry is written below (taps outside the input as zeros), so the buffer is
    // reused as it is.
    col.resize(g.patch() * len, 0.0);
    for (row, out) in col.chunks_mut(len).enumerate() {
        let mut written = 0;
        for_each_run(g, row, start, len, |t, count, i, step| {
            out[written..t].fill(0.0);
            let run = &mut out[t..t + count];
            if step == 1 {
                run.copy_from_slice(&x[i..i + count]);
            } else {
                for (j, value) in run.iter_mut().enumerate() {
                    *value = x[i + j * step];
                }
            }
            written = t + count;
        });
        out[written..].fill(0.0);
    }
}

/// Output cells of every tile: `(start, len)`.
fn tiles(g: &ConvGeometry) -> Vec<(usize, usize)> {
    let n = g.output_cells();
    let tile = g.tile();
    (0..n)
        .step_by(tile)
        .map(move |start| (start, tile.min(n - start)))
        .collect()
}

/// `Y [C_out, Do, Ho, Wo]` of `x [C_in, D, H, W]`, `weight [C_out, K]`, `bias [C_out]`.
///
/// Tiles run in parallel, each unfolding its own `Col` and multiplying it on one thread;
/// every output value is one product over `K` in a fixed order.
pub fn forward(g: &ConvGeometry, x: &[f32], weight: &[f32], bias: &[f32]) -> Vec<f32> {
    g.check();
    assert_eq!(x.len(), g.channels_in * g.input_cells(), "input shape");
    assert_eq!(weight.len(), g.channels_out * g.patch(), "weight shape");
    assert_eq!(bias.len(), g.channels_out, "bias shape");
    let n = g.output_cells();
    let w = View::row_major(weight, g.channels_out, g.patch());
    let tiles = tiles(g);
    let blocks: Vec<Vec<f32>> = tiles
        .par_iter()
        .map_init(Vec::new, |col, &(start, len)| {
            im2col(g, x, start, len, col);
            let mut block = vec![0.0f32; g.channels_out * len];
            matmul_into(
                &mut block,
                len,
                0,
                w,
                View::row_major(col, g.patch(), len),
                false,
            );
            block
        })
        .collect();
    let mut y = vec![0.0f32; g.channels_out * n];
    y.par_chunks_mut(n.max(1))
        .zip(bias)
        .enumerate()
        .for_each(|(o, (channel, b))| {
            for (&(start, len), block) in tiles.iter().zip(&blocks) {
                let row = &block[o * len..(o + 1) * len];
                for (v, r) in channel[start..start + len].iter_mut().zip(row) {
                    *v = r + b;
                }
            }
        });
    y
}

/// `dW [C_out, K]` given `x` and the output gradient `dy [C_out, Do, Ho, Wo]`: partial sums
/// over fixed groups of tiles in parallel, then added in order.
pub fn weight_grad(g: &ConvGeometry, x: &[f32], dy: &[f32]) -> Vec<f32> {
    g.check();
    assert_eq!(x.len(), g.channels_in * g.input_cells(), "input shape");
    let n = g.output_cells();
    assert_eq!(dy.len(), g.channels_out * n, "output gradient shape");
    let dy_view = View::row_major(dy, g.channels_out, n);
    let size = g.channels_out * g.patch();
    let partials: Vec<Vec<f32>> = tiles(g)
        .par_chunks(TILES_PER_PARTIAL)
        .map_init(Vec::new, |col, group| {
            let mut partial = vec![0.0f32; size];
            for (i, &(start, len)) in group.iter().enumerate() {
                im2col(g, x, start, len, col);
                matmul_into(
                    &mut partial,
                    g.patch(),
                    0,
                    dy_view.columns(start, len),
                    View::row_major(col, g.patch(), len).transpose(),
                    i > 0,
                );
            }
            partial
        })
        .collect();
    let mut dw = vec![0.0f32; size];
    dw.par_chunks_mut(g.patch().max(1))
        .enumerate()
        .for_each(|(o, row)| {
            let range = o * g.patch()..(o + 1) * g.patch();
            for partial in &partials {
                for (d, p) in row.iter_mut().zip(&partial[range.clone()]) {
                    *d += p;
                }
            }
        });
    dw
}

/// `W [C_out, C_in, k...]` as `W' [C_in, C_out, k...]` with every kernel axis reversed.
fn flip_kernel(g: &ConvGeometry, weight: &[f32]) -> Vec<f32> {
    let taps = g.kernel.iter().product::<usize>();
    let mut flipped = vec![0.0f32; weight.len()];
    for o in 0..g.channels_out {
        for c in 0..g.channels_in {
            let from = &weight[(o * g.channels_in + c) * taps..][..taps];
            let to = &mut flipped[(c * g.channels_out + o) * taps..][..taps];
            for (tap, value) in from.iter().enumerate() {
                to[taps - 1 - tap] = *value;
            }
        }
    }
    flipped
}

/// The adjoint of [`forward`] without its bias, `dX [C_in, D, H, W] = col2im(W^T dY)`: the
/// gradient with respect to the input, and the transposed convolution.
///
/// With stride 1 it is the convolution of `dY` with the flipped kernel ([`forward`]'s tiled
/// path). Otherwise `W^T dY` is formed tile by tile in parallel, a batch of tiles at a time,
/// and folded back channel by channel, each input cell summing its taps in a fixed order.
pub fn adjoint(g: &ConvGeometry, dy: &[f32], weight: &[f32]) -> Vec<f32> {
    g.check();
    let n = g.output_cells();
    assert_eq!(dy.len(), g.channels_out * n, "output gradient shape");
    assert_eq!(weight.len(), g.channels_out * g.patch(), "weight shape");
    if g.adjoint_is_a_convolution() {
        let flipped = g.flipped();
        let no_bias = vec![0.0f32; flipped.channels_out];
        return forward(&flipped, dy, &flip_kernel(g, weight), &no_bias);
    }
    let cells = g.input_cells();
    let mut dx = vec![0.0f32; g.channels_in * cells];
    let wt = View::row_major(weight, g.channels_out, g.patch()).transpose();
    let dy_view = View::row_major(dy, g.channels_out, n);
    let taps = g.kernel.iter().product::<usize>();
    let tiles = tiles(g);
    for batch in tiles.chunks(ADJOINT_BATCH_TILES) {
        let cols: Vec<Vec<f32>> = batch
            .par_iter()
            .map(|&(start, len)| {
                let mut col = vec![0.0f32; g.patch() * len];
                matmul_into(&mut col, len, 0, wt, dy_view.columns(start, len), false);
                col
            })
            .collect();
        dx.par_chunks_mut(cells).enumerate().for_each(|(c, plane)| {
            for (&(start, len), col) in batch.iter().zip(&cols) {
                for tap in 0..taps {
                    let row = c * taps + tap;
                    let values = &col[row * len..(row + 1) * len];
                    for_each_run(g, row, start, len, |t, count, i, step| {
                        let i = i - c * cells;
                        for (j, value) in values[t..t + count].iter().enumerate() {
                            plane[i + j * step] += value;
                        }
                    });
                }
            }
        });
    }
    dx
}

/// Per channel, the sum of `values [C, cells]` (the bias gradient).
pub fn channel_sums(values: &[f32], channels: usize) -> Vec<f32> {
    let cells = values.len() / channels.max(1);
    values
        .chunks(cells.max(1))
        .map(|channel| channel.iter().sum())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct definition of the convolution, in f64 (independent of the indexing above).
    fn naive(g: &ConvGeometry, x: &[f32], weight: &[f32]) -> Vec<f64> {
        let [d, h, w] = g.input;
        let [od, oh, ow] = g.output();
        let [kd, kh, kw] = g.kernel;
        let mut y = vec![0.0f64; g.channels_out * od * oh * ow];
        for o in 0..g.channels_out {
            for c in 0..g.channels_in {
                for (a, b, e) in
                    (0..kd).flat_map(|a| (0..kh).flat_map(move |b| (0..kw).map(move |e| (a, b, e))))
                {
                    let weight =
                        weight[(((o * g.channels_in + c) * kd + a) * kh + b) * kw + e] as f64;
                    for (z, yy, xx) in (0..od).flat_map(|z| {
                        (0..oh).flat_map(move |yy| (0..ow).map(move |xx| (z, yy, xx)))
                    }) {
                        let iz = (z * g.stride[0] + a) as isize - g.padding[0] as isize;
                        let iy = (yy * g.stride[1] + b) as isize - g.padding[1] as isize;
                        let ix = (xx * g.stride[2] + e) as isize - g.padding[2] as isize;
                        let inside = (0..d as isize).contains(&iz)
                            && (0..h as isize).contains(&iy)
                            && (0..w as isize).contains(&ix);
                        if inside {
                            let input =
                                x[((c * d + iz as usize) * h + iy as usize) * w + ix as usize];
                            y[((o * od + z) * oh + yy) * ow + xx] += weight * input as f64;
                        }
                    }
                }
            }
        }
        y
    }

    fn values(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = gausmoke_core::SplitMix64::new(seed);
        (0..len).map(|_| rng.range(-1.0, 1.0)).collect()
    }

    fn geometries() -> Vec<ConvGeometry> {
        let g = |ci, co, input, k, s, p| ConvGeometry {
            channels_in: ci,
            channels_out: co,
            input,
            kernel: [k; 3],
            stride: [s; 3],
            padding: [p; 3],
        };
        vec![
            g(5, 4, [6, 7, 5], 3, 1, 1),
            g(4, 6, [8, 6, 4], 2, 2, 0),
            g(3, 2, [4, 5, 6], 1, 1, 0),
            // More output cells than one tile holds.
            g(40, 3, [16, 18, 20], 3, 1, 1),
        ]
    }

    #[test]
    fn forward_matches_the_direct_sum() {
        for (i, g) in geometries().into_iter().enumerate() {
            let x = values(g.channels_in * g.input_cells(), i as u64);
            let w = values(g.channels_out * g.patch(), 10 + i as u64);
            let y = forward(&g, &x, &w, &vec![0.0; g.channels_out]);
            let expected = naive(&g, &x, &w);
            for (a, b) in y.iter().zip(&expected) {
                assert!((*a as f64 - b).abs() < 1e-4, "{g:?}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn adjoint_and_weight_gradient_are_the_transposes() {
        // <W * x, dy> = <x, adjoint(dy)> = <W, weight_grad(x, dy)>.
        for (i, g) in geometries().into_iter().enumerate() {
            let x = values(g.channels_in * g.input_cells(), 20 + i as u64);
            let w = values(g.channels_out * g.patch(), 30 + i as u64);
            let dy = values(g.channels_out * g.output_cells(), 40 + i as u64);
            let dot =
                |a: &[f32], b: &[f64]| a.iter().zip(b).map(|(a, b)| *a as f64 * b).sum::<f64>();
            let wide = |v: &[f32]| v.iter().map(|&v| v as f64).collect::<Vec<_>>();
            let lhs = dot(&dy, &naive(&g, &x, &w));
            let through_input = dot(&x, &wide(&adjoint(&g, &dy, &w)));
            let through_weight = dot(&w, &wide(&weight_grad(&g, &x, &dy)));
            let scale = lhs.abs().max(1.0);
            assert!(
                (lhs - through_input).abs() < 1e-4 * scale,
                "{g:?}: {lhs} vs {through_input}"
            );
            assert!(
                (lhs - through_weight).abs() < 1e-4 * scale,
                "{g:?}: {lhs} vs {through_weight}"
            );
        }
    }
}
