//! The accuracy plot (PNG, error against run time), drawn with `plotters` when built with the
//! `plots` cargo feature; without it the functions return [`AccuracyError::Plot`] saying so.

#[allow(clippy::wildcard_imports)]
use super::*;

// ---------------------------------------------------------------------------------------------
// Plot

static FONT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();

fn ensure_font() -> Result<(), AccuracyError> {
    let ok = *FONT.get_or_init(|| {
        plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, dejavu::sans::regular())
            .is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(AccuracyError::Plot("cannot load the DejaVu Sans font".into()))
    }
}

const SCENE_COLOURS: [(u8, u8, u8); 6] =
    [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (23, 190, 207)];

/// Draws the two log-log panels (flow EPE and image MAE against milliseconds) into an RGB
/// buffer of `width` x `height` (3 bytes per pixel).
pub fn plot_rgb(report: &AccuracyReport, width: u32, height: u32) -> Result<Vec<u8>, AccuracyError> {
    use plotters::prelude::*;
    ensure_font()?;
    let mut buf = vec![255u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| perr(&e))?;
        let root = root
            .titled(
                &format!("Error against render time, {}x{}, N = {}", report.width, report.height, n_list(report)),
                ("sans-serif", 22),
            )
            .map_err(|e| perr(&e))?;
        let panels = root.split_evenly((1, 2));
        let metrics: [(&str, Metric); 2] =
            [("flow EPE, edge-free (px)", |m| m.epe_edge_free), ("image MAE against the reference", |m| m.image.mae)];
        let xs: Vec<f64> = report.rows.iter().map(|r| r.m.time.median).filter(|v| v.is_finite() && *v > 0.0).collect();
        let x_range = bounds(&xs);
        for (panel, (label, metric)) in panels.iter().zip(metrics) {
            draw_panel(panel, report, label, metric, x_range)?;
        }
        root.present().map_err(|e| perr(&e))?;
    }
    Ok(buf)
}

/// A plotting error as the bench's error.
fn perr(e: &dyn std::fmt::Display) -> AccuracyError {
    AccuracyError::Plot(e.to_string())
}

