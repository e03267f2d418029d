//! Log–log line charts, written as SVG and as PNG by `plotters`: one drawing routine, generic over
//! the backend, so the two files show the same chart.
//!
//! PNG text is rasterised by plotters' pure-Rust `ab_glyph` backend from DejaVu Sans read at run
//! time (Debian: fonts-dejavu-core, or `$VOLGRAD_FONT`). Nothing here asks plotters to measure
//! text (no `caption`, no `series_labels`: both size their boxes from font metrics), so the SVG
//! needs no font at all and, without one, the PNG is still drawn, only without its labels.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{anyhow, bail, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

pub struct Series {
    pub name: String,
    /// (x, y) in data units; points that are not finite and positive are left out (log axes).
    pub points: Vec<(f64, f64)>,
}

pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
}

const WIDTH: u32 = 820;
const HEIGHT: u32 = 520;
/// The plot rectangle's distances to the image's edges; plotters puts the axis labels at the outer
/// edge of the label areas, so a margin keeps their glyphs off the border.
const LEFT: u32 = 84; // tick labels and the y-axis label
const RIGHT: u32 = 190; // room for the legend
const TOP: u32 = 44; // the title
const BOTTOM: u32 = 62; // tick labels and the x-axis label
const EDGE: u32 = 10;

/// Colour-blind-safe (Okabe–Ito) line colours.
const PALETTE: [RGBColor; 6] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
];
const INK: RGBColor = RGBColor(30, 30, 30);
const DECADE_LINE: RGBColor = RGBColor(190, 190, 190);
const MINOR_LINE: RGBColor = RGBColor(225, 225, 225);

/// The family the SVG names and the PNG's font is registered under.
const FAMILY: &str = "sans-serif";
/// Text sizes in plotters' unit: the SVG's font-size is this / 1.24 (13 px for labels).
const LABEL_SIZE: f64 = 16.0;
const AXIS_SIZE: f64 = 17.5;
const TITLE_SIZE: f64 = 20.0;

/// Where the fonts of Debian's fonts-dejavu-core and a few other systems live.
const FONT_PATHS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Registers the first usable TTF (`$VOLGRAD_FONT`, then the usual system places) with plotters,
/// once per process; false if there is none. plotters keeps fonts for the life of the process as
/// `&'static [u8]`, so the bytes are leaked, once.
fn font_registered() -> bool {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    *REGISTERED.get_or_init(|| {
        let from_env = std::env::var_os("VOLGRAD_FONT").map(PathBuf::from);
        from_env
            .into_iter()
            .chain(FONT_PATHS.iter().map(PathBuf::from))
            .filter_map(|path| std::fs::read(path).ok())
            .any(|bytes| {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                plotters::style::register_font(FAMILY, FontStyle::Normal, bytes).is_ok()
            })
    })
}

fn usable(p: &(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite() && p.0 > 0.0 && p.1 > 0.0
}

/// The whole decades that cover `values`, as a data range. The ends are widened by a relative
/// 1e-9 because plotters finds the decade lines by `10^ceil(log10(start))` and repeated ×10, and
/// rounding would otherwise drop the first or last decade (log10(0.1) is −0.99999…).
fn decade_range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    let (lo, mut hi) = (lo.log10().floor(), hi.log10().ceil());
    if hi <= lo {
        hi = lo + 1.0;
    }
    10f64.powf(lo) * (1.0 - 1e-9)..10f64.powf(hi) * (1.0 + 1e-9)
}

/// A decade's label: plain numbers near 1, powers of ten beyond.
fn tick_label(v: f64) -> String {
    let k = v.log10().round() as i32;
    match k {
        -3..=-1 => format!("{:.*}", k.unsigned_abs() as usize, 10f64.powi(k)),
        0..=4 => 10i64.pow(k as u32).to_string(),
        _ => format!("1e{k}"),
    }
}

/// Decades get labels; between 1 and 7 decades every one is labelled, beyond that plotters
/// thins them. Fewer than 8 labels also keeps plotters' minor lines at 2…9 × 10^k.
const MAX_DECADE_LABELS: usize = 7;

