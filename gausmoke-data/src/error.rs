use std::path::PathBuf;

use gausmoke_core::CameraError;

/// Why a data set could not be loaded or written. Every variant names the file it is about;
/// JSON problems also name the field (as a path such as `train_videos[2].camera_hw`) and what
/// was expected.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: cannot read or write: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: not valid JSON: {source}")]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{path}: field `{field}`: expected {expected}")]
    Field {
        path: PathBuf,
        field: String,
        expected: String,
    },
    #[error("{path}: field `{field}` does not give a usable camera: {source}")]
    Camera {
        path: PathBuf,
        field: String,
        #[source]
        source: CameraError,
    },
    #[error("{path}: has {found} frames, but `{field}` in {json} announces {expected}")]
    TooFewFrames {
        path: PathBuf,
        json: PathBuf,
        field: String,
        found: usize,
        expected: usize,
    },
    #[error(
        "{path}: frame {frame} is {found_width}x{found_height} (width x height), expected {expected_width}x{expected_height} from {origin}"
    )]
    FrameSize {
        path: PathBuf,
        frame: usize,
        found_width: u32,
        found_height: u32,
        expected_width: u32,
        expected_height: u32,
        origin: String,
    },
    #[error("{path}: cannot decode video: {reason}")]
    Video { path: PathBuf, reason: String },
    #[error("{path}: cannot {action} image: {source}")]
    Image {
        /// "read" or "write".
        action: &'static str,
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("{path}: {reason}")]
    Layout { path: PathBuf, reason: String },
    #[error("invalid option `{option}`: {reason}")]
    Options {
        option: &'static str,
        reason: String,
    },
    #[error("{path}: cannot write tensors: {reason}")]
    Tensors { path: PathBuf, reason: String },
}

pub type Result<T, E = DataError> = std::result::Result<T, E>;

pub(crate) fn io_err(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> DataError {
    let path = path.into();
    move |source| DataError::Io { path, source }
}
