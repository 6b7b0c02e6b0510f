//! The subscriber the command-line tools install: log lines to stderr (`RUST_LOG`, default
//! `info`; coloured only on a terminal) and the per-phase wall times that `metrics.json` reports
//! ([`gausmoke_core::phases::PhaseLayer`]).

use tracing_subscriber::Layer;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

/// Whether log lines may carry colour: only on a terminal, and never under `NO_COLOR`
/// (no-color.org), so redirected logs stay plain text.
fn colour_wanted() -> bool {
    use std::io::IsTerminal;
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

/// Installs the global subscriber; does nothing if one is already installed.
pub fn init() {
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let _ = tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(colour_wanted())
                .with_filter(filter),
        )
        .with(gausmoke_core::phases::PhaseLayer::new())
        .try_init();
}
