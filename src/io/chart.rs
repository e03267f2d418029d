//! Line charts (each axis log or linear), written as SVG and as PNG by `plotters`: one drawing
//! routine, generic over the backend, so the two files show the same chart. Several charts can be
//! stacked in one file.
//!
//! PNG text is rasterised by plotters' pure-Rust `ab_glyph` backend from DejaVu Sans read at run
//! time (Debian: fonts-dejavu-core, or `$VOLGRAD_FONT`). Nothing here asks plotters to measure
//! text (no `caption`, no `series_labels`: both size their boxes from font metrics), so the SVG
//! needs no font at all and, without one, the PNG is still drawn, only without its labels.

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
    pub x_scale: Scale,
    pub y_scale: Scale,
    pub series: Vec<Series>,
}

/// How an axis maps values: errors and costs span decades (log); dB and seconds of one run do not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scale {
    Log,
    Linear,
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

impl Chart {
    /// Whether a point can be drawn: finite, and positive on a log axis.
    fn usable(&self, p: &(f64, f64)) -> bool {
        let fits = |v: f64, scale: Scale| v.is_finite() && (scale == Scale::Linear || v > 0.0);
        fits(p.0, self.x_scale) && fits(p.1, self.y_scale)
    }

    fn usable_points(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.series
            .iter()
            .flat_map(|s| s.points.iter().copied().filter(|p| self.usable(p)))
    }
}

/// A linear axis range around `values`, padded by 5 % (a flat series gets ±1).
fn linear_range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    let pad = if hi > lo { 0.05 * (hi - lo) } else { 1.0 };
    lo - pad..hi + pad
}

/// A linear axis's tick label: as many decimals as the range needs.
fn linear_label(v: f64, range: &std::ops::Range<f64>) -> String {
    let decimals = (1.0 - (range.end - range.start).log10().floor()).clamp(0.0, 6.0) as usize;
    format!("{v:.decimals$}")
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

/// Draws `chart` on `root` (WIDTH × HEIGHT), each axis on its scale. Text is drawn in `ink`:
/// transparent when the backend has no font to draw it with (plotters then skips it instead of
/// failing).
fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
    ink: RGBAColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let xs = chart.usable_points().map(|p| p.0);
    let ys = chart.usable_points().map(|p| p.1);
    match (chart.x_scale, chart.y_scale) {
        (Scale::Log, Scale::Log) => draw_on(
            root,
            chart,
            ink,
            decade_range(xs).log_scale(),
            decade_range(ys).log_scale(),
        ),
        (Scale::Log, Scale::Linear) => draw_on(
            root,
            chart,
            ink,
            decade_range(xs).log_scale(),
            linear_range(ys),
        ),
        (Scale::Linear, Scale::Log) => draw_on(
            root,
            chart,
            ink,
            linear_range(xs),
            decade_range(ys).log_scale(),
        ),
        (Scale::Linear, Scale::Linear) => {
            draw_on(root, chart, ink, linear_range(xs), linear_range(ys))
        }
    }
}

/// Tick labels of an axis: decades on a log axis, evenly spaced numbers on a linear one.
fn ticks(scale: Scale, range: std::ops::Range<f64>) -> impl Fn(&f64) -> String {
    move |v| match scale {
        Scale::Log => tick_label(*v),
        Scale::Linear => linear_label(*v, &range),
    }
}

fn draw_on<DB, X, Y>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
    ink: RGBAColor,
    x_axis: X,
    y_axis: Y,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB: DrawingBackend,
    X: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    Y: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    X::CoordDescType: plotters::coord::ranged1d::ValueFormatter<f64>,
    Y::CoordDescType: plotters::coord::ranged1d::ValueFormatter<f64>,
{
    let text = |size: f64| TextStyle::from((FAMILY, size).into_font()).color(&ink);
    root.fill(&WHITE)?;
    let mut plot = ChartBuilder::on(root)
        .margin_top(TOP)
        .margin_right(RIGHT)
        .margin_left(EDGE)
        .margin_bottom(EDGE)
        .x_label_area_size(BOTTOM - EDGE)
        .y_label_area_size(LEFT - EDGE)
        .build_cartesian_2d(x_axis, y_axis)?;
    let (x_range, y_range) = (plot.x_range(), plot.y_range());
    let (x_ticks, y_ticks) = (ticks(chart.x_scale, x_range), ticks(chart.y_scale, y_range));
    plot.configure_mesh()
        .x_labels(MAX_DECADE_LABELS)
        .y_labels(MAX_DECADE_LABELS)
        .x_label_formatter(&x_ticks)
        .y_label_formatter(&y_ticks)
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
        let points: Vec<(f64, f64)> = series
            .points
            .iter()
            .copied()
            .filter(|p| chart.usable(p))
            .collect();
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
    Ok(())
}

