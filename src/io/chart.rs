//! Log–log line charts, written as SVG (text) and as PNG (rasterised here, text drawn with a TTF
//! font read at run time). One layout feeds both, so the two files show the same chart.
//!
//! Why not a plotting crate: `plotters` 0.3.7 draws bitmap text only through `font-kit` (system
//! fontconfig/freetype), which is fragile offline; lines, circles and a few labels are little code,
//! and `ab_glyph` (pure Rust) rasterises the labels from DejaVu Sans (Debian: fonts-dejavu-core).

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use ab_glyph::{point, Font, FontVec, PxScale, ScaleFont};
use anyhow::{bail, Context, Result};

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
const LEFT: f64 = 84.0;
const RIGHT: f64 = 190.0; // room for the legend
const TOP: f64 = 44.0;
const BOTTOM: f64 = 62.0;

/// Colour-blind-safe (Okabe–Ito) line colours.
const PALETTE: [[u8; 3]; 6] = [
    [0, 114, 178],
    [213, 94, 0],
    [0, 158, 115],
    [204, 121, 167],
    [230, 159, 0],
    [86, 180, 233],
];
const INK: [u8; 3] = [30, 30, 30];
const GRID: [u8; 3] = [225, 225, 225];

/// Where the fonts of Debian's fonts-dejavu-core and a few other systems live.
const FONT_PATHS: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Decade-aligned log10 ranges of the axes and the plot rectangle, in pixels.
struct Layout {
    x: (f64, f64),
    y: (f64, f64),
    plot: (f64, f64, f64, f64), // left, top, right, bottom
}

