use super::*;

#[test]
fn overrides_reach_nested_keys_and_round_trip_through_toml() {
    let config = TrainConfig::default()
        .with_overrides(&[
            "joint.lambda_div=0.5".into(),
            "image_size=[135, 240]".into(),
            "init.learning_rates.means=0.01".into(),
            "projection.kind=penalty".into(),
        ])
        .unwrap();
    assert_eq!(config.joint.lambda_div, 0.5);
    assert_eq!(config.image_size, Some([135, 240]));
    assert_eq!(config.init.learning_rates.means, 0.01);
    assert_eq!(config.projection.kind, ProjectionKind::Penalty);
    let back: TrainConfig = toml::from_str(&config.to_toml()).unwrap();
    assert_eq!(back, config);
}

#[test]
fn unknown_keys_and_bad_values_are_named() {
    let err = TrainConfig::default()
        .with_overrides(&["lamda_div=0.5".into()])
        .unwrap_err();
    assert!(err.to_string().contains("lamda_div"), "{err}");
    // A table given as an array is not read as the defaults.
    let err = TrainConfig::default()
        .with_overrides(&["init.learning_rates=[]".into()])
        .unwrap_err();
    assert!(err.to_string().contains("init.learning_rates"), "{err}");
    // Each invalid configuration is refused naming the setting to change.
    let invalid = [
        (
            TrainConfig {
                grid_resolution: 30,
                ..TrainConfig::default()
            },
            "grid_resolution",
        ),
        (
            {
                let mut config = TrainConfig::default();
                config.joint.inertia.horizontal_weight = 10.0;
                config
            },
            "joint.inertia.weight",
        ),
        (
            {
                let mut config = TrainConfig::default();
                config.joint.inertia.horizontal_weight = -1.0;
                config.joint.inertia.weight = 0.01;
                config
            },
            "joint.inertia.horizontal_weight",
        ),
        (
            TrainConfig {
                scene: SceneConfig {
                    open_faces: Some(Vec::new()),
                    open_face_flow: Some(0.5),
                    ..SceneConfig::default()
                },
                ..TrainConfig::default()
            },
            "set scene.open_faces",
        ),
        (
            TrainConfig {
                scene: SceneConfig {
                    open_faces: Some(vec!["y+".into()]),
                    open_face_flow: Some(1.5),
                    ..SceneConfig::default()
                },
                ..TrainConfig::default()
            },
            "scene.open_face_flow",
        ),
        (
            TrainConfig {
                scene: SceneConfig {
                    open_faces: Some(vec!["y+".into()]),
                    open_face_flow: Some(f32::NAN),
                    ..SceneConfig::default()
                },
                ..TrainConfig::default()
            },
            "scene.open_face_flow",
        ),
    ];
    for (config, named) in invalid {
        let err = config.validate().unwrap_err();
        assert!(err.to_string().contains(named), "{err}");
    }
    let region = |value: &str| {
        TrainConfig::default()
            .with_overrides(&[format!("scene.inflow={value}")])
            .and_then(|config| config.validate().map(|()| config))
    };
    let config = region("[0.3, 0, 0.3, 0.7, 0.15, 0.7]").unwrap();
    assert_eq!(config.scene.inflow, Some([0.3, 0.0, 0.3, 0.7, 0.15, 0.7]));
    for bad in ["[0.3, 0, 0.3, 0.2, 0.15, 0.7]", "[0, 0, 0, 1, 1, 1.5]"] {
        let err = region(bad).unwrap_err();
        assert!(err.to_string().contains("scene.inflow"), "{bad}: {err}");
    }
    // A half-open top reaches the projection's faces.
    let half_open = TrainConfig::default()
        .with_overrides(&[
            "scene.open_faces=[\"y+\"]".into(),
            "scene.open_face_flow=0.5".into(),
        ])
        .unwrap();
    half_open.validate().unwrap();
    let faces = half_open.open_faces().unwrap();
    assert_eq!(faces.face_flows(), [0.0, 0.0, 0.0, 0.5, 0.0, 0.0]);
}

#[test]
fn gradient_sums_reach_the_rasterizer_and_bad_spellings_are_refused() {
    assert_eq!(
        TrainConfig::default().raster_options().gradient_sums,
        gausmoke_render::GradientSums::Planes
    );
    let config = TrainConfig::default()
        .with_overrides(&["device.gradient_sums=per-pixel".into()])
        .unwrap();
    assert_eq!(
        config.raster_options().gradient_sums,
        gausmoke_render::GradientSums::PerPixel
    );
    let err = TrainConfig::default()
        .with_overrides(&["device.gradient_sums=warp".into()])
        .unwrap_err();
    assert!(err.to_string().contains("warp"), "{err}");
}

#[test]
fn solver_tests_are_spelled_for_toml_and_bad_spellings_are_refused() {
    assert_eq!(
        TrainConfig::default().device.solver_tests,
        SolverTests::Deferred
    );
    let config = TrainConfig::default()
        .with_overrides(&["device.solver_tests=immediate".into()])
        .unwrap();
    assert_eq!(
        gausmoke_model::ConvergenceTests::from(config.device.solver_tests),
        gausmoke_model::ConvergenceTests::Immediate
    );
    let err = TrainConfig::default()
        .with_overrides(&["device.solver_tests=sometimes".into()])
        .unwrap_err();
    assert!(err.to_string().contains("sometimes"), "{err}");
    assert!(is_resumable("device.solver_tests"));
}

/// Values that cannot train are refused naming the key: a decay that grows, learning rates
/// above 1, a huge time step or tolerance, a view named twice (issue 81 item 3).
#[test]
fn nonsense_values_are_refused_naming_the_key() {
    for (set, named) in [
        ("learning_rates.decay=1e12", "learning_rates.decay"),
        ("learning_rates.velocity=1e12", "learning_rates.velocity"),
        ("learning_rates.gaussians=2", "learning_rates.gaussians"),
        (
            "learning_rates.log_scales=1e12",
            "learning_rates.log_scales",
        ),
        ("init.iterations=1000000000000", "init.iterations"),
        ("refine.iterations=1000000000000", "refine.iterations"),
        ("static_gaussians=1000000000000", "static_gaussians"),
        ("init.learning_rates.means=5", "init.learning_rates.means"),
        ("dt=1e12", "dt"),
        ("projection.tolerance=1e12", "projection.tolerance"),
        (
            "device.tile_list_headroom=1e12",
            "device.tile_list_headroom",
        ),
        (r#"train_views=["view00", "view00"]"#, "view00"),
    ] {
        let err = TrainConfig::default()
            .with_overrides(&[set.to_string()])
            .and_then(|config| config.validate())
            .unwrap_err()
            .to_string();
        assert!(err.contains(named), "{set}: {err}");
    }
}
