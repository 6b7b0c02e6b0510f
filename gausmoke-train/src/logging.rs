//! The subscriber the command-line tools install: log lines to stderr (`RUST_LOG`, default
//! `info`) and the per-phase wall times that `metrics.json` reports
//! ([`gausmoke_core::phases::PhaseLayer`]).

use tracing_subscriber::Layer;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

/// Installs the global subscriber; does nothing if one is already installed.
pub fn init() {
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let _ = tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(filter),
        )
        .with(gausmoke_core::phases::PhaseLayer::new())
        .try_init();
}
