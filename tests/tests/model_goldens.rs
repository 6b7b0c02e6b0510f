//! Density splatting, the Eq. 11 interpolation with its closed-form divergence, and one
//! forward of the U-Net Phi on fixed weights: values and gradients against the torch float64
//! reference. Splatting and the U-Net on every compiled backend (the cubecl kernels and
//! burn-wgpu's Conv3d too, on lavapipe in CI), interpolation (plain burn ops) on the CPU
//! backends.
//!
//! Tolerances (same reasoning as the renderer's goldens): values within `1e-5 * max|ref|`;
//! gradients element-wise within `1e-5 * (largest gradient of the case) + 5e-5 * max|g_ref|`
//! of the same tensor. f32 sums over a few hundred cells or 64 stencil nodes. The GPU kernels
//! get 4x these bounds, as the renderer's: device exp is not correctly rounded and the forward
//! adds atomically in no fixed order.

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_model::{GridSpec, Interpolation, density_grid, sample_velocity};
use gausmoke_render::GaussianTensors;
use gausmoke_render::backends::{all_devices, cpu_devices};
use gausmoke_tests::{Golden, assert_close};

fn tensor<const D: usize>(golden: &Golden, key: &str, device: &Device) -> Tensor<D> {
    let shape: [usize; D] = golden.shape(key).try_into().expect("rank");
    Tensor::from_data(TensorData::new(golden.get(key).to_vec(), shape), device)
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

/// Grid stored as `[lo (3), cell (3), resolution (3), ...]`.
fn grid_of(golden: &Golden) -> GridSpec {
    let g = golden.get("grid");
    let lo = Vec3::new(g[0], g[1], g[2]);
    let cell = Vec3::new(g[3], g[4], g[5]);
    let res = [g[6] as usize, g[7] as usize, g[8] as usize];
    let hi = lo + cell * Vec3::new(res[0] as f32, res[1] as f32, res[2] as f32);
    GridSpec::new(lo, hi, res, 1).unwrap()
}

fn check_grads(golden: &Golden, what: &str, pairs: &[(&str, Vec<f32>)]) {
    check_grads_scaled(golden, what, pairs, 1.0);
}

/// [`check_grads`] with both bounds multiplied by `slack`.
fn check_grads_scaled(golden: &Golden, what: &str, pairs: &[(&str, Vec<f32>)], slack: f32) {
    let case_scale = pairs
        .iter()
        .flat_map(|(k, _)| golden.get(&format!("grad_{k}")))
        .fold(0.0f32, |m, g| m.max(g.abs()));
    for (name, actual) in pairs {
        assert_close(
            &format!("{what}: grad {name}"),
            actual,
            golden.get(&format!("grad_{name}")),
            1e-5 * case_scale * slack,
            5e-5 * slack,
        );
    }
}

#[test]
fn density_splatting_matches_torch() {
    let golden = Golden::load("model_density_splat");
    let grid = grid_of(&golden);
    let cpu: Vec<_> = cpu_devices().into_iter().map(|(name, _)| name).collect();
    for (backend, device) in all_devices() {
        let slack = if cpu.contains(&backend) { 1.0 } else { 4.0 };
        let ad = device.autodiff();
        let n = golden.shape("raw_densities")[0];
        let g = GaussianTensors {
            means: tensor::<2>(&golden, "means", &ad).require_grad(),
            rotations: tensor::<2>(&golden, "rotations", &ad).require_grad(),
            log_scales: tensor::<2>(&golden, "log_scales", &ad).require_grad(),
            raw_densities: tensor::<1>(&golden, "raw_densities", &ad).require_grad(),
            colors: Tensor::zeros([n, 3], &ad),
        };
        let sigma = density_grid(&g, &grid, golden.get("grid")[9]);
        let scale = golden
            .get("sigma")
            .iter()
            .fold(0.0f32, |m, v| m.max(v.abs()));
        assert_close(
            &format!("density on {backend}"),
            &host(sigma.clone()),
            golden.get("sigma"),
            1e-5 * scale * slack,
            0.0,
        );
        let grads = (sigma * tensor::<3>(&golden, "weight", &ad))
            .sum()
            .backward();
        let grad2 = |t: &Tensor<2>| host(t.grad(&grads).unwrap());
        check_grads_scaled(
            &golden,
            &format!("density on {backend}"),
            &[
                ("means", grad2(&g.means)),
                ("rotations", grad2(&g.rotations)),
                ("log_scales", grad2(&g.log_scales)),
                ("raw_densities", host(g.raw_densities.grad(&grads).unwrap())),
            ],
            slack,
        );
    }
}

#[test]
fn kernel_interpolation_and_divergence_match_torch() {
    let golden = Golden::load("model_interp_gaussian");
    let grid = grid_of(&golden);
    let spec = golden.get("grid");
    let kind = Interpolation::Gaussian {
        stencil: spec[9] as usize,
        std_cells: spec[10],
    };
    for (backend, device) in cpu_devices() {
        let ad = device.autodiff();
        let velocity = tensor::<4>(&golden, "velocity", &ad).require_grad();
        let points = tensor::<2>(&golden, "points", &ad).require_grad();
        let s = sample_velocity(&grid, &velocity, &points, kind);
        let what = format!("interpolation on {backend}");
        assert_close(
            &format!("{what}: u"),
            &host(s.velocity.clone()),
            golden.get("u"),
            2e-5,
            0.0,
        );
        let jac_scale = golden
            .get("jacobian")
            .iter()
            .fold(0.0f32, |m, v| m.max(v.abs()));
        assert_close(
            &format!("{what}: jacobian"),
            &host(s.jacobian.clone()),
            golden.get("jacobian"),
            2e-5 * jac_scale,
            0.0,
        );
        let div = s.divergence();
        assert_close(
            &format!("{what}: divergence"),
            &host(div.clone()),
            golden.get("divergence"),
            2e-5 * jac_scale,
            0.0,
        );
        let loss = (s.velocity * tensor::<2>(&golden, "weight_velocity", &ad)).sum()
            + (div * tensor::<1>(&golden, "weight_divergence", &ad)).sum();
        let grads = loss.backward();
        check_grads(
            &golden,
            &what,
            &[
                ("velocity", host(velocity.grad(&grads).unwrap())),
                ("points", host(points.grad(&grads).unwrap())),
            ],
        );
    }
}

/// Sets every float parameter of a module from the golden's `param.<path>` tensors (burn's
/// and torch's conv weight layouts agree), counting how many it set.
struct GoldenWeights<'a> {
    golden: &'a Golden,
    device: Device,
    path: Vec<String>,
    loaded: Vec<String>,
}

