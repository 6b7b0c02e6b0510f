//! The velocity update network Phi (paper Eq. 8): a light 3D U-Net on the Eulerian grid.
//!
//! Input channels: the current velocity (3), the splatted density (1) and a sinusoidal
//! encoding of the normalised time `t in [0, 1]` broadcast over the grid (`2 L` channels:
//! `sin(2^k pi t), cos(2^k pi t)`, `k < L`). Output: the velocity increment `Delta u` (3).
//!
//! Architecture: two 3^3 convolutions per level, strided 2^3 convolutions down, transposed
//! 2^3 convolutions up, skip connections by concatenation, SiLU activations; three levels, so
//! each grid axis must be divisible by 4. The output convolution starts at zero, so at
//! initialisation `Delta u = 0` and training starts from the previous frame's velocity.
//! The layers are burn's Conv3d and ConvTranspose3d modules (their parameters and
//! initialisation); their arithmetic is [`crate::conv`], which on the CPU backends replaces
//! burn's (no 3D pooling is needed).

use burn::module::{Initializer, Module, ModuleVisitor, Param};
use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3d, Conv3dConfig, ConvTranspose3d, ConvTranspose3dConfig};
use burn::tensor::activation::silu;
use burn::tensor::{Device, Tensor, TensorData};

use crate::conv::{conv_transpose3d, conv3d};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UNetConfig {
    /// Channels of the first level (doubled at each level down).
    pub base_channels: usize,
    /// Number of time frequencies `L`.
    pub time_frequencies: usize,
}

impl Default for UNetConfig {
    fn default() -> Self {
        Self {
            base_channels: 16,
            time_frequencies: 4,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum UNetError {
    #[error(
        "the U-Net halves the grid twice: every axis must be divisible by 4, got {resolution:?}"
    )]
    Resolution { resolution: [usize; 3] },
    #[error("`{name}` must have shape {expected}, got {got:?}")]
    Shape {
        name: &'static str,
        expected: String,
        got: Vec<usize>,
    },
}

#[derive(Module, Debug)]
struct DoubleConv {
    first: Conv3d,
    second: Conv3d,
}

impl DoubleConv {
    fn new(input: usize, output: usize, device: &Device) -> Self {
        let conv = |i, o| {
            Conv3dConfig::new([i, o], [3, 3, 3])
                .with_padding(PaddingConfig3d::Explicit(1, 1, 1))
                .init(device)
        };
        Self {
            first: conv(input, output),
            second: conv(output, output),
        }
    }

    fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        silu(conv3d(&self.second, silu(conv3d(&self.first, x))))
    }
}

/// Reads every float parameter once, which draws the lazily initialised ones.
struct DrawInitialWeights;

impl ModuleVisitor for DrawInitialWeights {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let _ = param.val();
    }
}

/// Held while the backend's generator is seeded and Phi's weights are drawn from it: the
/// generator is one per process, so two threads making Phi at once (parallel tests, two
/// runs in one program) would otherwise draw each other's numbers.
static INITIAL_DRAW: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Phi: `(u, sigma_grid, t) -> Delta u`.
#[derive(Module, Debug)]
pub struct VelocityUNet {
    encode1: DoubleConv,
    down1: Conv3d,
    encode2: DoubleConv,
    down2: Conv3d,
    bottleneck: DoubleConv,
    up2: ConvTranspose3d,
    decode2: DoubleConv,
    up1: ConvTranspose3d,
    decode1: DoubleConv,
    output: Conv3d,
    time_frequencies: usize,
}