/// Draws `charts` one above the other on `root`.
fn draw_stack<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    charts: &[&Chart],
    ink: RGBAColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    for (area, chart) in root.split_evenly((charts.len(), 1)).iter().zip(charts) {
        draw(area, chart, ink)?;
    }
    root.present()
}

fn check_drawable(chart: &Chart) -> Result<()> {
    if chart.usable_points().next().is_none() {
        bail!(
            "chart '{}' has no point to draw (finite, and positive on a log axis)",
            chart.title
        );
    }
    Ok(())
}

/// The chart as an SVG document: each series a `<polyline>` in its colour (the axes are ink
/// polylines), its points `<circle>`s, every label a `<text>`.
pub fn to_svg(chart: &Chart) -> Result<String> {
    stack_to_svg(&[chart])
}

/// Charts one above the other in one SVG document.
pub fn stack_to_svg(charts: &[&Chart]) -> Result<String> {
    charts.iter().try_for_each(|c| check_drawable(c))?;
    let mut svg = String::new();
    let height = HEIGHT * charts.len() as u32;
    draw_stack(
        SVGBackend::with_string(&mut svg, (WIDTH, height)).into_drawing_area(),
        charts,
        INK.to_rgba(),
    )
    .map_err(|e| anyhow!("drawing the SVG chart: {e}"))?;
    Ok(svg)
}

/// Draws the chart as a PNG. Returns false when no font was found: the lines are drawn, the
/// labels are not (the SVG has them), and the caller should say so.
pub fn write_png(chart: &Chart, path: &Path) -> Result<bool> {
    write_stack_png(&[chart], path)
}

/// Charts one above the other in one PNG (see `write_png`).
pub fn write_stack_png(charts: &[&Chart], path: &Path) -> Result<bool> {
    charts.iter().try_for_each(|c| check_drawable(c))?;
    let labelled = font_registered();
    let ink = if labelled { INK.to_rgba() } else { TRANSPARENT };
    let height = HEIGHT * charts.len() as u32;
    let mut rgb = vec![0u8; (WIDTH * height * 3) as usize];
    draw_stack(
        BitMapBackend::with_buffer(&mut rgb, (WIDTH, height)).into_drawing_area(),
        charts,
        ink,
    )
    .map_err(|e| anyhow!("drawing the PNG chart: {e}"))?;
    // Encoded here rather than by plotters' `bitmap_encoder`, which would bring in a second
    // `image` and `png` (and a JPEG decoder) for this one file.
    let mut encoded = Vec::new();
    let mut encoder = png::Encoder::new(&mut encoded, WIDTH, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut w| w.write_image_data(&rgb))
        .with_context(|| format!("encoding '{}'", path.display()))?;
    // Whole or not at all: progress.png is rewritten at every checkpoint.
    crate::io::output::write_bytes_whole(path, encoded)?;
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
            x_scale: Scale::Log,
            y_scale: Scale::Log,
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

    /// Zero and negative values are drawn on linear axes (dB, seconds from 0) and refused on log
    /// axes.
    #[test]
    fn linear_axes_take_zero_and_negative_values() {
        let mut c = chart();
        for s in &mut c.series {
            s.points = vec![(0.0, -1.0), (0.0, 2.5), (10.0, -0.5)];
        }
        assert!(to_svg(&c).is_err());
        c.x_scale = Scale::Linear;
        c.y_scale = Scale::Linear;
        let svg = to_svg(&c).unwrap();
        assert_eq!(
            svg.lines()
                .filter(|l| l.starts_with("<polyline") && l.contains("stroke=\"#0072B2\""))
                .count(),
            1
        );
        assert_eq!(linear_label(2.5, &(-1.2..2.7)), "2.5");
        assert_eq!(linear_label(25.0, &(20.0..40.0)), "25");
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
