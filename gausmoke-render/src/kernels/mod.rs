//! The renderer on burn's cube backends (wgpu, Vulkan, CUDA): host-side launch code for the
//! cubecl kernels in [`raster`].
//!
//! Forward pipeline, all on the device:
//! 1. `project_kernel`: one unit per Gaussian; whitened splat, centre depth, screen-tile
//!    rectangle, and an atomic count per tile;
//! 2. `tile_offsets_kernel`: exclusive scan of the counts (one read-back of the total, to size
//!    the tile lists);
//! 3. `fill_tiles_kernel`: scatter of Gaussian indices into the tile lists;
//! 4. `sort_tiles_kernel`: per-tile bitonic sort by (centre depth, index), so every backend
//!    composites in the same order;
//! 5. `rasterize_kernel`: one 16x16 cube per tile, batches of Gaussians in shared memory, early
//!    exit when every pixel is opaque.
//!
//! The backward pass bins again (same inputs, same lists), replays each pixel back to front
//! (`rasterize_backward_kernel`, gradients of the splats added atomically), chains them to the
//! world-space parameters (`view_backward_kernel`) and reduces the background's gradient.
//!
//! Summation order of the atomic adds is not fixed: gradients agree with the CPU path to float
//! tolerance, not bit for bit.

pub mod raster;

use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::ir::{FloatKind, Type};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_contiguous_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_core::Camera;

use crate::RasterOptions;
use crate::cpu::OUTPUT_CHANNELS;
use raster::{SPLAT_FLOATS, TILE_EDGE, TILE_THREADS, VIEW_FLOATS, ViewParam};

/// Per-stage wall times of one render call, for finding what limits the kernels: set
/// `GAUSMOKE_KERNEL_TIMINGS=1` and every stage waits for the device and its time is printed
/// to stderr (this serialises the pipeline, so totals are slightly higher than untimed ones).
struct StageTimer {
    enabled: bool,
    last: std::time::Instant,
    stages: Vec<(&'static str, f64)>,
}

impl StageTimer {
    fn new(client: &Client) -> Self {
        let enabled = crate::timings_enabled();
        if enabled {
            let _ = cubecl::future::block_on(client.sync());
        }
        Self {
            enabled,
            last: std::time::Instant::now(),
            stages: Vec::new(),
        }
    }

    fn stage(&mut self, client: &Client, name: &'static str) {
        if self.enabled {
            let _ = cubecl::future::block_on(client.sync());
            let now = std::time::Instant::now();
            self.stages
                .push((name, (now - self.last).as_secs_f64() * 1e3));
            self.last = now;
        }
    }

