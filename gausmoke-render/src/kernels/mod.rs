//! The renderer on burn's cube backends (wgpu, Vulkan, CUDA): one file per kernel stage, the
//! backward stages in [`backward`], and here the launch sequence.
//!
//! Forward, all on the device:
//! 1. [`project`]: one unit per Gaussian; its splat in the camera's whitened frame, centre
//!    depth, screen-tile rectangle, and an atomic count per tile;
//! 2. [`tile_offsets`]: exclusive scan of the counts into list offsets; the list buffer is
//!    sized by [`RasterOptions::tile_list_capacity`] when the caller gives one (no read-back;
//!    the offsets are clamped to it and the true total kept for the caller to check, see
//!    [`list_buffer_length`]), else by reading the total back;
//! 3. [`tile_fill`]: scatter of Gaussian indices into the tile lists;
//! 4. [`tile_sort`]: per-tile bitonic sort by (centre depth, index);
//! 5. [`rasterize`]: one 16x16 cube per tile, batches of splats in shared memory, early exit
//!    when every pixel is opaque.
//!
//! The forward pass keeps its splats, tile lists and per-pixel walked counts ([`DeviceSaved`]),
//! so the backward pass does not bin again: it replays each pixel back to front
//! ([`backward::rasterize`], splat gradients added atomically), chains them to the world-space
//! parameters ([`backward::view`]) and reduces the background's gradient
//! ([`backward::background`]). The order of the atomic adds is not fixed: gradients agree with
//! the CPU path to float tolerance, not bit for bit.
//!
//! [`math`], [`atomics`], [`reduce`] and [`buffers`] are shared with the kernels of
//! `gausmoke-model`.

pub mod atomics;
pub mod backward;
pub mod buffers;
pub mod math;
pub mod project;
pub mod rasterize;
pub mod reduce;
pub mod splat;
pub mod tile_fill;
pub mod tile_offsets;
pub mod tile_sort;
pub mod validate;

use burn::tensor::DType;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_core::{Camera, phase};

use crate::RasterOptions;
use crate::cpu::IMAGE_CHANNELS;
use crate::gaussians::Gaussians;
use atomics::{CasAdd, NativeAdd, native_float_atomics};
use buffers::{Allocator, GAUSSIAN_BLOCK, buffer, contiguous_f32, linear_cubes};
use project::{Projection, TILE_EDGE};
use rasterize::TILE_THREADS;
use splat::{SPLAT_FLOATS, view_params};

/// The depth-sorted per-tile lists of one view: tile `t` owns `list[offsets[t]..offsets[t+1]]`.
#[derive(Debug, Clone)]
pub struct TileLists {
    pub offsets: CubeTensor,
    pub list: CubeTensor,
    pub tiles_x: u32,
    pub tiles_y: u32,
}

/// Stages 2-4: the per-tile lists of `projection`, in a buffer of `capacity` entries (`None`:
/// the exact total, read back from the device).
pub fn bin(
    projection: &Projection,
    num_gaussians: usize,
    width: u32,
    height: u32,
    capacity: Option<u32>,
) -> TileLists {
    let alloc = Allocator::like(&projection.splats);
    let tiles_x = width.div_ceil(TILE_EDGE);
    let tiles_y = height.div_ceil(TILE_EDGE);
    let num_tiles = (tiles_x * tiles_y) as usize;
    let offsets = scan_counts(projection, num_tiles, capacity.unwrap_or(u32::MAX));
    let total = match capacity {
        Some(capacity) => capacity as usize,
        None => {
            let _phase = phase!("tile offsets");
            crate::device_traffic::note_read(crate::device_traffic::ReadKind::TileListLength);
            let bytes = alloc
                .client
                .read_one(offsets.handle.clone())
                .expect("reading the tile-list length back from the GPU failed (device lost?)");
            u32::from_bytes(&bytes)[num_tiles] as usize
        }
    };
    let list = alloc.empty(total, DType::U32);
    if num_gaussians > 0 && total > 0 {
        let _phase = phase!("tile fill and sort");
        let cursors = alloc.zeros(num_tiles, DType::U32);
        tile_fill::fill_tiles_kernel::launch(
            &alloc.client,
            linear_cubes(num_gaussians),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&projection.rects),
            buffer(&offsets),
            buffer(&cursors),
            buffer(&list),
            num_gaussians as u32,
            width,
        );
        tile_sort::sort_tiles_kernel::launch(
            &alloc.client,
            CubeCount::Static(num_tiles as u32, 1, 1),
            CubeDim::new_1d(TILE_THREADS as u32),
            buffer(&projection.depths),
            buffer(&offsets),
            buffer(&list),
        );
    }
    TileLists {
        offsets,
        list,
        tiles_x,
        tiles_y,
    }
}

