//! Writing evaluation results: the precision-recall curve as CSV and as a PNG plot, and the
//! JSON summary. The plot's text needs a TrueType font, loaded at run time from the system
//! (DejaVu Sans or Liberation Sans); without one the plot is drawn without any text.

use super::metrics::Metrics;
use anyhow::{Context, Result};
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

/// Writes `threshold,precision,recall` rows, highest threshold first.
pub fn write_curve_csv(metrics: &Metrics, path: &Path) -> Result<()> {
    crate::io::output::replace_with(path, |file| {
        let mut writer = csv::Writer::from_writer(file);
        writer.write_record(["threshold", "precision", "recall"])?;
        for point in &metrics.curve {
            writer.write_record([
                point.threshold.to_string(),
                point.precision.to_string(),
                point.recall.to_string(),
            ])?;
        }
        Ok(writer.flush()?)
    })
}

/// The JSON summary: `queries`, `positives`, `unknown`, `unknown_matches`, `recall_at_1`,
/// `recall_at_100_precision`, `average_precision` (null without positives), plus `timing_ms`
/// with whatever stage timings the caller measured (milliseconds, by stage name).
pub fn summary_json(metrics: &Metrics, timings_ms: &[(&str, f64)]) -> serde_json::Value {
    let mut value = serde_json::to_value(metrics).expect("metrics serialise to JSON");
    if !timings_ms.is_empty() {
        let timing: serde_json::Map<String, serde_json::Value> =
            timings_ms.iter().map(|(name, ms)| (name.to_string(), serde_json::json!(ms))).collect();
        value["timing_ms"] = serde_json::Value::Object(timing);
    }
    value
}

const FONT_CANDIDATES: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Draws a `size` RGB image with `draw` and writes it to `path` as PNG, replacing a regular file only
/// by rename ([`crate::io::output::replace_with`]).
fn write_png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&mut [u8], (u32, u32)) -> Result<(), Box<dyn std::error::Error>>,
) -> Result<()> {
    let png = (|| -> Result<Vec<u8>> {
        let mut buffer = vec![255u8; size.0 as usize * size.1 as usize * 3];
        draw(&mut buffer, size).map_err(|e| anyhow::anyhow!("{e}"))?;
        let image = image::RgbImage::from_raw(size.0, size.1, buffer).expect("buffer of the image's size");
        let mut png = std::io::Cursor::new(Vec::new());
        image.write_to(&mut png, image::ImageFormat::Png)?;
        Ok(png.into_inner())
    })()
    .with_context(|| format!("plotting {}", path.display()))?;
    crate::io::output::write_replacing(path, &png)
}

/// Registers the first system font found as plotters' "sans-serif"; false if there is none.
fn font_available() -> bool {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    *REGISTERED.get_or_init(|| {
        FONT_CANDIDATES.iter().any(|path| {
            let Ok(bytes) = std::fs::read(path) else { return false };
            // plotters keeps fonts for the life of the process; this runs at most once.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok()
        })
    })
}

/// Draws the precision-recall curve into a PNG (800x600), with the metrics in the caption when
/// a font is available.
pub fn plot_pr_curve(metrics: &Metrics, title: &str, path: &Path) -> Result<()> {
    let with_text = font_available();
    write_png(path, (800, 600), |buffer, size| draw_pr_curve(metrics, title, buffer, size, with_text))
}

fn draw_pr_curve(
    metrics: &Metrics,
    title: &str,
    buffer: &mut [u8],
    size: (u32, u32),
    with_text: bool,
) -> Result<(), Box<dyn std::error::Error>> {
    let root = BitMapBackend::with_buffer(buffer, size).into_drawing_area();
    root.fill(&WHITE)?;
    let mut builder = ChartBuilder::on(&root);
    builder.margin(20);
    if with_text {
        let fmt = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.3}"));
        let caption = format!(
            "{title}  AP {}  R@100%P {}  R@1 {}",
            fmt(metrics.average_precision),
            fmt(metrics.recall_at_100_precision),
            fmt(metrics.recall_at_1)
        );
        builder.caption(caption, ("sans-serif", 20)).x_label_area_size(45).y_label_area_size(55);
    }
    let mut chart = builder.build_cartesian_2d(0.0f64..1.0, 0.0f64..1.02)?;
    let mut mesh = chart.configure_mesh();
    if with_text {
        mesh.x_desc("recall").y_desc("precision").label_style(("sans-serif", 15));
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw()?;
    let points: Vec<(f64, f64)> = metrics.curve.iter().map(|p| (p.recall, p.precision)).collect();
    chart.draw_series(LineSeries::new(points.iter().copied(), BLUE.stroke_width(2)))?;
    // Markers only where they can be told apart; a dense curve is clearer as a line.
    if points.len() <= 60 {
        chart.draw_series(points.iter().map(|&p| Circle::new(p, 3, BLUE.filled())))?;
    }
    root.present()?;
    Ok(())
}

