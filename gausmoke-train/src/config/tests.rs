use super::*;

#[test]
fn overrides_reach_nested_keys_and_round_trip_through_toml() {
    let config = TrainConfig::default()
        .with_overrides(&[
            "lambda_div=0.5".into(),
            "image_size=[135, 240]".into(),
            "init_learning_rates.means=0.01".into(),
            "projection=penalty".into(),
        ])
        .unwrap();
    assert_eq!(config.lambda_div, 0.5);
    assert_eq!(config.image_size, Some([135, 240]));
    assert_eq!(config.init_learning_rates.means, 0.01);
    assert_eq!(config.projection, ProjectionKind::Penalty);
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
        .with_overrides(&["init_learning_rates=[]".into()])
        .unwrap_err();
    assert!(err.to_string().contains("init_learning_rates"), "{err}");
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
            TrainConfig {
                increment_horizontal_weight: 10.0,
                ..TrainConfig::default()
            },
            "lambda_increment",
        ),
        (
            TrainConfig {
                increment_horizontal_weight: -1.0,
                lambda_increment: 0.01,
                ..TrainConfig::default()
            },
            "increment_horizontal_weight",
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
        .with_overrides(&["gradient_sums=per-pixel".into()])
        .unwrap();
    assert_eq!(
        config.raster_options().gradient_sums,
        gausmoke_render::GradientSums::PerPixel
    );
    let err = TrainConfig::default()
        .with_overrides(&["gradient_sums=warp".into()])
        .unwrap_err();
    assert!(err.to_string().contains("warp"), "{err}");
}

#[test]
fn solver_tests_are_spelled_for_toml_and_bad_spellings_are_refused() {
    assert_eq!(TrainConfig::default().solver_tests, SolverTests::Deferred);
    let config = TrainConfig::default()
        .with_overrides(&["solver_tests=immediate".into()])
        .unwrap();
    assert_eq!(
        gausmoke_model::ConvergenceTests::from(config.solver_tests),
        gausmoke_model::ConvergenceTests::Immediate
    );
    let err = TrainConfig::default()
        .with_overrides(&["solver_tests=sometimes".into()])
        .unwrap_err();
    assert!(err.to_string().contains("sometimes"), "{err}");
    assert!(RESUMABLE_KEYS.contains(&"solver_tests"));
}

/// Values that cannot train are refused naming the key: a decay that grows, learning rates
/// above 1, a huge time step or tolerance, a view named twice (issue 81 item 3).
#[test]
fn nonsense_values_are_refused_naming_the_key() {
    for (set, named) in [
        ("lr_decay=1e12", "lr_decay"),
        ("lr_velocity=1e12", "lr_velocity"),
        ("lr_gaussians=2", "lr_gaussians"),
        ("lr_log_scales=1e12", "lr_log_scales"),
        ("init_iterations=1000000000000", "init_iterations"),
        ("refine_iterations=1000000000000", "refine_iterations"),
        ("static_gaussians=1000000000000", "static_gaussians"),
        ("init_learning_rates.means=5", "init_learning_rates.means"),
        ("dt=1e12", "dt"),
        ("projection_tolerance=1e12", "projection_tolerance"),
        ("tile_list_headroom=1e12", "tile_list_headroom"),
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