impl VelocityUNet {
    /// Phi with initial weights that depend on `seed` alone.
    pub fn new(config: &UNetConfig, seed: u64, device: &Device) -> Self {
        let _draw = INITIAL_DRAW
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        device.seed(seed);
        let c = config.base_channels;
        let input = 4 + 2 * config.time_frequencies;
        let down = |i, o| {
            Conv3dConfig::new([i, o], [2, 2, 2])
                .with_stride([2, 2, 2])
                .init(device)
        };
        let up = |i, o| {
            ConvTranspose3dConfig::new([i, o], [2, 2, 2])
                .with_stride([2, 2, 2])
                .init(device)
        };
        let unet = Self {
            encode1: DoubleConv::new(input, c, device),
            down1: down(c, 2 * c),
            encode2: DoubleConv::new(2 * c, 2 * c, device),
            down2: down(2 * c, 4 * c),
            bottleneck: DoubleConv::new(4 * c, 4 * c, device),
            up2: up(4 * c, 2 * c),
            decode2: DoubleConv::new(4 * c, 2 * c, device),
            up1: up(2 * c, c),
            decode1: DoubleConv::new(2 * c, c, device),
            output: Conv3dConfig::new([c, 3], [1, 1, 1])
                .with_initializer(Initializer::Zeros)
                .init(device),
            time_frequencies: config.time_frequencies,
        };
        // burn draws a layer's initial weights when they are first read: drawn here, under
        // the lock and right after the seed, they do not depend on what else the process
        // draws before Phi's first use. The module order is the forward pass's, so the
        // weights are those that a first forward pass would draw.
        unet.visit(&mut DrawInitialWeights);
        unet
    }

    /// `Delta u [nx, ny, nz, 3]` from `velocity [nx, ny, nz, 3]`, `density [nx, ny, nz]` and
    /// the normalised time `t in [0, 1]`.
    pub fn forward(
        &self,
        velocity: Tensor<4>,
        density: Tensor<3>,
        t: f32,
    ) -> Result<Tensor<4>, UNetError> {
        let [nx, ny, nz, c] = velocity.dims();
        if c != 3 {
            return Err(UNetError::Shape {
                name: "velocity",
                expected: "[nx, ny, nz, 3]".into(),
                got: vec![nx, ny, nz, c],
            });
        }
        if density.dims() != [nx, ny, nz] {
            return Err(UNetError::Shape {
                name: "density",
                expected: format!("[{nx}, {ny}, {nz}] (the velocity grid)"),
                got: density.dims().to_vec(),
            });
        }
        if [nx, ny, nz].iter().any(|n| n % 4 != 0) {
            return Err(UNetError::Resolution {
                resolution: [nx, ny, nz],
            });
        }
        let device = velocity.device();
        let encoding: Vec<f32> = (0..self.time_frequencies)
            .flat_map(|k| {
                let phase = (1u32 << k) as f32 * std::f32::consts::PI * t;
                [phase.sin(), phase.cos()]
            })
            .collect();
        let time = Tensor::<5>::from_data(
            TensorData::new(encoding, [1, 2 * self.time_frequencies, 1, 1, 1]),
            &device,
        )
        .expand([1, 2 * self.time_frequencies, nx, ny, nz]);
        let x = Tensor::cat(
            vec![
                velocity.permute([3, 0, 1, 2]).unsqueeze_dim::<5>(0),
                density.unsqueeze_dims::<5>(&[0, 1]),
                time,
            ],
            1,
        );
        let skip1 = self.encode1.forward(x);
        let skip2 = self
            .encode2
            .forward(silu(conv3d(&self.down1, skip1.clone())));
        let deep = self
            .bottleneck
            .forward(silu(conv3d(&self.down2, skip2.clone())));
        let up2 = self.decode2.forward(Tensor::cat(
            vec![conv_transpose3d(&self.up2, deep), skip2],
            1,
        ));
        let up1 = self.decode1.forward(Tensor::cat(
            vec![conv_transpose3d(&self.up1, up2), skip1],
            1,
        ));
        let delta = conv3d(&self.output, up1); // [1, 3, nx, ny, nz]
        Ok(delta.squeeze_dim::<4>(0).permute([1, 2, 3, 0]))
    }
}

#[cfg(test)]
#[allow(clippy::disallowed_methods)] // tests read tensors freely
mod tests {
    use super::*;
    use burn::tensor::Distribution;
    use gausmoke_render::backends::cpu_devices;