/// Stage 2: `[num_tiles + 2]` offsets, clamped to `capacity`, the last the unclamped total
/// (see [`tile_offsets::tile_offsets_kernel`]).
fn scan_counts(projection: &Projection, num_tiles: usize, capacity: u32) -> CubeTensor {
    let alloc = Allocator::like(&projection.splats);
    let offsets = alloc.empty(num_tiles + 2, DType::U32);
    let _phase = phase!("tile offsets");
    tile_offsets::tile_offsets_kernel::launch(
        &alloc.client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        buffer(&projection.counts),
        buffer(&offsets),
        num_tiles as u32,
        capacity,
    );
    offsets
}

/// Stage 1 for `camera`: the uploaded view parameters and the projection of `gaussians`
/// (contiguous f32), shared by [`forward`] and [`list_buffer_length`] so both count the same
/// tile-list entries.
fn project_view(
    gaussians: &Gaussians<CubeTensor>,
    camera: &Camera,
    options: &RasterOptions,
) -> (CubeTensor, Projection) {
    let alloc = Allocator::like(&gaussians.means);
    let view = alloc.f32s(&view_params(camera, options));
    let _phase = phase!("project");
    let projection = project::project(gaussians, &view, camera.width(), camera.height());
    (view, projection)
}

/// How many entries the tile-list buffer of a forward render of `gaussians` seen by `camera`
/// needs: `[1]` f32 on the device (exact below 2^24), from the same projection and scan as
/// [`forward`], so a caller can size [`RasterOptions::tile_list_capacity`] from it and check
/// later, with its other diagnostics, that a render's buffer was long enough.
pub fn list_buffer_length(
    gaussians: Gaussians<CubeTensor>,
    camera: &Camera,
    options: &RasterOptions,
) -> CubeTensor {
    let gaussians = buffers::contiguous_gaussians(gaussians);
    let alloc = Allocator::like(&gaussians.means);
    let (width, height) = (camera.width(), camera.height());
    let (_, projection) = project_view(&gaussians, camera, options);
    let num_tiles = (width.div_ceil(TILE_EDGE) * height.div_ceil(TILE_EDGE)) as usize;
    let offsets = scan_counts(&projection, num_tiles, u32::MAX);
    let length = alloc.empty(1, DType::F32);
    tile_offsets::list_length_kernel::launch(
        &alloc.client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(1),
        buffer(&offsets),
        buffer(&length),
        num_tiles as u32,
    );
    length
}

/// What the forward pass keeps for the backward pass.
#[derive(Debug, Clone)]
pub struct DeviceSaved {
    /// The inputs, contiguous f32.
    pub gaussians: Gaussians<CubeTensor>,
    pub background: CubeTensor,
    pub view: CubeTensor,
    pub options: RasterOptions,
    pub splats: CubeTensor,
    pub tiles: TileLists,
    /// `[H, W, IMAGE_CHANNELS]`.
    pub image: CubeTensor,
    /// Per pixel, the tile-list entries it walked (`u32`).
    pub walked: CubeTensor,
    pub width: u32,
    pub height: u32,
}