fn usable(p: &(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite() && p.0 > 0.0 && p.1 > 0.0
}

impl Layout {
    fn new(chart: &Chart) -> Result<Layout> {
        let points: Vec<(f64, f64)> = chart
            .series
            .iter()
            .flat_map(|s| s.points.iter().copied().filter(usable))
            .collect();
        if points.is_empty() {
            bail!(
                "chart '{}' has no finite positive point to draw on log axes",
                chart.title
            );
        }
        let range = |f: &dyn Fn(&(f64, f64)) -> f64| {
            let lo = points.iter().map(f).fold(f64::INFINITY, f64::min).log10();
            let hi = points
                .iter()
                .map(f)
                .fold(f64::NEG_INFINITY, f64::max)
                .log10();
            let (lo, mut hi) = (lo.floor(), hi.ceil());
            if hi <= lo {
                hi = lo + 1.0;
            }
            (lo, hi)
        };
        Ok(Layout {
            x: range(&|p| p.0),
            y: range(&|p| p.1),
            plot: (LEFT, TOP, WIDTH as f64 - RIGHT, HEIGHT as f64 - BOTTOM),
        })
    }

    fn px(&self, x: f64) -> f64 {
        let (l, _, r, _) = self.plot;
        l + (x.log10() - self.x.0) / (self.x.1 - self.x.0) * (r - l)
    }

    fn py(&self, y: f64) -> f64 {
        let (_, t, _, b) = self.plot;
        b - (y.log10() - self.y.0) / (self.y.1 - self.y.0) * (b - t)
    }

    /// Every decade gets a line; labels thin out so they do not collide on wide ranges.
    fn decades(range: (f64, f64)) -> Vec<(f64, bool)> {
        let (lo, hi) = (range.0 as i32, range.1 as i32);
        let step = ((hi - lo) / 6 + 1).max(1);
        (lo..=hi)
            .map(|k| (10f64.powi(k), (k - lo) % step == 0))
            .collect()
    }

    /// 2·10^k … 9·10^k inside the range: the faint lines that make a log axis readable.
    fn minor(range: (f64, f64)) -> Vec<f64> {
        let (lo, hi) = (range.0 as i32, range.1 as i32);
        (lo..hi)
            .flat_map(|k| (2..10).map(move |m| m as f64 * 10f64.powi(k)))
            .collect()
    }
}

fn tick_label(v: f64) -> String {
    let k = v.log10().round() as i32;
    match k {
        -3..=-1 => format!("{}", v),
        0..=4 => format!("{}", v as i64),
        _ => format!("1e{k}"),
    }
}

fn rgb(c: [u8; 3]) -> String {
    format!("rgb({},{},{})", c[0], c[1], c[2])
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The chart as an SVG document: one `<polyline>` per series.
pub fn to_svg(chart: &Chart) -> Result<String> {
    let l = Layout::new(chart)?;
    let (pl, pt, pr, pb) = l.plot;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{WIDTH}\" height=\"{HEIGHT}\" viewBox=\"0 0 {WIDTH} {HEIGHT}\" font-family=\"DejaVu Sans, Arial, sans-serif\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
    );
    for x in Layout::minor(l.x) {
        let sx = l.px(x);
        s += &format!("<line x1=\"{sx:.1}\" y1=\"{pt}\" x2=\"{sx:.1}\" y2=\"{pb}\" stroke=\"{}\" stroke-width=\"0.6\"/>\n", rgb(GRID));
    }
    for y in Layout::minor(l.y) {
        let sy = l.py(y);
        s += &format!("<line x1=\"{pl}\" y1=\"{sy:.1}\" x2=\"{pr}\" y2=\"{sy:.1}\" stroke=\"{}\" stroke-width=\"0.6\"/>\n", rgb(GRID));
    }
    for (x, labelled) in Layout::decades(l.x) {
        let sx = l.px(x);
        s += &format!("<line x1=\"{sx:.1}\" y1=\"{pt}\" x2=\"{sx:.1}\" y2=\"{pb}\" stroke=\"rgb(190,190,190)\" stroke-width=\"1\"/>\n");
        if labelled {
            s += &format!(
                "<text x=\"{sx:.1}\" y=\"{:.1}\" font-size=\"13\" text-anchor=\"middle\">{}</text>\n",
                pb + 18.0,
                tick_label(x)
            );
        }
    }
    for (y, labelled) in Layout::decades(l.y) {
        let sy = l.py(y);
        s += &format!("<line x1=\"{pl}\" y1=\"{sy:.1}\" x2=\"{pr}\" y2=\"{sy:.1}\" stroke=\"rgb(190,190,190)\" stroke-width=\"1\"/>\n");
        if labelled {
            s += &format!(
                "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"13\" text-anchor=\"end\">{}</text>\n",
                pl - 6.0,
                sy + 4.5,
                tick_label(y)
            );
        }
    }
    s += &format!(
        "<rect x=\"{pl}\" y=\"{pt}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"none\" stroke=\"{}\"/>\n",
        pr - pl,
        pb - pt,
        rgb(INK)
    );
    s += &format!(
        "<text x=\"{:.1}\" y=\"26\" font-size=\"16\" text-anchor=\"middle\">{}</text>\n",
        (pl + pr) / 2.0,
        escape(&chart.title)
    );
    s += &format!(
        "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"14\" text-anchor=\"middle\">{}</text>\n",
        (pl + pr) / 2.0,
        HEIGHT as f64 - 16.0,
        escape(&chart.x_label)
    );
    s += &format!(
        "<text transform=\"translate(22,{:.1}) rotate(-90)\" font-size=\"14\" text-anchor=\"middle\">{}</text>\n",
        (pt + pb) / 2.0,
        escape(&chart.y_label)
    );
    for (i, series) in chart.series.iter().enumerate() {
        let c = rgb(PALETTE[i % PALETTE.len()]);
        let pts: Vec<(f64, f64)> = series
            .points
            .iter()
            .filter(|p| usable(p))
            .map(|&(x, y)| (l.px(x), l.py(y)))
            .collect();
        let list: Vec<String> = pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
        s += &format!(
            "<polyline points=\"{}\" fill=\"none\" stroke=\"{c}\" stroke-width=\"2.2\"/>\n",
            list.join(" ")
        );
        for (x, y) in &pts {
            s += &format!("<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"3.2\" fill=\"{c}\"/>\n");
        }
        let ly = pt + 12.0 + 22.0 * i as f64;
        s += &format!(
            "<line x1=\"{:.1}\" y1=\"{ly:.1}\" x2=\"{:.1}\" y2=\"{ly:.1}\" stroke=\"{c}\" stroke-width=\"2.2\"/>\n<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"13\">{}</text>\n",
            pr + 14.0,
            pr + 40.0,
            pr + 46.0,
            ly + 4.5,
            escape(&series.name)
        );
    }
    s += "</svg>\n";
    Ok(s)
}

/// An RGB8 image with anti-aliased drawing by coverage (distance to the shape, one pixel ramp).
struct Canvas {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl Canvas {
    fn new(width: u32, height: u32) -> Self {
        Canvas {
            width,
            height,
            data: vec![255; (width * height * 3) as usize],
        }
    }

    fn blend(&mut self, x: i64, y: i64, c: [u8; 3], coverage: f64) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 || coverage <= 0.0 {
            return;
        }
        let a = coverage.min(1.0);
        let i = ((y as u32 * self.width + x as u32) * 3) as usize;
        for (channel, &target) in self.data[i..i + 3].iter_mut().zip(&c) {
            let old = *channel as f64;
            *channel = (old + (target as f64 - old) * a).round() as u8;
        }
    }

    /// A segment of width `2·half` with round caps.
    fn line(&mut self, a: (f64, f64), b: (f64, f64), half: f64, c: [u8; 3]) {
        let pad = half + 1.0;
        let (x0, x1) = (a.0.min(b.0) - pad, a.0.max(b.0) + pad);
        let (y0, y1) = (a.1.min(b.1) - pad, a.1.max(b.1) + pad);
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len2 = dx * dx + dy * dy;
        for y in y0.floor() as i64..=y1.ceil() as i64 {
            for x in x0.floor() as i64..=x1.ceil() as i64 {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let t = if len2 > 0.0 {
                    (((px - a.0) * dx + (py - a.1) * dy) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let d = ((px - a.0 - t * dx).powi(2) + (py - a.1 - t * dy).powi(2)).sqrt();
                self.blend(x, y, c, half + 0.5 - d);
            }
        }
    }

    fn disc(&mut self, centre: (f64, f64), r: f64, c: [u8; 3]) {
        self.line(centre, centre, r, c);
    }

    /// Text with its baseline at `y`; `align` 0 = left, 0.5 = centred, 1 = right; `vertical`
    /// turns it a quarter to read bottom to top (a y-axis label), centred on (x, y).
    #[allow(clippy::too_many_arguments)]
    fn text(
        &mut self,
        font: &FontVec,
        s: &str,
        x: f64,
        y: f64,
        size: f32,
        align: f64,
        vertical: bool,
        c: [u8; 3],
    ) {
        let scaled = font.as_scaled(PxScale::from(size));
        let mut glyphs = Vec::new();
        let mut caret = 0.0f32;
        let mut previous = None;
        for ch in s.chars() {
            let id = font.glyph_id(ch);
            if let Some(p) = previous {
                caret += scaled.kern(p, id);
            }
            glyphs.push(id.with_scale_and_position(size, point(caret, 0.0)));
            caret += scaled.h_advance(id);
            previous = Some(id);
        }
        let start = -(caret as f64) * align;
        for g in glyphs {
            if let Some(outline) = font.outline_glyph(g) {
                let b = outline.px_bounds();
                let mut pixels = Vec::new();
                outline.draw(|gx, gy, cov| pixels.push((gx, gy, cov)));
                for (gx, gy, cov) in pixels {
                    // Offsets from the text origin (along the text, below the baseline).
                    let u = start + b.min.x as f64 + gx as f64;
                    let v = b.min.y as f64 + gy as f64;
                    let (px, py) = if vertical {
                        (x + v, y - u)
                    } else {
                        (x + u, y + v)
                    };
                    self.blend(px.floor() as i64, py.floor() as i64, c, cov as f64);
                }
            }
        }
    }

    fn write_png(&self, path: &Path) -> Result<()> {
        let file =
            File::create(path).with_context(|| format!("cannot create '{}'", path.display()))?;
        let mut encoder = png::Encoder::new(BufWriter::new(file), self.width, self.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder
            .write_header()
            .with_context(|| format!("writing '{}'", path.display()))?;
        writer
            .write_image_data(&self.data)
            .with_context(|| format!("writing '{}'", path.display()))?;
        Ok(())
    }
}

/// The first TTF found: `$VOLGRAD_FONT`, then the usual system places.
pub fn find_font() -> Option<(PathBuf, FontVec)> {
    let from_env = std::env::var_os("VOLGRAD_FONT").map(PathBuf::from);
    from_env
        .into_iter()
        .chain(FONT_PATHS.iter().map(PathBuf::from))
        .find_map(|p| {
            let bytes = std::fs::read(&p).ok()?;
            FontVec::try_from_vec(bytes).ok().map(|f| (p, f))
        })
}

/// Draws the chart as a PNG. Returns false when no font was found: the lines are drawn, the
/// labels are not (the SVG has them), and the caller should say so.
pub fn write_png(chart: &Chart, path: &Path) -> Result<bool> {
    let l = Layout::new(chart)?;
    let (pl, pt, pr, pb) = l.plot;
    let font = find_font().map(|(_, f)| f);
    let mut c = Canvas::new(WIDTH, HEIGHT);
    for x in Layout::minor(l.x) {
        c.line((l.px(x), pt), (l.px(x), pb), 0.3, GRID);
    }
    for y in Layout::minor(l.y) {
        c.line((pl, l.py(y)), (pr, l.py(y)), 0.3, GRID);
    }
    for (x, _) in Layout::decades(l.x) {
        c.line((l.px(x), pt), (l.px(x), pb), 0.5, [190; 3]);
    }
    for (y, _) in Layout::decades(l.y) {
        c.line((pl, l.py(y)), (pr, l.py(y)), 0.5, [190; 3]);
    }
    for (a, b) in [
        ((pl, pt), (pr, pt)),
        ((pr, pt), (pr, pb)),
        ((pr, pb), (pl, pb)),
        ((pl, pb), (pl, pt)),
    ] {
        c.line(a, b, 0.6, INK);
    }
    for (i, series) in chart.series.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        let pts: Vec<(f64, f64)> = series
            .points
            .iter()
            .filter(|p| usable(p))
            .map(|&(x, y)| (l.px(x), l.py(y)))
            .collect();
        for w in pts.windows(2) {
            c.line(w[0], w[1], 1.1, colour);
        }
        for &p in &pts {
            c.disc(p, 3.2, colour);
        }
        let ly = pt + 12.0 + 22.0 * i as f64;
        c.line((pr + 14.0, ly), (pr + 40.0, ly), 1.1, colour);
        if let Some(f) = &font {
            c.text(f, &series.name, pr + 46.0, ly + 4.5, 13.0, 0.0, false, INK);
        }
    }
    if let Some(f) = &font {
        for (x, labelled) in Layout::decades(l.x) {
            if labelled {
                c.text(f, &tick_label(x), l.px(x), pb + 18.0, 13.0, 0.5, false, INK);
            }
        }
        for (y, labelled) in Layout::decades(l.y) {
            if labelled {
                c.text(
                    f,
                    &tick_label(y),
                    pl - 6.0,
                    l.py(y) + 4.5,
                    13.0,
                    1.0,
                    false,
                    INK,
                );
            }
        }
        c.text(
            f,
            &chart.title,
            (pl + pr) / 2.0,
            26.0,
            16.0,
            0.5,
            false,
            INK,
        );
        let bottom = HEIGHT as f64 - 16.0;
        c.text(
            f,
            &chart.x_label,
            (pl + pr) / 2.0,
            bottom,
            14.0,
            0.5,
            false,
            INK,
        );
        c.text(
            f,
            &chart.y_label,
            22.0,
            (pt + pb) / 2.0,
            14.0,
            0.5,
            true,
            INK,
        );
    }
    c.write_png(path)?;
    Ok(font.is_some())
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
        let l = Layout::new(&chart()).unwrap();
        assert_eq!(l.x, (-1.0, 2.0));
        assert_eq!(l.y, (-2.0, 1.0));
        let (pl, pt, pr, pb) = l.plot;
        assert!((l.px(0.1) - pl).abs() < 1e-9 && (l.px(100.0) - pr).abs() < 1e-9);
        assert!((l.py(0.01) - pb).abs() < 1e-9 && (l.py(10.0) - pt).abs() < 1e-9);
    }

    #[test]
    fn svg_has_one_polyline_per_series_and_escapes_names() {
        let svg = to_svg(&chart()).unwrap();
        assert_eq!(svg.matches("<polyline").count(), 2);
        assert!(svg.contains("b&lt;c"));
        assert!(!svg.contains("NaN"));
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
