//! The synthetic generator writes the tiny preset; the PINF loader reads it back.

use gausmoke_core::glam::Vec3;
use gausmoke_data::synth::{self, Solver, SynthConfig};
use gausmoke_data::{LoadOptions, Split, load_pinf};

#[test]
fn tiny_scene_round_trips_through_the_pinf_loader() {
    let cfg = SynthConfig::tiny();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("tiny");
    let scene = synth::generate(&cfg, &out).unwrap();
    assert!(!tmp.path().join(".tiny.partial").exists());
    let ds = load_pinf(&out, &LoadOptions::default()).unwrap();
    assert_eq!(ds.views.len(), 3);
    assert_eq!(ds.views_in(Split::Test).count(), 1);
    assert_eq!(ds.view("view01").unwrap().split, Split::Test);
    assert_eq!(ds.times.len(), 8);
    let bbox = ds.bbox.unwrap();
    let (lo, hi) = synth::world_box();
    assert!(
        (bbox.min - lo).length() < 1e-6 && (bbox.max - hi).length() < 1e-6,
        "{bbox:?}"
    );
    let mut max_pixel = 0.0f32;
    for (k, cam) in scene.cameras.iter().enumerate() {
        let view = ds.view(&format!("view{k:02}")).unwrap();
        assert_eq!(view.frames.len(), 8);
        for (t, f) in view.frames.iter().enumerate() {
            // Cameras: same size, intrinsics and pose as generated.
            assert_eq!((f.camera.width(), f.camera.height()), (64, 96));
            let (a, b) = (f.camera.intrinsics(), cam.intrinsics());
            assert!((a.fx - b.fx).abs() < 1e-3 && (a.cx - b.cx).abs() < 1e-6);
            assert!(
                f.camera
                    .camera_to_world()
                    .abs_diff_eq(cam.camera_to_world(), 1e-6)
            );
            // Pixels: the PNG holds the marcher's value to 8 bits.
            let written = &scene.frames[k][t];
            for (x, y) in written.data().iter().zip(f.image.data()) {
                assert!((x.clamp(0.0, 1.0) - y).abs() <= 0.5 / 255.0 + 1e-6);
            }
            max_pixel = max_pixel.max(f.image.data().iter().copied().fold(0.0, f32::max));
        }
        // The box centre is seen by every camera.
        assert!(cam.project(bbox.center()).is_some());
    }
    assert!(
        max_pixel > 0.2,
        "the plume should be visible, max pixel {max_pixel}"
    );

    // Ground truth: one file per frame with density [24,24,24] and velocity [24,24,24,3].
    let bytes = std::fs::read(out.join("gt/frame_007.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let d = st.tensor("density").unwrap();
    assert_eq!(d.shape(), [24, 24, 24]);
    assert_eq!(st.tensor("velocity").unwrap().shape(), [24, 24, 24, 3]);
    let density: Vec<f32> = d
        .data()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    assert!(density.iter().any(|&v| v > 0.5));

    // Inspection: the summary and a contact sheet with the box drawn in red.
    let text = gausmoke_data::inspect::summary(&ds);
    assert!(text.contains("3 views, 8 distinct times"), "{text}");
    let sheet = gausmoke_data::inspect::contact_sheet(&ds).unwrap();
    assert_eq!((sheet.width(), sheet.height()), (3 * 64, 3 * 96));
    let red = sheet
        .data()
        .chunks_exact(3)
        .filter(|p| p == &[1.0, 0.0, 0.0])
        .count();
    assert!(red > 100, "{red} red pixels");

    // Refuses to overwrite.
    assert!(synth::generate(&cfg, &out).is_err());
}

#[test]
fn solver_is_seeded_and_projection_reduces_divergence() {
    let cfg = SynthConfig::tiny();
    let run = |seed: u64| {
        let mut s = Solver::new(&SynthConfig {
            seed,
            ..cfg.clone()
        })
        .unwrap();
        for _ in 0..4 {
            s.step_frame();
        }
        s
    };
    let (a, b, c) = (run(1), run(1), run(2));
    assert_eq!(a.density.data, b.density.data);
    assert_ne!(a.density.data, c.density.data);
    // Vorticity confinement acts (and can be switched off).
    let mut calm = Solver::new(&SynthConfig {
        seed: 1,
        vorticity: 0.0,
        ..cfg.clone()
    })
    .unwrap();
    for _ in 0..4 {
        calm.step_frame();
    }
    assert_ne!(calm.velocity[0].data, a.velocity[0].data);
    // The plume rises: the density's centre of mass moves up over time.
    let com_y = |s: &Solver| {
        let n = s.density.n;
        let (mut m, mut my) = (0.0f64, 0.0f64);
        for (i, &d) in s.density.data.iter().enumerate() {
            m += d as f64;
            my += d as f64 * ((i / n) % n) as f64;
        }
        my / m
    };
    let mut s = run(1);
    let before = com_y(&s);
    for _ in 0..4 {
        s.step_frame();
    }
    assert!(com_y(&s) > before, "{} -> {}", before, com_y(&s));
    // Fewer Jacobi iterations leave more divergence.
    let div_with = |iters: usize| {
        let mut s = Solver::new(&SynthConfig {
            jacobi_iterations: iters,
            ..cfg.clone()
        })
        .unwrap();
        for _ in 0..4 {
            s.step_frame();
        }
        s.mean_abs_divergence()
    };
    let (none, many) = (div_with(0), div_with(200));
    eprintln!("mean |div u|: no projection {none:.4}, 200 Jacobi iterations {many:.4}");
    assert!(many < 0.5 * none, "{none} vs {many}");
}

/// The long preset is the drift test: smoke must reach the open top within the first half of
/// the video and flow out through it while the source keeps feeding the plume.
#[test]
fn long_plume_leaves_through_the_top() {
    let cfg = SynthConfig::long_plume();
    assert!(cfg.frames >= 60, "{} frames", cfg.frames);
    let mut s = Solver::new(&cfg).unwrap();
    let n = s.density.n;
    let top = |s: &Solver| {
        let (mut smoke, mut upward) = (0.0f32, 0.0f32);
        for z in 0..n {
            for x in 0..n {
                let i = (z * n + n - 1) * n + x;
                smoke += s.density.data[i];
                upward += s.density.data[i] * s.velocity[1].data[i];
            }
        }
        (smoke, upward)
    };
    let mass = |s: &Solver| s.density.data.iter().sum::<f32>();
    for _ in 0..10 {
        s.step_frame();
    }
    assert_eq!(top(&s).0, 0.0, "smoke at the top by frame 10");
    for _ in 10..cfg.frames / 2 {
        s.step_frame();
    }
    let (smoke, upward) = top(&s);
    assert!(
        smoke > 1.0,
        "top layer holds {smoke} by frame {}",
        cfg.frames / 2
    );
    assert!(upward > 0.0, "smoke in the top layer moves down ({upward})");
    // The source still feeds it: mass keeps growing after the plume reached the top.
    let halfway = mass(&s);
    for _ in cfg.frames / 2..cfg.frames {
        s.step_frame();
    }
    assert!(mass(&s) > halfway, "{} -> {}", halfway, mass(&s));
}

#[test]
fn turning_plume_turns_about_its_axis() {
    // The smoke's mean angular velocity about the source's axis, in degrees per frame
    // (density-weighted, cells at least 2 from the axis).
    let turn = |cfg: &SynthConfig| {
        let mut s = Solver::new(cfg).unwrap();
        for _ in 0..20 {
            s.step_frame();
        }
        let n = s.density.n;
        let centre = 0.5 * n as f32;
        let (mut mass, mut turning) = (0.0f64, 0.0f64);
        for (i, &d) in s.density.data.iter().enumerate() {
            let (x, z) = (i % n, i / (n * n));
            let (dx, dz) = (x as f32 + 0.5 - centre, z as f32 + 0.5 - centre);
            let r2 = dx * dx + dz * dz;
            if r2 < 4.0 {
                continue;
            }
            let along = (s.velocity[0].data[i] * dz - s.velocity[2].data[i] * dx) / r2;
            mass += d as f64;
            turning += (d * along) as f64;
        }
        ((turning / mass) as f32).to_degrees()
    };
    let still = turn(&SynthConfig::long_plume());
    let turning = SynthConfig::turning_plume();
    let turns = turn(&turning);
    assert!(
        still.abs() < 0.3,
        "the long plume turns {still} degrees/frame"
    );
    assert!(
        turns > 0.5 * turning.swirl_degrees && turns < 1.1 * turning.swirl_degrees,
        "the turning plume turns {turns} degrees/frame, set {}",
        turning.swirl_degrees
    );
    let backwards = turn(&SynthConfig {
        swirl_degrees: -turning.swirl_degrees,
        ..turning
    });
    assert!(
        (backwards + turns).abs() < 0.5,
        "{backwards} against {turns}"
    );
}

/// No smoke and no velocity in the `solid` cells of `s` after `frame`.
fn assert_nothing_in(s: &Solver, solid: &[usize], frame: usize) {
    for &i in solid {
        let values = [
            s.density.data[i],
            s.velocity[0].data[i],
            s.velocity[1].data[i],
            s.velocity[2].data[i],
        ];
        assert_eq!(values, [0.0; 4], "frame {frame}, cell {i}");
    }
}

/// The obstacle preset: no smoke and no velocity ever inside the sphere, the plume gets past
/// it (smoke above it, sideways flow beside it), and where the free plume rises through the
/// sphere's place the obstacle's stands still.
#[test]
fn obstacle_plume_flows_around_the_sphere() {
    let cfg = SynthConfig::obstacle_plume();
    let gausmoke_data::Obstacle::Sphere { centre, radius } = cfg.solids[0].shape else {
        panic!("the obstacle preset's solid is a sphere");
    };
    let mut s = Solver::new(&cfg).unwrap();
    let mut free = Solver::new(&SynthConfig {
        solids: Vec::new(),
        ..cfg.clone()
    })
    .unwrap();
    let n = s.density.n;
    let solid: Vec<usize> = (0..n * n * n).filter(|&i| s.solid[i]).collect();
    assert!(solid.len() > 100, "{} solid cells", solid.len());
    let (lo, hi) = synth::world_box();
    let top_cell = ((centre.y + radius - lo.y) / (hi.y - lo.y) * n as f32) as usize;
    for frame in 0..30 {
        s.step_frame();
        free.step_frame();
        assert_nothing_in(&s, &solid, frame);
    }
    let above: f32 = (top_cell + 1..n)
        .flat_map(|y| (0..n * n).map(move |zx| (zx / n * n + y) * n + zx % n))
        .map(|i| s.density.data[i])
        .sum();
    assert!(above > 1.0, "smoke above the obstacle: {above}");
    // Just under the sphere the flow turns outwards, away from its axis.
    let cell = (hi - lo) / n as f32;
    let outward = |solver: &Solver| -> f32 {
        let mut sum = 0.0;
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let p = lo
                        + cell
                            * (gausmoke_data::glam::Vec3::new(x as f32, y as f32, z as f32) + 0.5);
                    let d = p - centre;
                    let shell = d.length() - radius;
                    if !(0.0..2.0 * cell.x).contains(&shell) || d.y > 0.0 {
                        continue;
                    }
                    let i = (z * n + y) * n + x;
                    let h = gausmoke_data::glam::Vec2::new(d.x, d.z).normalize_or_zero();
                    sum += h.x * solver.velocity[0].data[i] + h.y * solver.velocity[2].data[i];
                }
            }
        }
        sum
    };
    let (with, without) = (outward(&s), outward(&free));
    assert!(
        with > 0.0 && with > 2.0 * without.abs(),
        "outward flow under the sphere {with} with the obstacle, {without} without"
    );
    let rising_free: f32 = solid.iter().map(|&i| free.velocity[1].data[i]).sum();
    assert!(
        rising_free > 0.1 * solid.len() as f32,
        "the free plume does not pass the sphere's place ({rising_free})"
    );
}