    fn report(&self, what: &str) {
        if self.enabled {
            let parts: Vec<String> = self
                .stages
                .iter()
                .map(|(name, ms)| format!("{name} {ms:.3}"))
                .collect();
            eprintln!("gausmoke kernel timings ({what}, ms): {}", parts.join(", "));
        }
    }
}

/// Units per cube of the per-Gaussian kernels.
pub const GAUSSIAN_BLOCK: u32 = 256;

/// The view as the kernels read it (see [`ViewParam`]).
fn view_params(camera: &Camera, options: &RasterOptions) -> [f32; VIEW_FLOATS] {
    let mut params = [0.0f32; VIEW_FLOATS];
    let w2c = camera.rotation_world_to_camera();
    // glam is column-major: row i of W is (x_axis[i], y_axis[i], z_axis[i]).
    for (row, slot) in [0usize, 1, 2].iter().zip([0usize, 3, 6]) {
        params[ViewParam::ROTATION + slot] = w2c.x_axis[*row];
        params[ViewParam::ROTATION + slot + 1] = w2c.y_axis[*row];
        params[ViewParam::ROTATION + slot + 2] = w2c.z_axis[*row];
    }
    let origin = camera.position();
    params[ViewParam::ORIGIN] = origin.x;
    params[ViewParam::ORIGIN + 1] = origin.y;
    params[ViewParam::ORIGIN + 2] = origin.z;
    let k = camera.intrinsics();
    params[ViewParam::FX] = k.fx;
    params[ViewParam::FY] = k.fy;
    params[ViewParam::CX] = k.cx;
    params[ViewParam::CY] = k.cy;
    params[ViewParam::ALPHA_MIN] = options.alpha_min;
    params[ViewParam::ALPHA_MAX] = options.alpha_max;
    params[ViewParam::TRANSMITTANCE_MIN] = options.transmittance_min;
    params[ViewParam::KERNEL_CUTOFF] = options.kernel_cutoff;
    params[ViewParam::NEAR_PLANE] = options.near_plane;
    params[ViewParam::MIN_OPTICAL_DEPTH] = -(1.0 - options.alpha_min).ln();
    params[ViewParam::ALPHA_MODEL] = match options.alpha_model {
        crate::AlphaModel::BeerLambert => 0.0,
        crate::AlphaModel::SplatOpacity => 1.0,
    };
    params
}

/// A device buffer argument covering all of `tensor` (which must be contiguous).
pub fn buffer(tensor: &CubeTensor) -> BufferArg {
    tensor.clone().into_buffer_arg()
}

/// `tensor` as a contiguous f32 buffer; panics naming `name` for another dtype (the kernels
/// are f32 only).
pub fn contiguous_f32(tensor: CubeTensor, name: &str) -> CubeTensor {
    assert_eq!(
        tensor.dtype,
        DType::F32,
        "the GPU renderer works in f32; `{name}` is {:?}",
        tensor.dtype
    );
    into_contiguous(tensor)
}

/// Number of cubes of [`GAUSSIAN_BLOCK`] units covering `n` Gaussians.
pub fn gaussian_cubes(n: usize) -> CubeCount {
    let cubes = n.div_ceil(GAUSSIAN_BLOCK as usize).max(1);
    assert!(
        cubes <= u16::MAX as usize,
        "{n} Gaussians exceed the per-launch limit of the GPU renderer ({} Gaussians)",
        u16::MAX as usize * GAUSSIAN_BLOCK as usize
    );
    CubeCount::Static(cubes as u32, 1, 1)
}

/// The Gaussian parameters, contiguous f32 on the device.
struct DeviceScene {
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    colors: CubeTensor,
    background: CubeTensor,
}

impl DeviceScene {
    fn new(
        means: CubeTensor,
        quats: CubeTensor,
        log_scales: CubeTensor,
        raw_densities: CubeTensor,
        colors: CubeTensor,
        background: CubeTensor,
    ) -> Self {
        Self {
            means: contiguous_f32(means, "means"),
            quats: contiguous_f32(quats, "rotations"),
            log_scales: contiguous_f32(log_scales, "log_scales"),
            raw_densities: contiguous_f32(raw_densities, "raw_densities"),
            colors: contiguous_f32(colors, "colors"),
            background: contiguous_f32(background, "background"),
        }
    }

    fn len(&self) -> usize {
        self.raw_densities.meta.num_elements()
    }

    fn client(&self) -> &Client {
        &self.means.client
    }
}

/// Projected Gaussians and the sorted per-tile lists.
struct Binning {
    view: CubeTensor,
    splats: CubeTensor,
    offsets: CubeTensor,
    list: CubeTensor,
    tiles_x: u32,
    tiles_y: u32,
}

fn f32_tensor(scene: &DeviceScene, values: &[f32]) -> CubeTensor {
    use burn::backend::ops::FloatTensorOps;
    CubeBackend::float_from_data(
        burn::tensor::TensorData::new(values.to_vec(), [values.len()]),
        &scene.means.device,
    )
}

fn empty(scene: &DeviceScene, len: usize, dtype: DType) -> CubeTensor {
    empty_device_contiguous_dtype(
        scene.client().clone(),
        scene.means.device.clone(),
        [len.max(1)].into(),
        dtype,
    )
}

fn zeros(scene: &DeviceScene, len: usize, dtype: DType) -> CubeTensor {
    zeros_client(
        scene.client().clone(),
        scene.means.device.clone(),
        [len.max(1)].into(),
        dtype,
    )
}

fn bin(
    scene: &DeviceScene,
    camera: &Camera,
    options: &RasterOptions,
    timer: &mut StageTimer,
) -> Binning {
    let client = scene.client().clone();
    let n = scene.len();
    let width = camera.width();
    let height = camera.height();
    let tiles_x = width.div_ceil(TILE_EDGE);
    let tiles_y = height.div_ceil(TILE_EDGE);
    let num_tiles = (tiles_x * tiles_y) as usize;

    let view = f32_tensor(scene, &view_params(camera, options));
    let Projection {
        splats,
        depths,
        rects,
        counts,
    } = project(scene, &view, width, height);
    timer.stage(&client, "project");

    let offsets = empty(scene, num_tiles + 1, DType::U32);
    raster::tile_offsets_kernel::launch(
        &client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        buffer(&counts),
        buffer(&offsets),
        num_tiles as u32,
    );
    // The one read-back of the forward pass: the list length sizes its buffer.
    let bytes = client
        .read_one(offsets.handle.clone())
        .expect("reading the tile-list length back from the GPU failed (device lost?)");
    let total = u32::from_bytes(&bytes)[num_tiles] as usize;
    timer.stage(&client, "scan+readback");

    let list = empty(scene, total, DType::U32);
    if n > 0 && total > 0 {
        let cursors = zeros(scene, num_tiles, DType::U32);
        raster::fill_tiles_kernel::launch(
            &client,
            gaussian_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&rects),
            buffer(&offsets),
            buffer(&cursors),
            buffer(&list),
            n as u32,
            width,
        );
        timer.stage(&client, "fill");
        raster::sort_tiles_kernel::launch(
            &client,
            CubeCount::Static(num_tiles as u32, 1, 1),
            CubeDim::new_1d(TILE_THREADS as u32),
            buffer(&depths),
            buffer(&offsets),
            buffer(&list),
        );
        timer.stage(&client, "sort");
    }
    Binning {
        view,
        splats,
        offsets,
        list,
        tiles_x,
        tiles_y,
    }
}

