//! A data set arranged for training: per frame, the (camera, image) pairs of the training
//! views and of the held-out views, the background and the smoke box.

use std::path::{Path, PathBuf};

use gausmoke_core::Camera;
use gausmoke_core::glam::Vec3;
use gausmoke_data::{Dataset, Format, Image, LoadOptions, Obstacle, PlannedView, Split};

use crate::hash::Fnv1a;
use crate::{TrainConfig, TrainError};

/// One observation: a camera and what it saw.
#[derive(Debug, Clone)]
pub struct Observation {
    pub view: String,
    pub camera: Camera,
    pub image: Image,
}

/// The sequence to reconstruct: per frame, what the training and held-out cameras saw.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The data set's path as given.
    pub path: PathBuf,
    /// `train[t]`: training observations at frame `t`.
    pub train: Vec<Vec<Observation>>,
    /// `test[t]`: held-out observations at frame `t` (may be empty).
    pub test: Vec<Vec<Observation>>,
    pub background: [f32; 3],
    /// Smoke box, world units.
    pub lo: Vec3,
    pub hi: Vec3,
    /// `<path>/gt`: per-frame ground truth written by the synthetic generator, if present.
    pub ground_truth: Option<PathBuf>,
    /// The data's frame that is frame 0 here (`first_frame` of the configuration).
    pub first_frame: usize,
    /// Density scale the synthetic generator rendered with (sigma = scale * density).
    pub ground_truth_density_scale: Option<f32>,
    /// Solids inside the box that the data set describes (see `TrainConfig::obstacles`).
    pub obstacles: Vec<Obstacle>,
}

impl Sequence {
    pub fn frames(&self) -> usize {
        self.train.len()
    }

    /// A 64-bit FNV-1a hash of what makes two data sets the same for a run, as 16 hex digits:
    /// the smoke box, every view's name, image size and camera (pose and intrinsics, bit for
    /// bit), and frame 0's images. Not the frame count, so that a run can be extended with
    /// `frames`. Resuming refuses a different one.
    pub fn fingerprint(&self) -> String {
        let mut hash = Fnv1a::default();
        for value in self.lo.to_array().iter().chain(&self.hi.to_array()) {
            hash.write(&value.to_bits().to_le_bytes());
        }
        let first = self.train.first().into_iter().chain(self.test.first());
        for observation in first.flatten() {
            let camera = &observation.camera;
            hash.write(observation.view.as_bytes());
            hash.write(&[0]);
            hash.write(&camera.width().to_le_bytes());
            hash.write(&camera.height().to_le_bytes());
            let k = camera.intrinsics();
            let pose = camera.camera_to_world().to_cols_array();
            for value in [k.fx, k.fy, k.cx, k.cy].iter().chain(&pose) {
                hash.write(&value.to_bits().to_le_bytes());
            }
            for value in observation.image.data() {
                hash.write(&value.to_bits().to_le_bytes());
            }
        }
        hash.hex()
    }

    /// Loads the data set in the folder `path` (any format [`Format::detect`] knows) at the
    /// configured image size and frame count, and splits views as configured.
    pub fn open(path: &Path, config: &TrainConfig) -> Result<Self, TrainError> {
        let options = Self::load_options(config);
        if Format::detect(path).is_none() {
            return Err(TrainError::Dataset {
                path: path.to_path_buf(),
                reason: "none of info.json (PINF/HyFluid), transforms_train.json (D-NeRF), \
                         transforms.json (nerfstudio) and rig.json (a COLMAP rig) found"
                    .into(),
            });
        }
        let dataset = gausmoke_data::load(path, &options)?;
        Self::from_dataset(path, &dataset, config)
    }

    /// What [`Sequence::open`] would load (views, frames, image sizes), read from the data
    /// set's description without decoding a frame: the input of the memory estimate.
    pub fn plan(path: &Path, config: &TrainConfig) -> Result<Vec<PlannedView>, TrainError> {
        Ok(gausmoke_data::plan(path, &Self::load_options(config))?)
    }

    fn load_options(config: &TrainConfig) -> LoadOptions {
        LoadOptions {
            resolution: config.image_size.map(|[w, h]| (w, h)),
            frames: config
                .frames
                .map(|n| config.first_frame..config.first_frame.saturating_add(n)),
            background: None,
        }
    }