/// Draws `chart` on `root` (WIDTH × HEIGHT). Text is drawn in `ink`: transparent when the backend
/// has no font to draw it with (plotters then skips it instead of failing).
fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
    ink: RGBAColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let text = |size: f64| TextStyle::from((FAMILY, size).into_font()).color(&ink);
    root.fill(&WHITE)?;
    let usable_points = || {
        chart
            .series
            .iter()
            .flat_map(|s| s.points.iter().copied().filter(usable))
    };
    let x_range = decade_range(usable_points().map(|p| p.0));
    let y_range = decade_range(usable_points().map(|p| p.1));
    let mut plot = ChartBuilder::on(root)
        .margin_top(TOP)
        .margin_right(RIGHT)
        .margin_left(EDGE)
        .margin_bottom(EDGE)
        .x_label_area_size(BOTTOM - EDGE)
        .y_label_area_size(LEFT - EDGE)
        .build_cartesian_2d(x_range.log_scale(), y_range.log_scale())?;
    plot.configure_mesh()
        .x_labels(MAX_DECADE_LABELS)
        .y_labels(MAX_DECADE_LABELS)
        .x_label_formatter(&|v| tick_label(*v))
        .y_label_formatter(&|v| tick_label(*v))
        .bold_line_style(DECADE_LINE.stroke_width(1))
        .light_line_style(MINOR_LINE.stroke_width(1))
        .axis_style(INK.stroke_width(1))
        .label_style(text(LABEL_SIZE))
        .axis_desc_style(text(AXIS_SIZE))
        .x_desc(chart.x_label.as_str())
        .y_desc(chart.y_label.as_str())
        .draw()?;
    // The mesh draws the left and bottom axes only: close the frame.
    let (xs, ys) = plot.plotting_area().get_pixel_range();
    root.draw(&Rectangle::new(
        [(xs.start, ys.start), (xs.end - 1, ys.end - 1)],
        INK.stroke_width(1),
    ))?;
    root.draw_text(
        &chart.title,
        &text(TITLE_SIZE).pos(Pos::new(HPos::Center, VPos::Center)),
        ((xs.start + xs.end) / 2, TOP as i32 / 2),
    )?;
    for (i, series) in chart.series.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        let points: Vec<(f64, f64)> = series.points.iter().copied().filter(usable).collect();
        plot.draw_series(LineSeries::new(points, colour.filled().stroke_width(2)).point_size(3))?;
        // The legend, by hand (plotters' own measures text): a short bar and the name, in the
        // right margin. A bar is a rect, so each series has one polyline of its colour in the SVG.
        let (x, y) = (xs.end + 14, ys.start + 12 + 22 * i as i32);
        root.draw(&Rectangle::new(
            [(x, y - 1), (x + 26, y + 1)],
            colour.filled(),
        ))?;
        root.draw_text(
            &series.name,
            &text(LABEL_SIZE).pos(Pos::new(HPos::Left, VPos::Center)),
            (x + 32, y),
        )?;
    }
    root.present()
}

fn check_drawable(chart: &Chart) -> Result<()> {
    if !chart.series.iter().any(|s| s.points.iter().any(usable)) {
        bail!(
            "chart '{}' has no finite positive point to draw on log axes",
            chart.title
        );
    }
    Ok(())
}

/// The chart as an SVG document: each series a `<polyline>` in its colour (the axes are ink
/// polylines), its points `<circle>`s, every label a `<text>`.
pub fn to_svg(chart: &Chart) -> Result<String> {
    check_drawable(chart)?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, HEIGHT)).into_drawing_area();
        draw(&root, chart, INK.to_rgba()).map_err(|e| anyhow!("drawing the SVG chart: {e}"))?;
    }
    Ok(svg)
}

/// Draws the chart as a PNG. Returns false when no font was found: the lines are drawn, the
/// labels are not (the SVG has them), and the caller should say so.
pub fn write_png(chart: &Chart, path: &Path) -> Result<bool> {
    check_drawable(chart)?;
    let labelled = font_registered();
    let ink = if labelled { INK.to_rgba() } else { TRANSPARENT };
    let mut rgb = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (WIDTH, HEIGHT)).into_drawing_area();
        draw(&root, chart, ink).map_err(|e| anyhow!("drawing the PNG chart: {e}"))?;
    }
    // Encoded here rather than by plotters' `bitmap_encoder`, which would bring in a second
    // `image` and `png` (and a JPEG decoder) for this one file.
    let file = File::create(path).with_context(|| format!("cannot create '{}'", path.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), WIDTH, HEIGHT);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(&rgb))
        .with_context(|| format!("writing '{}'", path.display()))?;
    Ok(labelled)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chart() -> Chart {
        Chart {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            series: vec![
                Series {
                    name: "a".into(),
                    points: vec![(0.1, 1.0), (0.2, 0.7), (0.4, 0.5), (0.0, f64::NAN)],
                },
                Series {
                    name: "b<c".into(),
                    points: vec![(0.3, 2.0), (30.0, 0.02)],
                },
            ],
        }
    }

    #[test]
    fn axes_cover_every_point_in_whole_decades() {
        let x = decade_range([0.1, 0.2, 0.4, 0.3, 30.0].into_iter());
        assert!((x.start - 0.1).abs() < 1e-9 && (x.end - 100.0).abs() < 1e-6);
        assert!(x.start < 0.1 && x.end > 100.0, "the end decades are inside");
        let y = decade_range([2.0, 2.0].into_iter());
        assert!((y.start - 1.0).abs() < 1e-9 && (y.end - 10.0).abs() < 1e-6);
        let labels: Vec<String> = [1e-3, 0.1, 1.0, 1e4, 1e5, 1e-4]
            .into_iter()
            .map(tick_label)
            .collect();
        assert_eq!(labels, ["0.001", "0.1", "1", "10000", "1e5", "1e-4"]);
    }

    #[test]
    fn svg_has_one_polyline_per_series_a_label_per_decade_and_escapes_names() {
        let svg = to_svg(&chart()).unwrap();
        // The axes and tick marks are polylines too, in INK.
        let series_lines = |colour: &str| {
            svg.lines()
                .filter(|l| l.starts_with("<polyline") && l.contains(colour))
                .count()
        };
        assert_eq!(series_lines("stroke=\"#0072B2\""), 1);
        assert_eq!(series_lines("stroke=\"#D55E00\""), 1);
        assert!(svg.contains("b&lt;c"));
        assert!(!svg.contains("NaN"));
        for decade in ["0.1", "1", "10", "100", "0.01"] {
            assert!(
                svg.contains(&format!(">\n{decade}\n<")),
                "no label {decade}"
            );
        }
    }

    #[test]
    fn a_chart_without_positive_points_is_an_error() {
        let mut c = chart();
        for s in &mut c.series {
            s.points = vec![(0.0, 1.0), (1.0, -1.0)];
        }
        assert!(to_svg(&c).is_err());
    }
}