/// The trajectories of a pose-graph run, for [`plot_trajectories`]: camera positions in metres, all
/// in the ground truth's frame.
pub struct TrajectoryPlot<'a> {
    pub title: &'a str,
    pub groundtruth: &'a [nalgebra::Vector3<f64>],
    pub odometry: &'a [nalgebra::Vector3<f64>],
    pub corrected: &'a [nalgebra::Vector3<f64>],
    /// Loop edges as (query, match) positions on the corrected trajectory.
    pub loops: &'a [(nalgebra::Vector3<f64>, nalgebra::Vector3<f64>)],
}

/// Draws the paper's Fig. 11 kind of figure into a PNG (900x900): the trajectories seen from above
/// (the two axes along which the ground truth, else the corrected trajectory, extends most), ground truth black, odometry red,
/// corrected blue, loop edges green.
pub fn plot_trajectories(plot: &TrajectoryPlot, path: &Path) -> Result<()> {
    let with_text = font_available();
    write_png(path, (900, 900), |buffer, size| draw_trajectories(plot, buffer, size, with_text))
}

fn draw_trajectories(
    plot: &TrajectoryPlot,
    buffer: &mut [u8],
    size: (u32, u32),
    with_text: bool,
) -> Result<(), Box<dyn std::error::Error>> {
    let all = || plot.groundtruth.iter().chain(plot.odometry).chain(plot.corrected);
    let reference = if plot.groundtruth.is_empty() { plot.corrected } else { plot.groundtruth };
    let extent = |axis: usize| {
        let values = reference.iter().map(|p| p[axis]);
        values.clone().fold(f64::MIN, f64::max) - values.fold(f64::MAX, f64::min)
    };
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| extent(b).total_cmp(&extent(a)));
    let (u, v) = (axes[0].min(axes[1]), axes[0].max(axes[1]));
    let range = |axis: usize| {
        let (lo, hi) = all().fold((f64::MAX, f64::MIN), |(lo, hi), p| (lo.min(p[axis]), hi.max(p[axis])));
        (lo, hi)
    };
    let ((u0, u1), (v0, v1)) = (range(u), range(v));
    // Equal scales on both axes, with a margin.
    let half = ((u1 - u0).max(v1 - v0) / 2.0).max(0.5) * 1.08;
    let (uc, vc) = ((u0 + u1) / 2.0, (v0 + v1) / 2.0);
    let root = BitMapBackend::with_buffer(buffer, size).into_drawing_area();
    root.fill(&WHITE)?;
    let mut builder = ChartBuilder::on(&root);
    builder.margin(20);
    if with_text {
        builder.caption(plot.title, ("sans-serif", 20)).x_label_area_size(45).y_label_area_size(55);
    }
    let mut chart = builder.build_cartesian_2d(uc - half..uc + half, vc - half..vc + half)?;
    let mut mesh = chart.configure_mesh();
    let names = ["x (m)", "y (m)", "z (m)"];
    if with_text {
        mesh.x_desc(names[u]).y_desc(names[v]).label_style(("sans-serif", 15));
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw()?;
    let project = |p: &nalgebra::Vector3<f64>| (p[u], p[v]);
    let green = RGBColor(0, 160, 0);
    for (a, b) in plot.loops {
        chart.draw_series(LineSeries::new([project(a), project(b)], green.stroke_width(1)))?;
    }
    for (points, colour, name) in [
        (plot.groundtruth, BLACK, "ground truth"),
        (plot.odometry, RED, "odometry"),
        (plot.corrected, BLUE, "corrected"),
    ] {
        let series = chart.draw_series(LineSeries::new(points.iter().map(project), colour.stroke_width(2)))?;
        if with_text {
            series.label(name).legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
        }
    }
    if with_text {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()?;
    }
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{evaluate, LoopTruth, QueryResult};

    fn metrics() -> Metrics {
        let mut truth = LoopTruth::default();
        truth.insert(5, 1);
        truth.insert(6, 2);
        let results = [
            QueryResult { query: 5, best: Some((1, 0.9)) },
            QueryResult { query: 6, best: Some((0, 0.5)) },
            QueryResult { query: 7, best: Some((3, 0.25)) },
        ];
        evaluate(&results, &truth).unwrap()
    }

    #[test]
    fn csv_json_and_plot_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let m = metrics();
        let csv_path = dir.path().join("pr.csv");
        write_curve_csv(&m, &csv_path).unwrap();
        let text = std::fs::read_to_string(&csv_path).unwrap();
        assert_eq!(text, "threshold,precision,recall\n0.9,1,0.5\n0.5,0.5,0.5\n0.25,0.3333333333333333,0.5\n");
        let json = summary_json(&m, &[("network", 12.5)]);
        assert_eq!(json["queries"], 3);
        assert_eq!(json["recall_at_1"], 0.5);
        assert_eq!(json["recall_at_100_precision"], 0.5);
        assert_eq!(json["average_precision"], 0.5);
        assert_eq!(json["timing_ms"]["network"], 12.5);
        let png = dir.path().join("pr.png");
        plot_pr_curve(&m, "test", &png).unwrap();
        let image = image::open(&png).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (800, 600));
        assert!(image.pixels().any(|p| p.0 == [0, 0, 255]), "the curve is drawn in blue");
    }
}