    pub fn from_dataset(
        path: &Path,
        dataset: &Dataset,
        config: &TrainConfig,
    ) -> Result<Self, TrainError> {
        let fail = |reason: String| TrainError::Dataset {
            path: path.to_path_buf(),
            reason,
        };
        let pick = |names: &Option<Vec<String>>, split: Split| -> Result<Vec<String>, TrainError> {
            match names {
                Some(names) => {
                    for name in names {
                        if dataset.view(name).is_none() {
                            let known: Vec<&str> =
                                dataset.views.iter().map(|v| v.name.as_str()).collect();
                            return Err(fail(format!(
                                "no view `{name}`; the data set has {}",
                                known.join(", ")
                            )));
                        }
                    }
                    Ok(names.clone())
                }
                None => Ok(dataset.views_in(split).map(|v| v.name.clone()).collect()),
            }
        };
        let train_names = pick(&config.train_views, Split::Train)?;
        let mut test_names = pick(&config.test_views, Split::Test)?;
        if config.test_views.is_none() && test_names.is_empty() {
            test_names = dataset
                .views_in(Split::Val)
                .map(|v| v.name.clone())
                .collect();
        }
        if train_names.is_empty() {
            return Err(fail("no training views".into()));
        }
        if let Some(shared) = train_names.iter().find(|n| test_names.contains(n)) {
            return Err(fail(format!(
                "view `{shared}` is both a train and a test view"
            )));
        }
        let frames = dataset.times.len();
        let gather = |names: &[String]| {
            let mut per_frame: Vec<Vec<Observation>> = vec![Vec::new(); frames];
            for name in names {
                let view = dataset.view(name).expect("checked above");
                for frame in &view.frames {
                    per_frame[frame.time_index].push(Observation {
                        view: view.name.clone(),
                        camera: frame.camera,
                        image: frame.image.clone(),
                    });
                }
            }
            per_frame
        };
        let train = gather(&train_names);
        if let Some(t) = train.iter().position(Vec::is_empty) {
            return Err(fail(format!("frame {t} has no training image")));
        }
        let bbox = dataset.bbox.ok_or_else(|| {
            fail(
                "the data set gives no smoke box (PINF voxel_matrix/voxel_scale, nerfstudio \
                 `aabb`)"
                    .into(),
            )
        })?;
        // Every view must see every frame: a shorter video would silently train later frames
        // on fewer views and leave their held-out metrics empty.
        for name in train_names.iter().chain(&test_names) {
            let view = dataset.view(name).expect("checked above");
            let mut seen = vec![0usize; frames];
            for frame in &view.frames {
                seen[frame.time_index] += 1;
            }
            if let Some(missing) = seen.iter().position(|&n| n != 1) {
                let longest = dataset
                    .views
                    .iter()
                    .max_by_key(|v| v.frames.len())
                    .expect("a data set with a view");
                return Err(fail(format!(
                    "view `{name}` has {} frames but view `{}` has {} (first disagreement at \
                     frame {missing}); every train and test view must cover every frame: trim \
                     the videos to the same length, or pass --set frames=N with N <= {}",
                    view.frames.len(),
                    longest.name,
                    longest.frames.len(),
                    view.frames.len().min(frames),
                )));
            }
        }
        let ground_truth = path.join("gt");
        // Our generator's scale, in either layout's main file.
        let density_scale = ["info.json", "transforms_train.json"]
            .iter()
            .filter_map(|name| std::fs::read_to_string(path.join(name)).ok())
            .filter_map(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
            .find_map(|info| info["synth"]["density_scale"].as_f64())
            .map(|s| s as f32);
        let test = gather(&test_names);
        for jump in sudden_changes(&train, &test) {
            tracing::warn!(
                view = %jump.view,
                frame = jump.frame,
                change = jump.change,
                typical = jump.typical,
                "this view's picture is far from the mean of its frames before and after, \
                 farther than the view's pictures usually are: a damaged or missing video \
                 frame (a black or garbled picture) looks like this; check the file"
            );
        }
        for suspect in implausible_pictures(&train, &test) {
            tracing::warn!(
                view = %suspect.view,
                frame = suspect.frame,
                frames = suspect.count,
                mean = suspect.mean,
                others = suspect.others,
                "this view's picture is far brighter or darker than every other view's at the \
                 same time: a damaged video frame decodes into such a picture without an error \
                 (the H.264 decoder reports no concealment); check the file"
            );
        }
        Ok(Self {
            path: path.to_path_buf(),
            train,
            test,
            background: dataset.background,
            lo: bbox.min,
            hi: bbox.max,
            ground_truth: ground_truth.is_dir().then_some(ground_truth),
            first_frame: config.first_frame,
            ground_truth_density_scale: density_scale,
            obstacles: dataset.obstacles.clone(),
        })
    }
}

/// A view whose pictures stand out from all the others at the same time (see
/// [`implausible_pictures`]): the first such frame, how many there are, and the means.
#[derive(Debug, Clone, PartialEq)]
pub struct ImplausiblePicture {
    pub view: String,
    pub frame: usize,
    pub count: usize,
    /// The picture's mean value and the median of the other views' means at that frame.
    pub mean: f32,
    pub others: f32,
}

/// How far (in [0, 1] pixel units) a picture's mean may stray from the median view's before
/// it is reported. The views of one plume share background and lighting; the damaged frames
/// of a capture we tried decoded to means of 0.24-0.79 against 0.003.
const IMPLAUSIBLE_MEAN_GAP: f32 = 0.15;

/// Pictures whose mean value differs from the median of all views' means at the same frame by
/// more than [`IMPLAUSIBLE_MEAN_GAP`], at most one entry per view. A heuristic (it needs three
/// views or more and misses damage that keeps the brightness): the decoder gives no signal
/// when corrupted slice data happens to parse.
pub fn implausible_pictures(
    train: &[Vec<Observation>],
    test: &[Vec<Observation>],
) -> Vec<ImplausiblePicture> {
    let mut found: Vec<ImplausiblePicture> = Vec::new();
    for (frame, (a, b)) in train.iter().zip(test).enumerate() {
        let views: Vec<(&str, f32)> = a
            .iter()
            .chain(b)
            .map(|o| {
                let data = o.image.data();
                (
                    o.view.as_str(),
                    data.iter().sum::<f32>() / data.len().max(1) as f32,
                )
            })
            .collect();
        if views.len() < 3 {
            continue;
        }
        let mut means: Vec<f32> = views.iter().map(|&(_, m)| m).collect();
        means.sort_by(f32::total_cmp);
        let median = means[means.len() / 2];
        for &(view, mean) in &views {
            if (mean - median).abs() <= IMPLAUSIBLE_MEAN_GAP {
                continue;
            }
            match found.iter_mut().find(|f| f.view == view) {
                Some(seen) => seen.count += 1,
                None => found.push(ImplausiblePicture {
                    view: view.to_string(),
                    frame,
                    count: 1,
                    mean,
                    others: median,
                }),
            }
        }
    }
    found
}

/// A picture unlike the same view's pictures just before and after it (see
/// [`sudden_changes`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SuddenChange {
    pub view: String,
    pub frame: usize,
    /// Mean absolute difference from the mean of the view's pictures before and after it,
    /// and the median of that difference over the view's other frames.
    pub change: f32,
    pub typical: f32,
}