/// What `project_kernel` writes: the splats, centre depths, tile rectangles and per-tile
/// counts of one view.
struct Projection {
    splats: CubeTensor,
    depths: CubeTensor,
    rects: CubeTensor,
    counts: CubeTensor,
}

/// Projects every Gaussian of `scene` into `view` for a `width` x `height` image.
fn project(scene: &DeviceScene, view: &CubeTensor, width: u32, height: u32) -> Projection {
    let n = scene.len();
    let num_tiles = (width.div_ceil(TILE_EDGE) * height.div_ceil(TILE_EDGE)) as usize;
    let projection = Projection {
        splats: empty(scene, n * SPLAT_FLOATS, DType::F32),
        depths: empty(scene, n, DType::F32),
        rects: empty(scene, n * 4, DType::U32),
        counts: zeros(scene, num_tiles, DType::U32),
    };
    if n > 0 {
        raster::project_kernel::launch(
            scene.client(),
            gaussian_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&scene.means),
            buffer(&scene.quats),
            buffer(&scene.log_scales),
            buffer(&scene.raw_densities),
            buffer(&scene.colors),
            buffer(view),
            buffer(&projection.splats),
            buffer(&projection.depths),
            buffer(&projection.rects),
            buffer(&projection.counts),
            n as u32,
            width,
            height,
        );
    }
    projection
}

/// Forward render on the device: `[H, W, OUTPUT_CHANNELS]`, as [`crate::cpu::forward`].
#[allow(clippy::too_many_arguments)]
pub fn forward(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    colors: CubeTensor,
    background: CubeTensor,
    camera: &Camera,
    options: &RasterOptions,
) -> CubeTensor {
    let scene = DeviceScene::new(means, quats, log_scales, raw_densities, colors, background);
    let mut timer = StageTimer::new(scene.client());
    let binning = bin(&scene, camera, options, &mut timer);
    let (width, height) = (camera.width(), camera.height());
    let output = empty_device_contiguous_dtype(
        scene.client().clone(),
        scene.means.device.clone(),
        [height as usize, width as usize, OUTPUT_CHANNELS].into(),
        DType::F32,
    );
    raster::rasterize_kernel::launch(
        scene.client(),
        CubeCount::Static(binning.tiles_x, binning.tiles_y, 1),
        CubeDim::new_2d(TILE_EDGE, TILE_EDGE),
        buffer(&binning.splats),
        buffer(&binning.offsets),
        buffer(&binning.list),
        buffer(&binning.view),
        buffer(&scene.background),
        buffer(&output),
        width,
        height,
    );
    timer.stage(scene.client(), "rasterize");
    timer.report("forward");
    output
}

/// Whether the device adds `f32` atomically in storage buffers (else the backward pass uses a
/// compare-and-swap loop).
pub fn has_native_f32_atomic_add(client: &Client) -> bool {
    client
        .properties()
        .atomic_type_usage(Type::atomic(FloatKind::F32))
        .contains(AtomicUsage::Add)
}