impl burn::module::ModuleMapper for GoldenWeights<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(
        &mut self,
        param: burn::module::Param<Tensor<D>>,
    ) -> burn::module::Param<Tensor<D>> {
        let key = format!("param.{}", self.path.join("."));
        let shape: [usize; D] = self
            .golden
            .shape(&key)
            .try_into()
            .unwrap_or_else(|_| panic!("{key}: rank differs from the module's"));
        assert_eq!(param.val().dims(), shape, "{key}: shape differs");
        self.loaded.push(key.clone());
        let value = Tensor::<D>::from_data(
            TensorData::new(self.golden.get(&key).to_vec(), shape),
            &self.device,
        )
        .require_grad();
        burn::module::Param::initialized(param.id, value)
    }
}

#[test]
fn unet_forward_and_gradients_match_torch() {
    use burn::module::Module;
    use gausmoke_model::{UNetConfig, VelocityUNet};
    let golden = Golden::load("model_unet");
    let config = golden.get("config");
    let unet_config = UNetConfig {
        base_channels: config[0] as usize,
        time_frequencies: config[1] as usize,
    };
    let cpu: Vec<_> = cpu_devices().into_iter().map(|(name, _)| name).collect();
    for (backend, device) in all_devices() {
        let slack = if cpu.contains(&backend) { 1.0 } else { 4.0 };
        let ad = device.autodiff();
        let mut weights = GoldenWeights {
            golden: &golden,
            device: ad.clone(),
            path: Vec::new(),
            loaded: Vec::new(),
        };
        let unet = VelocityUNet::new(&unet_config, 0, &ad).map(&mut weights);
        // 5 double convolutions (2 layers each), 2 down, 2 up and the output layer.
        assert_eq!(weights.loaded.len(), 2 * 15, "{:?}", weights.loaded);
        let velocity = tensor::<4>(&golden, "velocity", &ad).require_grad();
        let density = tensor::<3>(&golden, "density", &ad).require_grad();
        let delta = unet
            .forward(velocity.clone(), density.clone(), config[2])
            .unwrap();
        let scale = golden
            .get("delta")
            .iter()
            .fold(0.0f32, |m, v| m.max(v.abs()));
        assert_close(
            &format!("U-Net delta on {backend}"),
            &host(delta.clone()),
            golden.get("delta"),
            1e-5 * scale * slack,
            0.0,
        );
        let grads = (delta * tensor::<4>(&golden, "weight", &ad))
            .sum()
            .backward();
        let param_grad = |path: &str| {
            let mut found = None;
            let mut finder = FindParam {
                path: Vec::new(),
                wanted: path,
                grads: &grads,
                found: &mut found,
            };
            unet.visit(&mut finder);
            found.unwrap_or_else(|| panic!("no gradient for {path}"))
        };
        check_grads_scaled(
            &golden,
            &format!("U-Net on {backend}"),
            &[
                ("velocity", host(velocity.grad(&grads).unwrap())),
                ("density", host(density.grad(&grads).unwrap())),
                ("encode1.first.weight", param_grad("encode1.first.weight")),
                ("output.weight", param_grad("output.weight")),
            ],
            slack,
        );
    }
}

/// Reads the gradient of the float parameter at `wanted` (a dotted module path).
struct FindParam<'a> {
    path: Vec<String>,
    wanted: &'a str,
    grads: &'a burn::tensor::Gradients,
    found: &'a mut Option<Vec<f32>>,
}

impl burn::module::ModuleVisitor for FindParam<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
        if self.path.join(".") == self.wanted {
            *self.found = param.val().grad(self.grads).map(host);
        }
    }
}