/// How many times its view's median the difference must exceed, and by how much at least
/// (pixel units in [0, 1]), to be reported. Smoke moves smoothly, so a picture is close to
/// the mean of its neighbours in time; a black frame, or a garbled slice, is not.
const SUDDEN_CHANGE_FACTOR: f32 = 6.0;
const SUDDEN_CHANGE_FLOOR: f32 = 0.002;

/// Pictures whose mean absolute difference from the mean of the same view's pictures at the
/// frames before and after is more than [`SUDDEN_CHANGE_FACTOR`] times the median of the
/// view's other frames' (leaving out the two beside it) plus [`SUDDEN_CHANGE_FLOOR`], and the largest of the three frames around it
/// (so a black frame is reported once, not its neighbours too): per view and over time, so it
/// needs no other view (unlike [`implausible_pictures`]) and sees a dark picture in a dark
/// scene. A heuristic: it needs six frames or more, and misses damage smaller than the
/// smoke's own change between frames.
pub fn sudden_changes(train: &[Vec<Observation>], test: &[Vec<Observation>]) -> Vec<SuddenChange> {
    let at = |t: usize, v: usize| {
        train[t]
            .iter()
            .chain(test.get(t).into_iter().flatten())
            .nth(v)
    };
    let views = train.first().map_or(0, Vec::len) + test.first().map_or(0, Vec::len);
    let mut found = Vec::new();
    for v in 0..views {
        // changes[i] belongs to frame i + 1.
        let changes: Vec<f32> = (1..train.len().saturating_sub(1))
            .map_while(|t| {
                let [a, b, c] = [t - 1, t, t + 1].map(|t| at(t, v).map(|o| o.image.data()));
                let (a, b, c) = (a?, b?, c?);
                let sum: f32 = (0..b.len())
                    .map(|i| (b[i] - 0.5 * (a[i] + c[i])).abs())
                    .sum();
                Some(sum / b.len().max(1) as f32)
            })
            .collect();
        if changes.len() < 4 {
            continue;
        }
        for (i, &change) in changes.iter().enumerate() {
            let near = i.saturating_sub(1)..(i + 2).min(changes.len());
            let around = changes[near.clone()].iter().fold(0.0f32, |m, &c| m.max(c));
            // The view's usual difference, without the frames a damaged one spoils.
            let mut others: Vec<f32> = changes
                .iter()
                .enumerate()
                .filter(|(j, _)| !near.contains(j))
                .map(|(_, &c)| c)
                .collect();
            others.sort_by(f32::total_cmp);
            let typical = others[others.len() / 2];
            if change > SUDDEN_CHANGE_FACTOR * typical + SUDDEN_CHANGE_FLOOR && change >= around {
                found.push(SuddenChange {
                    view: at(i + 1, v).map_or_else(String::new, |o| o.view.clone()),
                    frame: i + 1,
                    change,
                    typical,
                });
            }
        }
    }
    found
}