/// Gradients of every input, as [`crate::cpu::backward`].
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
pub fn backward(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    colors: CubeTensor,
    background: CubeTensor,
    camera: &Camera,
    options: &RasterOptions,
    output: CubeTensor,
    grad_output: CubeTensor,
    force_compare_and_swap: bool,
) -> (
    CubeTensor,
    CubeTensor,
    CubeTensor,
    CubeTensor,
    CubeTensor,
    CubeTensor,
) {
    let scene = DeviceScene::new(means, quats, log_scales, raw_densities, colors, background);
    let output = contiguous_f32(output, "render output");
    let grad_output = contiguous_f32(grad_output, "render gradient");
    let client = scene.client().clone();
    let n = scene.len();
    let mut timer = StageTimer::new(&client);
    let binning = bin(&scene, camera, options, &mut timer);
    let (width, height) = (camera.width(), camera.height());

    let splat_grads = zeros(&scene, n * SPLAT_FLOATS, DType::F32);
    let cubes = CubeCount::Static(binning.tiles_x, binning.tiles_y, 1);
    let cube_dim = CubeDim::new_2d(TILE_EDGE, TILE_EDGE);
    macro_rules! launch_backward {
        ($adder:ty) => {
            raster::rasterize_backward_kernel::launch::<$adder>(
                &client,
                cubes,
                cube_dim,
                buffer(&binning.splats),
                buffer(&binning.offsets),
                buffer(&binning.list),
                buffer(&binning.view),
                buffer(&scene.background),
                buffer(&output),
                buffer(&grad_output),
                buffer(&splat_grads),
                width,
                height,
            )
        };
    }
    if n > 0 {
        if has_native_f32_atomic_add(&client) && !force_compare_and_swap {
            launch_backward!(raster::NativeAdd);
        } else {
            launch_backward!(raster::CasAdd);
        }
    }
    timer.stage(&client, "rasterize_backward");

    let [
        grad_means,
        grad_quats,
        grad_log_scales,
        grad_raw_densities,
        grad_colors,
    ] = view_backward(&scene, &binning.view, &splat_grads);
    timer.stage(&client, "view_backward");
    let grad_background = empty(&scene, 3, DType::F32);
    raster::background_grad_kernel::launch(
        &client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        buffer(&output),
        buffer(&grad_output),
        buffer(&grad_background),
        width * height,
    );
    timer.stage(&client, "background");
    timer.report("backward");

    (
        leading(grad_means, vec![n, 3]),
        leading(grad_quats, vec![n, 4]),
        leading(grad_log_scales, vec![n, 3]),
        leading(grad_raw_densities, vec![n]),
        leading(grad_colors, vec![n, 3]),
        leading(grad_background, vec![3]),
    )
}

/// The view of a camera at the world origin with axes aligned to the world's, and no
/// culling (the near plane at infinity): with it `project_kernel` returns each Gaussian's
/// world-space whitening and `view_backward_kernel` chains gradients of that whitening.
fn world_view_params() -> [f32; VIEW_FLOATS] {
    let mut params = [0.0f32; VIEW_FLOATS];
    params[ViewParam::ROTATION] = 1.0;
    params[ViewParam::ROTATION + 4] = 1.0;
    params[ViewParam::ROTATION + 8] = 1.0;
    params[ViewParam::NEAR_PLANE] = f32::INFINITY;
    params[ViewParam::KERNEL_CUTOFF] = 9.0;
    params[ViewParam::MIN_OPTICAL_DEPTH] = 1.0;
    params
}

/// World-space whitening of every Gaussian, [`SPLAT_FLOATS`] floats each: `L = S^-1 R^T`
/// (row-major), `L mu`, `sigma = softplus(raw)`, and a zero colour. This is what density
/// splatting evaluates (`k(x) = exp(-|L x - L mu|^2 / 2)`); it is the renderer's projection
/// with the camera at the origin, so both ops share one parameterisation.
pub fn world_splats(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
) -> CubeTensor {
    let scene = world_scene(means, quats, log_scales, raw_densities);
    let view = f32_tensor(&scene, &world_view_params());
    // A 1x1 image: with the near plane at infinity no Gaussian touches a tile.
    project(&scene, &view, 1, 1).splats
}

/// Gradients `(means, quats, log_scales, raw_densities)` given the gradient of
/// [`world_splats`]' output (`[n * SPLAT_FLOATS]`; its colour slots are ignored).
pub fn world_splats_backward(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    splat_grads: CubeTensor,
) -> (CubeTensor, CubeTensor, CubeTensor, CubeTensor) {
    let scene = world_scene(means, quats, log_scales, raw_densities);
    let splat_grads = contiguous_f32(splat_grads, "splat gradients");
    let n = scene.len();
    assert_eq!(
        splat_grads.meta.num_elements(),
        (n * SPLAT_FLOATS).max(1),
        "splat gradients must hold SPLAT_FLOATS values per Gaussian"
    );
    let view = f32_tensor(&scene, &world_view_params());
    let [
        grad_means,
        grad_quats,
        grad_log_scales,
        grad_raw_densities,
        _,
    ] = view_backward(&scene, &view, &splat_grads);
    (
        leading(grad_means, vec![n, 3]),
        leading(grad_quats, vec![n, 4]),
        leading(grad_log_scales, vec![n, 3]),
        leading(grad_raw_densities, vec![n]),
    )
}

