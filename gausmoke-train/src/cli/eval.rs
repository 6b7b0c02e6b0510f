//! `eval`: the printed summary of an evaluation (every figure is in `RUN/eval.json`).

use gausmoke_train::eval::EvalReport;

/// The summary's rows, label and value; the optional figures only where the run has them.
pub(super) fn summary_rows(report: &EvalReport) -> Vec<(&'static str, String)> {
    let show = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.4}"));
    let mut rows = vec![
        ("frames evaluated", report.frames.len().to_string()),
        ("held-out PSNR (dB)", show(report.test_psnr_mean)),
        ("held-out SSIM", show(report.test_ssim_mean)),
        ("held-out LPIPS", show(report.test_lpips_mean)),
        (
            "mean |div u| (1/frame)",
            format!("{:.3e}", report.mean_abs_divergence),
        ),
    ];
    let mut optional = |label, value: Option<f64>| {
        if value.is_some() {
            rows.push((label, show(value)));
        }
    };
    optional("velocity rel. error", report.velocity_relative_error_mean);
    optional("velocity cosine", report.velocity_cosine_mean);
    optional(
        "estimate rel. error",
        report.velocity_estimate_relative_error_mean,
    );
    optional("estimate cosine", report.velocity_estimate_cosine_mean);
    optional("density rel. error", report.density_relative_error_mean);
    optional("density correlation", report.density_correlation_mean);
    optional(
        "density rel. error, best scale",
        report.density_scaled_relative_error_mean,
    );
    optional("density best scale", report.density_best_scale_mean);
    optional(
        "density share outside the smoke",
        report.density_outside_smoke_fraction_mean,
    );
    optional("obstacle normal flow", report.obstacle_normal_flow_mean);
    optional(
        "estimate obstacle normal flow",
        report.velocity_estimate_obstacle_normal_flow_mean,
    );
    rows
}

/// The rows as a table whose values start in one column.
pub(super) fn table(rows: &[(&str, String)]) -> String {
    let width = rows.iter().map(|(label, _)| label.len()).max().unwrap_or(0);
    rows.iter()
        .map(|(label, value)| format!("{label:<width$}  {value}\n"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::table;

    /// Every value starts in the same column, however long its label.
    #[test]
    fn the_values_line_up() {
        let text = table(&[
            ("a", "1".into()),
            ("mean |div u| (1/frame)", "2".into()),
            ("held-out PSNR (dB)", "n/a".into()),
        ]);
        let starts: Vec<usize> = text
            .lines()
            .map(|line| line.len() - line.split_whitespace().last().unwrap().len())
            .collect();
        assert!(starts.iter().all(|&s| s == starts[0]), "{text}");
    }
}