    fn inputs(device: &Device, n: [usize; 3]) -> (Tensor<4>, Tensor<3>) {
        let [x, y, z] = n;
        let cells = x * y * z;
        let u: Vec<f32> = (0..3 * cells)
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.5)
            .collect();
        let d: Vec<f32> = (0..cells)
            .map(|i| ((i * 104_729) % 53) as f32 / 53.0)
            .collect();
        (
            Tensor::from_data(TensorData::new(u, [x, y, z, 3]), device),
            Tensor::from_data(TensorData::new(d, [x, y, z]), device),
        )
    }

    #[test]
    fn starts_at_zero_and_trains_its_output_layer_on_every_backend() {
        for (backend, device) in cpu_devices() {
            let device = device.autodiff();
            let unet = VelocityUNet::new(
                &UNetConfig {
                    base_channels: 4,
                    time_frequencies: 2,
                },
                0,
                &device,
            );
            let (u, d) = inputs(&device, [8, 12, 4]);
            let delta = unet.forward(u, d, 0.3).unwrap();
            assert_eq!(delta.dims(), [8, 12, 4, 3], "{backend}");
            let values = delta.clone().into_data().try_into_vec_as::<f32>().unwrap();
            assert!(
                values.iter().all(|&v| v == 0.0),
                "zero-initialised output: Delta u = 0"
            );
            let weights = Tensor::<4>::ones([8, 12, 4, 3], &device);
            let grads = (delta * weights).sum().backward();
            let g = unet
                .output
                .weight
                .val()
                .grad(&grads)
                .expect("output weight is trained");
            let g = g.into_data().try_into_vec_as::<f32>().unwrap();
            assert!(
                g.iter().any(|v| v.abs() > 1e-6),
                "{backend}: gradient reaches the output layer"
            );
        }
    }

    /// Every float parameter's values, in module order.
    struct Values(Vec<f32>);

    impl ModuleVisitor for Values {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let values = param.val().into_data().try_into_vec_as::<f32>().unwrap();
            self.0.extend(values);
        }
    }

    /// The seed alone decides Phi's initial weights: neither what the process draws from
    /// the backend's generator between making Phi and using it, nor other threads making
    /// Phi with other seeds at the same time, moves them.
    #[test]
    fn its_initial_weights_depend_on_the_seed_alone() {
        let config = UNetConfig {
            base_channels: 2,
            time_frequencies: 1,
        };
        let weights = |seed: u64, device: &Device| {
            let mut values = Values(Vec::new());
            VelocityUNet::new(&config, seed, device).visit(&mut values);
            values.0
        };
        for (backend, device) in cpu_devices() {
            let plain = weights(7, &device);
            assert!(
                plain.iter().any(|&v| v != 0.0),
                "{backend}: weights were drawn"
            );
            assert!(
                plain != weights(8, &device),
                "{backend}: the seed decides the weights"
            );
            let unet = VelocityUNet::new(&config, 7, &device);
            let _ = Tensor::<1>::random([64], Distribution::Default, &device).into_data();
            let mut drawn_between = Values(Vec::new());
            unet.visit(&mut drawn_between);
            assert!(
                plain == drawn_between.0,
                "{backend}: a draw between making Phi and using it moved its initial weights"
            );
            std::thread::scope(|scope| {
                let makers: Vec<_> = (0..4u64)
                    .map(|thread| {
                        let (device, weights) = (&device, &weights);
                        scope.spawn(move || {
                            (0..8)
                                .map(|_| weights(7 + thread % 2, device))
                                .collect::<Vec<_>>()
                        })
                    })
                    .collect();
                for (thread, maker) in makers.into_iter().enumerate() {
                    let expected = if thread % 2 == 0 {
                        plain.clone()
                    } else {
                        weights(8, &device)
                    };
                    for made in maker.join().unwrap() {
                        assert!(
                            made == expected,
                            "{backend}: threads making Phi at once moved each other's weights"
                        );
                    }
                }
            });
        }
    }

    #[test]
    fn refuses_bad_shapes() {
        let device = cpu_devices()[0].1.clone();
        let unet = VelocityUNet::new(
            &UNetConfig {
                base_channels: 2,
                time_frequencies: 1,
            },
            0,
            &device,
        );
        let (u, d) = inputs(&device, [8, 6, 4]);
        assert_eq!(
            unet.forward(u, d, 0.0).unwrap_err(),
            UNetError::Resolution {
                resolution: [8, 6, 4]
            }
        );
        let (u, _) = inputs(&device, [8, 8, 4]);
        let (_, d) = inputs(&device, [8, 8, 8]);
        assert!(matches!(
            unet.forward(u, d, 0.0),
            Err(UNetError::Shape {
                name: "density",
                ..
            })
        ));
    }
}