/// Forward render on the device: the `[H, W, IMAGE_CHANNELS]` image of `cpu::forward`, and
/// what the backward pass reuses.
pub fn forward(
    gaussians: Gaussians<CubeTensor>,
    background: CubeTensor,
    camera: &Camera,
    options: &RasterOptions,
) -> DeviceSaved {
    let gaussians = buffers::contiguous_gaussians(gaussians);
    let background = contiguous_f32(background, "background");
    let alloc = Allocator::like(&background);
    let n = gaussians.raw_densities.meta.num_elements();
    let (width, height) = (camera.width(), camera.height());
    let (view, projection) = project_view(&gaussians, camera, options);
    let tiles = bin(&projection, n, width, height, options.tile_list_capacity);
    let image = alloc.empty_shaped(
        vec![height as usize, width as usize, IMAGE_CHANNELS],
        DType::F32,
    );
    let walked = alloc.empty((width * height) as usize, DType::U32);
    {
        let _phase = phase!("rasterize");
        rasterize::rasterize_kernel::launch(
            &alloc.client,
            CubeCount::Static(tiles.tiles_x, tiles.tiles_y, 1),
            CubeDim::new_1d(TILE_THREADS as u32),
            buffer(&projection.splats),
            buffer(&tiles.offsets),
            buffer(&tiles.list),
            buffer(&view),
            buffer(&background),
            buffer(&image),
            buffer(&walked),
            width,
            height,
        );
    }
    DeviceSaved {
        gaussians,
        background,
        view,
        options: *options,
        splats: projection.splats,
        tiles,
        image,
        walked,
        width,
        height,
    }
}

/// Chains per-Gaussian splat gradients (`[n * SPLAT_FLOATS]`) through `view` back to the
/// world-space parameters: flat gradient buffers of every attribute (see
/// [`buffers::gradient_shapes`] for their shapes).
pub fn view_backward(
    gaussians: &Gaussians<CubeTensor>,
    view: &CubeTensor,
    splat_grads: &CubeTensor,
) -> Gaussians<CubeTensor> {
    let n = gaussians.raw_densities.meta.num_elements();
    let alloc = Allocator::like(view);
    let grads =
        Gaussians::default().map(|attribute, ()| alloc.empty(n * attribute.columns, DType::F32));
    if n > 0 {
        backward::view::view_backward_kernel::launch(
            &alloc.client,
            linear_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&gaussians.means),
            buffer(&gaussians.rotations),
            buffer(&gaussians.log_scales),
            buffer(&gaussians.raw_densities),
            buffer(view),
            buffer(splat_grads),
            buffer(&grads.means),
            buffer(&grads.rotations),
            buffer(&grads.log_scales),
            buffer(&grads.raw_densities),
            buffer(&grads.colors),
            n as u32,
        );
    }
    grads
}

/// Gradients of every input of the forward pass that produced `saved`, given the gradient of
/// its image: the Gaussians' (shaped as the attributes) and the background's (`[3]`).
pub fn backward(
    saved: &DeviceSaved,
    grad_image: CubeTensor,
) -> (Gaussians<CubeTensor>, CubeTensor) {
    let grad_image = contiguous_f32(grad_image, "render gradient");
    let alloc = Allocator::like(&saved.view);
    let n = saved.gaussians.raw_densities.meta.num_elements();
    let splat_grads = alloc.zeros(n * SPLAT_FLOATS, DType::F32);
    if n > 0 {
        let _phase = phase!("rasterize backward");
        let cubes = CubeCount::Static(saved.tiles.tiles_x, saved.tiles.tiles_y, 1);
        let cube_dim = CubeDim::new_1d(TILE_THREADS as u32);
        let sums = backward::rasterize::resolve(&alloc.client, saved.options.gradient_sums);
        macro_rules! launch_backward {
            ($adder:ty) => {
                backward::rasterize::rasterize_backward_kernel::launch::<$adder>(
                    &alloc.client,
                    cubes,
                    cube_dim,
                    buffer(&saved.splats),
                    buffer(&saved.tiles.offsets),
                    buffer(&saved.tiles.list),
                    buffer(&saved.view),
                    buffer(&saved.background),
                    buffer(&saved.image),
                    buffer(&saved.walked),
                    buffer(&grad_image),
                    buffer(&splat_grads),
                    saved.width,
                    saved.height,
                    sums,
                )
            };
        }
        if native_float_atomics(&alloc.client, saved.options.float_atomics) {
            launch_backward!(NativeAdd);
        } else {
            launch_backward!(CasAdd);
        }
    }
    let grads = {
        let _phase = phase!("view backward");
        view_backward(&saved.gaussians, &saved.view, &splat_grads)
    };
    let grad_background = alloc.empty(3, DType::F32);
    backward::background::background_grad_kernel::launch(
        &alloc.client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        buffer(&saved.image),
        buffer(&grad_image),
        buffer(&grad_background),
        saved.width * saved.height,
    );
    (
        buffers::gradient_shapes(grads, n),
        buffers::leading(grad_background, vec![3]),
    )
}