/// The Gaussians with a zero colour and background (not read by the world-space kernels
/// apart from the colour slots they copy).
fn world_scene(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
) -> DeviceScene {
    let n = raw_densities.meta.num_elements();
    let client = means.client.clone();
    let device = means.device.clone();
    let colors = zeros_client(
        client.clone(),
        device.clone(),
        [(n * 3).max(1)].into(),
        DType::F32,
    );
    let background = zeros_client(client, device, [3].into(), DType::F32);
    DeviceScene::new(means, quats, log_scales, raw_densities, colors, background)
}

/// The leading `shape.product()` values of a flat buffer (kernel buffers hold at least one
/// element: zero-sized allocations are avoided), reshaped to `shape`.
pub fn leading(tensor: CubeTensor, shape: Vec<usize>) -> CubeTensor {
    let len: usize = shape.iter().product();
    let flat = burn_cubecl::ops::reshape(tensor.clone(), [tensor.meta.num_elements()].into());
    let flat = if len == flat.meta.num_elements() {
        flat
    } else {
        #[allow(clippy::single_range_in_vec_init)] // one range per dimension
        burn_cubecl::kernel::slice(flat, &[0..len])
    };
    burn_cubecl::ops::reshape(flat, shape.into())
}

/// Chains per-Gaussian splat gradients (`[n * SPLAT_FLOATS]`) through `view` back to the
/// world-space parameters: `[means, quats, log_scales, raw_densities, colors]` gradients,
/// flat (see [`leading`] for their shapes).
fn view_backward(
    scene: &DeviceScene,
    view: &CubeTensor,
    splat_grads: &CubeTensor,
) -> [CubeTensor; 5] {
    let n = scene.len();
    let grads = [3, 4, 3, 1, 3].map(|columns| empty(scene, n * columns, DType::F32));
    if n > 0 {
        let [means, quats, log_scales, raw_densities, colors] = &grads;
        raster::view_backward_kernel::launch(
            scene.client(),
            gaussian_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&scene.means),
            buffer(&scene.quats),
            buffer(&scene.log_scales),
            buffer(&scene.raw_densities),
            buffer(view),
            buffer(splat_grads),
            buffer(means),
            buffer(quats),
            buffer(log_scales),
            buffer(raw_densities),
            buffer(colors),
            n as u32,
        );
    }
    grads
}

static FORCE_COMPARE_AND_SWAP: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// Makes the backward pass use the compare-and-swap fallback even where the device has native
/// float atomics (process-wide), so tests can check both paths on one device.
pub fn set_force_compare_and_swap(force: bool) {
    FORCE_COMPARE_AND_SWAP.store(force, std::sync::atomic::Ordering::SeqCst);
}

/// See [`set_force_compare_and_swap`].
pub fn force_compare_and_swap() -> bool {
    FORCE_COMPARE_AND_SWAP.load(std::sync::atomic::Ordering::SeqCst)
}

/// Validation statistics of the inputs on the device: one kernel and an 8-float result (see
/// `VolumeRenderBackend::volume_render_input_stats`).
pub fn input_stats(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    colors: CubeTensor,
    background: CubeTensor,
) -> CubeTensor {
    let parts = [background, means, quats, log_scales, raw_densities, colors];
    let mut ends = Vec::with_capacity(6);
    let mut total = 0usize;
    let flat: Vec<CubeTensor> = parts
        .into_iter()
        .map(|t| {
            let t = contiguous_f32(t, "render input");
            let len = t.meta.num_elements();
            total += len;
            ends.push(total as u32);
            burn_cubecl::ops::reshape(t, [len].into())
        })
        .collect();
    assert!(
        total < u32::MAX as usize,
        "render inputs too large to validate"
    );
    use burn::backend::ops::FloatTensorOps;
    let inputs = CubeBackend::float_cat(flat, 0);
    let client = inputs.client.clone();
    let ends = client.create_from_slice(u32::as_bytes(&ends));
    let stats = empty_device_contiguous_dtype(
        client.clone(),
        inputs.device.clone(),
        [8].into(),
        DType::F32,
    );
    raster::input_stats_kernel::launch(
        &client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        buffer(&inputs),
        // SAFETY: the handle holds exactly the 6 offsets written above.
        unsafe { BufferArg::from_raw_parts(ends, 6) },
        buffer(&stats),
    );
    stats
}