/// One panel: `metric` (its axis named `label`) against the median render time over
/// `xmin..xmax`, a line per scene and layering, and the legend.
fn draw_panel(
    panel: &plotters::drawing::DrawingArea<plotters::prelude::BitMapBackend<'_>, plotters::coord::Shift>,
    report: &AccuracyReport,
    label: &str,
    metric: Metric,
    (xmin, xmax): (f64, f64),
) -> Result<(), AccuracyError> {
    use plotters::prelude::*;
    let ys: Vec<f64> = report.rows.iter().map(|r| metric(&r.m)).filter(|v| v.is_finite() && *v > 0.0).collect();
    let (ymin, ymax) = bounds(&ys);
    let mut chart = ChartBuilder::on(panel)
        .margin(12)
        .x_label_area_size(48)
        .y_label_area_size(72)
        .build_cartesian_2d(
            (xmin..xmax)
                .log_scale()
                .with_key_points(log_ticks(xmin, xmax).0)
                .with_light_points(log_ticks(xmin, xmax).1),
            (ymin..ymax)
                .log_scale()
                .with_key_points(log_ticks(ymin, ymax).0)
                .with_light_points(log_ticks(ymin, ymax).1),
        )
        .map_err(|e| perr(&e))?;
    chart
        .configure_mesh()
        .x_desc("render time, image + flow + depth (ms, median)")
        .y_desc(label)
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .x_label_formatter(&|v| fmt_tick(*v))
        .y_label_formatter(&|v| fmt_tick(*v))
        .draw()
        .map_err(|e| perr(&e))?;
    for (si, sc) in report.scenes.iter().enumerate() {
        let (r, g, b) = SCENE_COLOURS[si % SCENE_COLOURS.len()];
        let colour = RGBColor(r, g, b);
        for layering in [Layering::Soft, Layering::Hard] {
            let pts: Vec<(f64, f64, usize)> = report
                .rows
                .iter()
                .filter(|q| q.scene == sc.name && q.layering == layering)
                .map(|q| (q.m.time.median, metric(&q.m), q.planes))
                .filter(|(x, y, _)| x.is_finite() && y.is_finite() && *x > 0.0 && *y > 0.0)
                .collect();
            let name = format!("{}, {}", sc.name, layering_name(layering));
            draw_line(&mut chart, &pts, name, colour, layering == Layering::Soft)?;
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()
        .map_err(|e| perr(&e))?;
    Ok(())
}

/// The line of one scene and layering through `pts` (time, error, N), with its legend entry `name`:
/// soft layering solid with circles and N next to each point, hard dashed with triangles.
fn draw_line<'a, CT: plotters::coord::CoordTranslate<From = (f64, f64)>>(
    chart: &mut plotters::chart::ChartContext<'a, plotters::prelude::BitMapBackend<'a>, CT>,
    pts: &[(f64, f64, usize)],
    name: String,
    colour: plotters::style::RGBColor,
    soft: bool,
) -> Result<(), AccuracyError> {
    use plotters::prelude::*;
    let line: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.1)).collect();
    let style = colour.stroke_width(if soft { 2 } else { 1 });
    if soft {
        chart.draw_series(LineSeries::new(line.clone(), style)).map_err(|e| perr(&e))?.label(name).legend(
            move |(x, y)| {
                EmptyElement::at((x, y))
                    + PathElement::new(vec![(0, 0), (22, 0)], colour.stroke_width(2))
                    + Circle::new((11, 0), 4, colour.filled())
            },
        );
        chart.draw_series(line.iter().map(|&p| Circle::new(p, 4, colour.filled()))).map_err(|e| perr(&e))?;
    } else {
        chart.draw_series(DashedLineSeries::new(line.clone(), 6, 4, style)).map_err(|e| perr(&e))?.label(name).legend(
            move |(x, y)| {
                EmptyElement::at((x, y))
                    + PathElement::new(vec![(0, 0), (22, 0)], colour.stroke_width(1))
                    + TriangleMarker::new((11, 0), 5, colour.filled())
            },
        );
        chart.draw_series(line.iter().map(|&p| TriangleMarker::new(p, 5, colour.filled()))).map_err(|e| perr(&e))?;
    }
    if soft {
        // N next to each soft point (hard points share the abscissa)
        chart
            .draw_series(pts.iter().map(|&(x, y, n)| {
                EmptyElement::at((x, y))
                    + Text::new(format!("{n}"), (6, -16), ("sans-serif", 12).into_font().color(&colour))
            }))
            .map_err(|e| perr(&e))?;
    }
    Ok(())
}

fn n_list(report: &AccuracyReport) -> String {
    let mut ns: Vec<usize> = report.rows.iter().map(|r| r.planes).collect();
    ns.sort_unstable();
    ns.dedup();
    ns.iter().map(std::string::ToString::to_string).collect::<Vec<_>>().join(", ")
}

/// A log axis range covering `v` with some room (a decade around 1 when empty).
fn bounds(v: &[f64]) -> (f64, f64) {
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !(lo.is_finite() && hi.is_finite()) {
        return (0.1, 10.0);
    }
    let (lo, hi) = if hi / lo < 1.5 { (lo / 1.5, hi * 1.5) } else { (lo, hi) };
    (lo / 1.6, hi * 1.6)
}

/// Labelled ticks (1, 2, 5 per decade; decades only over more than three decades) and light
/// mesh lines (1..9 per decade) of a log axis over [lo, hi].
fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>) {
    let (mut bold, mut light) = (Vec::new(), Vec::new());
    if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi > lo) {
        return (bold, light);
    }
    let steps: &[f64] = if hi / lo > 1e3 { &[1.0] } else { &[1.0, 2.0, 5.0] };
    for e in (lo.log10().floor() as i32)..=(hi.log10().ceil() as i32) {
        let d = 10f64.powi(e);
        for m in 1..10 {
            let v = m as f64 * d;
            if v >= lo && v <= hi {
                light.push(v);
                if steps.contains(&(m as f64)) {
                    bold.push(v);
                }
            }
        }
    }
    (bold, light)
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if (1e-3..1e4).contains(&v.abs()) {
        let s = format!("{v:.4}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.0e}")
    }
}

/// Writes the plot as a PNG file.
pub fn write_plot(report: &AccuracyReport, path: &Path, width: u32, height: u32) -> Result<(), AccuracyError> {
    let buf = plot_rgb(report, width, height)?;
    crate::io::image::write_png(path, width, height, &buf, ::image::ExtendedColorType::Rgb8)?;
    Ok(())
}