/// `info.json` describes the obstacle; the loader reads it back, and refuses a bad one naming
/// the field.
#[test]
fn obstacles_round_trip_through_the_pinf_loader() {
    let cfg = SynthConfig {
        frames: 2,
        solids: SynthConfig::obstacle_plume().solids,
        ..SynthConfig::tiny()
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("ball");
    synth::generate(&cfg, &out).unwrap();
    let ds = load_pinf(&out, &LoadOptions::default()).unwrap();
    assert_eq!(ds.obstacles, vec![cfg.solids[0].shape]);
    assert_eq!(
        gausmoke_data::read_obstacles(&out).unwrap(),
        ds.obstacles,
        "the description alone gives the loader's obstacles"
    );
    let info = out.join("info.json");
    let text = std::fs::read_to_string(&info).unwrap();
    // A box beside the sphere, and a box turned inside out.
    let with_box = |max: &str| {
        let mut value: serde_json::Value = serde_json::from_str(&text).unwrap();
        let cuboid: serde_json::Value = serde_json::from_str(&format!(
            r#"{{"box": {{"min": [-0.1, 0.05, -0.1], "max": {max}}}}}"#
        ))
        .unwrap();
        value["obstacles"].as_array_mut().unwrap().push(cuboid);
        std::fs::write(&info, value.to_string()).unwrap();
        load_pinf(&out, &LoadOptions::default())
    };
    let ds = with_box("[0.1, 0.15, 0.1]").unwrap();
    assert_eq!(
        ds.obstacles[1],
        gausmoke_data::Obstacle::Box {
            min: Vec3::new(-0.1, 0.05, -0.1),
            max: Vec3::new(0.1, 0.15, 0.1)
        }
    );
    assert_eq!(gausmoke_data::read_obstacles(&out).unwrap(), ds.obstacles);
    let err = with_box("[0.1, 0.0, 0.1]").unwrap_err().to_string();
    assert!(
        err.contains("obstacles[1].box") && err.contains("min"),
        "{err}"
    );
    let err = gausmoke_data::read_obstacles(&out).unwrap_err().to_string();
    assert!(
        err.contains("info.json") && err.contains("obstacles[1].box"),
        "{err}"
    );
    std::fs::write(&info, text.replace("\"sphere\"", "\"ball\"")).unwrap();
    let err = load_pinf(&out, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("obstacles[0]") && err.contains("box"), "{err}");
    std::fs::write(&info, text.replace("\"radius\"", "\"raduis\"")).unwrap();
    let err = load_pinf(&out, &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("radius") && err.contains("obstacles"), "{err}");
    // Without the key there are none (every published data set).
    let tiny = tmp.path().join("tiny");
    synth::generate(
        &SynthConfig {
            frames: 1,
            ..SynthConfig::tiny()
        },
        &tiny,
    )
    .unwrap();
    assert!(
        load_pinf(&tiny, &LoadOptions::default())
            .unwrap()
            .obstacles
            .is_empty()
    );
    assert!(gausmoke_data::read_obstacles(&tiny).unwrap().is_empty());
    // Read from the description alone: with every camera's frames gone, the loader fails
    // and the obstacles are still there.
    std::fs::write(&info, &text).unwrap();
    for entry in std::fs::read_dir(&out).unwrap() {
        let path = entry.unwrap().path();
        if path.file_name().is_some_and(|n| n != "info.json") {
            if path.is_dir() {
                std::fs::remove_dir_all(&path).unwrap();
            } else {
                std::fs::remove_file(&path).unwrap();
            }
        }
    }
    assert!(load_pinf(&out, &LoadOptions::default()).is_err());
    assert_eq!(
        gausmoke_data::read_obstacles(&out).unwrap(),
        vec![cfg.solids[0].shape]
    );
    assert_eq!(
        gausmoke_data::read_obstacles(&info).unwrap(),
        vec![cfg.solids[0].shape],
        "the path of info.json itself"
    );
    let err = gausmoke_data::read_obstacles(tmp.path())
        .unwrap_err()
        .to_string();
    assert!(err.contains("info.json"), "{err}");
}

/// The blocks preset: no smoke and no velocity ever inside the block or the wall, the plume
/// gets past the block, every camera sees the wall's two checker shades behind the smoke,
/// and `info.json` describes both boxes for the loader.
#[test]
fn blocks_plume_keeps_out_of_its_boxes_and_shows_the_wall() {
    let cfg = SynthConfig::blocks_plume();
    let mut s = Solver::new(&cfg).unwrap();
    let n = s.density.n;
    let (lo, hi) = synth::world_box();
    let cell = (hi - lo) / n as f32;
    let centre = |i: usize| {
        let (x, y, z) = (i % n, i / n % n, i / (n * n));
        lo + cell * (Vec3::new(x as f32, y as f32, z as f32) + 0.5)
    };
    let solid: Vec<usize> = (0..n * n * n).filter(|&i| s.solid[i]).collect();
    for (k, solid_k) in cfg.solids.iter().enumerate() {
        let cells = solid.iter().filter(|&&i| solid_k.shape.contains(centre(i)));
        assert!(cells.count() > 100, "solid {k} fills too few cells");
    }
    assert!(
        solid
            .iter()
            .all(|&i| cfg.solids.iter().any(|b| b.shape.contains(centre(i))))
    );
    for frame in 0..24 {
        s.step_frame();
        assert_nothing_in(&s, &solid, frame);
    }
    let above_block: f32 = (0..n * n * n)
        .filter(|&i| centre(i).y > 0.5)
        .map(|i| s.density.data[i])
        .sum();
    assert!(above_block > 1.0, "smoke above the block: {above_block}");

    // Without smoke, each camera sees the wall's two shades and the background.
    let lit = 0.3 + 0.7 * 0.5 / 1.34f32.sqrt();
    let empty = synth::Grid {
        n,
        data: vec![0.0; n * n * n],
    };
    for camera in synth::cameras(&cfg).unwrap() {
        let image = synth::render(
            &empty,
            &camera,
            cfg.density_scale,
            cfg.background,
            &cfg.solids,
        )
        .unwrap();
        let count = |value: f32| {
            image
                .data()
                .chunks(3)
                .filter(|p| p.iter().all(|c| (c - value).abs() < 1e-5))
                .count()
        };
        let pixels = (image.width() * image.height()) as usize;
        let (dark, light) = (count(0.35 * lit), count(0.75 * lit));
        assert!(
            dark > pixels / 20 && light > pixels / 20,
            "{dark} dark and {light} light wall pixels of {pixels}"
        );
        let background = image
            .data()
            .chunks(3)
            .filter(|p| **p == cfg.background)
            .count();
        assert!(background > pixels / 20, "{background} background pixels");
    }

    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("blocks");
    synth::generate(
        &SynthConfig {
            frames: 1,
            ..cfg.clone()
        },
        &out,
    )
    .unwrap();
    let ds = load_pinf(&out, &LoadOptions::default()).unwrap();
    let shapes: Vec<_> = cfg.solids.iter().map(|s| s.shape).collect();
    assert_eq!(ds.obstacles, shapes);
}

/// The Blender layout: D-NeRF files the D-NeRF loader reads back as one view per training
/// camera and the held-out middle one, with the generator's poses, times from 0 to 1, the
/// smoke box and the solids; its RGBA frames, composited over the scene's background, give
/// the marcher's pictures to 8 bits of colour and alpha; over black, the solids stay opaque
/// and the background goes.
#[test]
fn blender_layout_round_trips_through_the_dnerf_loader() {
    let cfg = SynthConfig {
        grid: 24,
        views: 4,
        frames: 3,
        width: 40,
        height: 32,
        arc_degrees: 270.0,
        ..SynthConfig::blender_blocks()
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("blender");
    let scene = synth::generate(&cfg, &out).unwrap();
    assert!(out.join("transforms_train.json").is_file());
    assert!(out.join("test/view02_002.png").is_file());
    assert!(!out.join("info.json").exists());
    let over = |background| gausmoke_data::LoadOptions {
        background: Some(background),
        ..LoadOptions::default()
    };
    let ds = gausmoke_data::load_dnerf(&out, &over(cfg.background)).unwrap();
    let names: Vec<&str> = ds.views.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["train_00", "train_01", "train_02", "test"]);
    assert_eq!(ds.times, [0.0, 0.5, 1.0]);
    let shapes: Vec<_> = cfg.solids.iter().map(|s| s.shape).collect();
    assert_eq!(ds.obstacles, shapes);
    assert_eq!(gausmoke_data::read_obstacles(&out).unwrap(), shapes);
    assert_eq!(
        gausmoke_data::Format::detect(&out),
        Some(gausmoke_data::Format::DNerf)
    );
    let bbox = ds.bbox.unwrap();
    let (lo, hi) = synth::world_box();
    assert!((bbox.min - lo).length() < 1e-6 && (bbox.max - hi).length() < 1e-6);
    // Training cameras 0, 1, 3 in order, then the middle one.
    for (view, k) in ds.views.iter().zip([0, 1, 3, 2]) {
        assert_eq!(view.frames.len(), 3);
        for (t, frame) in view.frames.iter().enumerate() {
            assert!(
                frame
                    .camera
                    .camera_to_world()
                    .abs_diff_eq(scene.cameras[k].camera_to_world(), 1e-6)
            );
            // Straight colour and alpha each round to 8 bits.
            let written = &scene.frames[k][t];
            for (x, y) in written.data().iter().zip(frame.image.data()) {
                assert!(
                    (x - y).abs() <= 1.5 / 255.0,
                    "view {k} frame {t}: {x} against {y}"
                );
            }
        }
    }
    // Over black the grey-blue background is gone and the wall stays.
    let black = gausmoke_data::load_dnerf(&out, &over([0.0; 3])).unwrap();
    let picture = &black.views[3].frames[0].image;
    let corner = picture.pixel(0, 0);
    assert_eq!(corner, [0.0; 3], "the background is transparent");
    let centre = picture.pixel(20, 16);
    assert!(centre[0] > 0.15, "the wall is opaque: {centre:?}");
    // The synthetic density scale rides along for the evaluation's ground truth.
    let train: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("transforms_train.json")).unwrap())
            .unwrap();
    assert_eq!(train["synth"]["density_scale"], 5.0);
}

#[test]
fn two_generators_into_one_folder_take_turns() {
    // Two processes that need the same scene (two `reproduce` runs started together) must
    // not build it in one partial folder at once: one writes it, the other is refused
    // because the folder is then full, and what is left is one whole scene.
    let cfg = SynthConfig::tiny();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("tiny");
    let results: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..2)
            .map(|_| s.spawn(|| synth::generate(&cfg, &out).map(|_| ())))
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let written = results.iter().filter(|r| r.is_ok()).count();
    assert_eq!(written, 1, "{results:?}");
    let refused = results.iter().find_map(|r| r.as_ref().err()).unwrap();
    assert!(
        refused.to_string().contains("exists and is not empty"),
        "{refused}"
    );
    assert!(!tmp.path().join(".tiny.partial").exists());
    let ds = load_pinf(&out, &LoadOptions::default()).unwrap();
    assert_eq!(ds.times.len(), cfg.frames);
    for view in &ds.views {
        assert_eq!(view.frames.len(), cfg.frames, "{}", view.name);
    }
}
