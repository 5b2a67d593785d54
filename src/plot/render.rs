//! Drawing one figure (a title, a legend row, three stacked joint panels sharing the time
//! axis) with plotters, to PNG and to SVG. Text is rasterised by ab_glyph from a font compiled
//! into the binary, so nothing is needed from the system at build or run time.

use super::figures::Role;
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::OnceLock;

/// DejaVu Sans (Bitstream Vera licence, see `fonts/LICENSE-DejaVu.txt`).
const FONT: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

/// Figure width by default, px (the SVG's user units too).
pub const WIDTH: u32 = 1200;
/// Figure height by default, px.
pub const HEIGHT: u32 = 900;
/// The largest side a figure may have, px (a PNG buffer of 3 bytes a pixel).
pub const MAX_SIDE: u32 = 8000;

const TITLE_H: u32 = 46;
const LEGEND_H: u32 = 30;
const TITLE_PX: f64 = 24.0;
const PANEL_TITLE_PX: f64 = 18.0;
const LABEL_PX: f64 = 16.0;
const DESC_PX: f64 = 17.0;

/// Why a figure could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The font compiled into the binary could not be loaded.
    #[error("the embedded font could not be loaded")]
    Font,
    /// The drawing backend failed.
    #[error("drawing: {0}")]
    Draw(String),
    /// The PNG encoder failed.
    #[error("encoding the PNG: {0}")]
    Png(#[from] png::EncodingError),
    /// Writing the file failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The file cannot be created there.
    #[error(transparent)]
    Output(#[from] crate::output::OutputError),
}

/// One line as drawn: its points (already in plotted units) and its pen.
pub struct Line {
    /// (time s, value in plotted units), in time order.
    pub points: Vec<(f64, f64)>,
    /// Its pen.
    pub role: Role,
}

/// One panel of a figure (one joint, or a norm).
pub struct Panel {
    /// Heading drawn above it.
    pub title: &'static str,
    /// Its lines, in drawing order.
    pub lines: Vec<Line>,
}

/// A figure ready to draw: panels stacked, sharing the time axis.
pub struct Figure {
    /// Heading drawn above the panels.
    pub title: &'static str,
    /// Y-axis description, with its unit.
    pub y_desc: &'static str,
    /// Time axis range, s.
    pub x_range: (f64, f64),
    /// Shade the start-up blend, from the first sample to this time.
    pub shade_until: Option<f64>,
    /// Draw y = 0 (error signals); their y range leaves out the start-up blend (shaded),
    /// whose transient would flatten the steady error to a line.
    pub zero_line: bool,
    /// Width and height, px.
    pub size: (u32, u32),
    /// Text size relative to the default.
    pub font_scale: f64,
    /// Labels and roles, in drawing order.
    pub legend: Vec<(&'static str, Role)>,
    /// The panels, top to bottom.
    pub panels: Vec<Panel>,
}

/// The start-up blend's shading.
const SHADE: RGBColor = RGBColor(228, 228, 228);
const SHADE_LABEL: &str = "start-up blend";

/// Colour and width per role: the target wide and pale under the measurement, the estimate
/// in a contrasting colour on top. Blue against orange stays apart for colour-blind readers;
/// the thin lines are dark enough to read at one pixel.
fn pen(role: Role) -> ShapeStyle {
    let (color, width) = match role {
        Role::Target => (RGBColor(230, 159, 0), 3),
        Role::Measured => (RGBColor(0, 90, 181), 1),
        Role::Estimate => (RGBColor(213, 94, 0), 2),
        Role::Error => (RGBColor(0, 130, 100), 1),
        Role::Wall => (RGBColor(110, 110, 110), 2),
    };
    color.stroke_width(width)
}

fn register_font() -> Result<(), RenderError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        Err(RenderError::Font)
    }
}

/// The file formats every figure is written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Png,
    Svg,
}

/// Every figure is written in each of these.
pub const FORMATS: [Format; 2] = [Format::Png, Format::Svg];

impl Format {
    pub fn extension(self) -> &'static str {
        match self {
            Format::Png => "png",
            Format::Svg => "svg",
        }
    }
}

/// Draw `figure` into a new file at `path` in `format`.
pub fn write(figure: &Figure, format: Format, path: &Path) -> Result<(), RenderError> {
    match format {
        Format::Png => write_png(figure, path),
        Format::Svg => write_svg(figure, path),
    }
}

fn write_png(figure: &Figure, path: &Path) -> Result<(), RenderError> {
    register_font()?;
    let (w, h) = figure.size;
    let mut rgb = vec![0u8; (w as usize) * (h as usize) * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        draw(&root, figure, Surface::Raster)?;
        root.present()
            .map_err(|e| RenderError::Draw(e.to_string()))?;
    }
    // Encoded here rather than through plotters' `image` feature: one small crate instead of
    // a whole image library.
    crate::output::write_with(path, |file| {
        let mut encoder = png::Encoder::new(file, w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::High);
        let mut writer = encoder.write_header()?;
        writer.write_image_data(&rgb)?;
        writer.finish()?;
        Ok(())
    })
}

fn write_svg(figure: &Figure, path: &Path) -> Result<(), RenderError> {
    register_font()?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, figure.size).into_drawing_area();
        draw(&root, figure, Surface::Vector)?;
        root.present()
            .map_err(|e| RenderError::Draw(e.to_string()))?;
    }
    Ok(crate::output::write_bytes(path, svg.as_bytes())?)
}

/// What the figure is drawn on: it decides how wide lines are made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Surface {
    Raster,
    Vector,
}

fn font(px: f64) -> TextStyle<'static> {
    (FAMILY, px).into_font().color(&BLACK)
}

/// Pixel sizes that grow with the text: title and legend rows, label areas.
fn px(figure: &Figure, base: f64) -> f64 {
    base * figure.font_scale
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    figure: &Figure,
    surface: Surface,
) -> Result<(), RenderError> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| RenderError::Draw(e.to_string());
    root.fill(&WHITE).map_err(err)?;
    let title_h = px(figure, TITLE_H as f64) as u32;
    let (title_area, rest) = root.split_vertically(title_h);
    let (legend_area, panels_area) = rest.split_vertically(px(figure, LEGEND_H as f64) as u32);

    let title_style = font(px(figure, TITLE_PX)).pos(Pos::new(HPos::Center, VPos::Center));
    title_area
        .draw_text(
            figure.title,
            &title_style,
            (figure.size.0 as i32 / 2, title_h as i32 / 2 + 4),
        )
        .map_err(err)?;
    draw_legend(&legend_area, figure).map_err(err)?;

    let panels = panels_area.split_evenly((figure.panels.len().max(1), 1));
    let last = figure.panels.len().saturating_sub(1);
    for (i, (area, panel)) in panels.iter().zip(&figure.panels).enumerate() {
        draw_panel(area, figure, panel, i == last, surface).map_err(err)?;
    }
    Ok(())
}

/// One centred row: a short stroke in each line's pen, then its label; last the shading.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    figure: &Figure,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (lines, shaded) = (&figure.legend, figure.shade_until.is_some());
    let entries: Vec<(&str, Option<Role>)> = lines
        .iter()
        .map(|&(label, role)| (label, Some(role)))
        .chain(shaded.then_some((SHADE_LABEL, None)))
        .collect();
    const SWATCH: i32 = 32;
    const GAP: i32 = 8;
    const SPACING: i32 = 36;
    let style = font(px(figure, LABEL_PX)).pos(Pos::new(HPos::Left, VPos::Center));
    let widths: Vec<i32> = entries
        .iter()
        .map(|(label, _)| {
            area.estimate_text_size(label, &style)
                .map(|(w, _)| w as i32)
        })
        .collect::<Result<_, _>>()?;
    let total: i32 = widths.iter().map(|w| SWATCH + GAP + w).sum::<i32>()
        + SPACING * (entries.len() as i32 - 1).max(0);
    let y = px(figure, LEGEND_H as f64) as i32 / 2;
    let mut x = (figure.size.0 as i32 - total) / 2;
    for ((label, role), w) in entries.iter().zip(widths) {
        match role {
            Some(role) => {
                area.draw(&PathElement::new(vec![(x, y), (x + SWATCH, y)], pen(*role)))?
            }
            None => area.draw(&Rectangle::new(
                [(x, y - 7), (x + SWATCH, y + 7)],
                SHADE.filled(),
            ))?,
        }
        area.draw_text(label, &style, (x + SWATCH + GAP, y))?;
        x += SWATCH + GAP + w + SPACING;
    }
    Ok(())
}

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    figure: &Figure,
    panel: &Panel,
    bottom: bool,
    surface: Surface,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (x0, x1) = widen(
        (figure.x_range.0.max(-LIMIT), figure.x_range.1.min(LIMIT)),
        0.0,
    );
    let steady_from = figure.zero_line.then_some(figure.shade_until).flatten();
    let (y0, y1) = y_range(panel, figure.zero_line, steady_from);
    let mut chart = ChartBuilder::on(area)
        .caption(panel.title, font(px(figure, PANEL_TITLE_PX)))
        .margin_left(10)
        .margin_right(24)
        .margin_top(2)
        .margin_bottom(if bottom { 6 } else { 2 })
        .x_label_area_size(px(figure, if bottom { 48.0 } else { 26.0 }) as u32)
        .y_label_area_size(px(figure, 76.0) as u32)
        .build_cartesian_2d(x0..x1, y0..y1)?;

    let x_labels = 12;
    let y_labels = 5;
    let x_fmt = tick_formatter((x0, x1), x_labels);
    let y_fmt = tick_formatter((y0, y1), y_labels);
    if let Some(end) = figure.shade_until {
        // Under the mesh and the lines.
        chart.draw_series(std::iter::once(Rectangle::new(
            [(x0, y0), (end.min(x1), y1)],
            SHADE.filled(),
        )))?;
    }
    let mut mesh = chart.configure_mesh();
    mesh.x_labels(x_labels)
        .y_labels(y_labels)
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&y_fmt)
        .label_style(font(px(figure, LABEL_PX)))
        .axis_desc_style(font(px(figure, DESC_PX)))
        .y_desc(figure.y_desc)
        .max_light_lines(4)
        .bold_line_style(RGBColor(215, 215, 215))
        .light_line_style(RGBColor(242, 242, 242));
    if bottom {
        mesh.x_desc("time (s)");
    }
    mesh.draw()?;

    if figure.zero_line && y0 < 0.0 && y1 > 0.0 {
        chart.draw_series(LineSeries::new(
            [(x0, 0.0), (x1, 0.0)],
            RGBColor(90, 90, 90).stroke_width(1),
        ))?;
    }
    draw_lines(&mut chart, panel, surface, (x0, x1), (y0, y1))
}

/// The panel's lines on its chart, over the mesh. `(x0, x1)`, `(y0, y1)`: the chart's ranges.
fn draw_lines<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    panel: &Panel,
    surface: Surface,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    // plotters fills a wide polyline as one polygon, which a dense zigzag (min/max pairs,
    // repeated pixels) turns into specks and spikes. On a bitmap a wide line is therefore
    // drawn as 1-px lines shifted by whole pixels; SVG strokes width natively.
    let (w_px, h_px) = chart.plotting_area().dim_in_pixel();
    let pixel = (
        (x1 - x0) / f64::from(w_px.max(1)),
        (y1 - y0) / f64::from(h_px.max(1)),
    );
    // Points far off the chart (garbage values beyond LIMIT) would overflow plotters' pixel
    // arithmetic; pulled to just outside the frame they are still clipped, lines still leave
    // the chart in their direction.
    let (xs, ys) = (x1 - x0, y1 - y0);
    let inside = |(x, y): (f64, f64)| (x.clamp(x0 - xs, x1 + xs), y.clamp(y0 - ys, y1 + ys));
    for line in &panel.lines {
        let style = pen(line.role);
        if surface == Surface::Raster && style.stroke_width > 1 {
            for (dx, dy) in pixel_offsets(style.stroke_width) {
                let shifted = line
                    .points
                    .iter()
                    .map(|&(x, y)| inside((x + dx * pixel.0, y + dy * pixel.1)));
                chart.draw_series(LineSeries::new(shifted, style.stroke_width(1)))?;
            }
        } else {
            chart.draw_series(LineSeries::new(
                line.points.iter().map(|&p| inside(p)),
                style,
            ))?;
        }
    }
    Ok(())
}

/// Whole-pixel shifts whose union of 1-px lines looks like a line `width` pixels wide.
fn pixel_offsets(width: u32) -> Vec<(f64, f64)> {
    let r = width as i32 / 2;
    let lo = -(width as i32 - 1) / 2;
    let mut out = Vec::new();
    for dx in lo..=r {
        for dy in lo..=r {
            // A diamond, not a square: square corners make diagonal lines look heavier.
            if width <= 2 || dx.abs() + dy.abs() <= r {
                out.push((f64::from(dx), f64::from(dy)));
            }
        }
    }
    out
}

/// The y range of a panel: every line's points, 6 % headroom, and y = 0 kept in view for
/// error plots when it is near (so the sign of the error is obvious).
fn y_range(panel: &Panel, zero_line: bool, from_t: Option<f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let points = || panel.lines.iter().flat_map(|l| l.points.iter());
    // Points from `from_t` on, when there are any (the blend's transient off the scale).
    let after = from_t.filter(|&t0| points().any(|&(t, y)| t > t0 && y.is_finite()));
    for (_, y) in points().filter(|&&(t, _)| after.is_none_or(|t0| t > t0)) {
        lo = lo.min(*y);
        hi = hi.max(*y);
    }
    if lo > hi {
        // No finite point at all (an all-gap signal): an empty panel with a sane axis.
        return (-1.0, 1.0);
    }
    if zero_line {
        lo = lo.min(0.0);
        hi = hi.max(0.0);
    }
    // A garbage value near f64::MAX would make the span infinite, on which plotters' tick
    // search never ends; such points are drawn off the chart instead.
    widen((lo.max(-LIMIT), hi.min(LIMIT)), 0.06)
}

/// The largest magnitude an axis shows.
const LIMIT: f64 = 1e300;

/// Pad a range by `frac` of its span each side; a point-like range gets a span of its own.
fn widen((lo, hi): (f64, f64), frac: f64) -> (f64, f64) {
    let span = hi - lo;
    if span > 0.0 && span.is_finite() {
        (lo - span * frac, hi + span * frac)
    } else {
        let half = (lo.abs() * 0.05).max(1e-3);
        (lo - half, hi + half)
    }
}

/// Tick labels with as many decimals as the tick spacing needs, no more: plotters' default
/// prints long float tails on small ranges. Axes that would need very long labels (huge or
/// tiny values, from a broken log) get scientific notation instead.
fn tick_formatter((lo, hi): (f64, f64), labels: usize) -> impl Fn(&f64) -> String {
    // The ticks plotters will draw, asked of plotters itself: the decimals follow the step it
    // chose (0.05 needs two), not a guess at it.
    let decimals = exact_decimals(&RangedCoordf64::from(lo..hi).key_points(labels))
        .unwrap_or_else(|| tick_decimals(hi - lo, labels));
    let scientific = decimals > 6 || lo.abs().max(hi.abs()) >= 1e7;
    move |v: &f64| {
        if scientific {
            return format!("{v:.2e}");
        }
        let s = format!("{v:.decimals$}");
        // "-0.00" reads as a sign error.
        if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
            s[1..].to_string()
        } else {
            s
        }
    }
}

/// The fewest decimals (up to 6) that print every one of `ticks` exactly; None when there are
/// none or they need more (scientific notation then).
fn exact_decimals(ticks: &[f64]) -> Option<usize> {
    // The step between ticks: labels must tell neighbours apart.
    let step = ticks
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .filter(|d| *d > 0.0)
        .fold(f64::INFINITY, f64::min);
    if !step.is_finite() {
        return None;
    }
    (0..=6).find(|&d| {
        let scale = 10f64.powi(d as i32);
        step * scale >= 1.0 - 1e-9
            && ticks.iter().all(|&v| {
                let scaled = v * scale;
                (scaled - scaled.round()).abs() <= 1e-6 * scaled.abs().max(1.0)
            })
    })
}

/// Decimals for ticks spaced at least `span / labels` apart, rounded to 1, 2 or 5 × 10^k.
fn tick_decimals(span: f64, labels: usize) -> usize {
    if !span.is_finite() || span <= 0.0 || labels == 0 {
        return 2;
    }
    let raw = span / labels as f64;
    let exp = raw.log10().floor();
    let mantissa = raw / 10f64.powf(exp);
    // 1, 2 and 5 steps need no more digits than their exponent; 2.5 never occurs.
    let step_exp = if mantissa > 5.0 { exp + 1.0 } else { exp };
    (-step_exp).max(0.0) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tick_decimals_follow_the_spacing() {
        assert_eq!(tick_decimals(10.0, 10), 0);
        assert_eq!(tick_decimals(3.0, 12), 1);
        assert_eq!(tick_decimals(0.06, 5), 2);
        assert_eq!(tick_decimals(0.006, 5), 3);
        assert_eq!(tick_decimals(600.0, 12), 0);
        assert_eq!(tick_decimals(f64::NAN, 5), 2);
    }

    #[test]
    fn pixel_offsets_make_the_width() {
        assert_eq!(pixel_offsets(1), vec![(0.0, 0.0)]);
        assert_eq!(pixel_offsets(2).len(), 4);
        let three = pixel_offsets(3);
        assert_eq!(three.len(), 5);
        assert!(three.contains(&(0.0, 0.0)) && three.contains(&(-1.0, 0.0)));
    }

    #[test]
    fn negative_zero_is_printed_as_zero() {
        let f = tick_formatter((-0.5, 0.5), 5);
        assert_eq!(f(&-0.0001), "0.0");
        assert_eq!(f(&-0.2), "-0.2");
    }

    #[test]
    fn labels_have_the_decimals_of_the_ticks_plotters_draws() {
        // The control-effort axis: ticks 0.05 apart need two decimals.
        for (lo, hi, n) in [
            (-0.12, 0.22, 5),
            (-0.11, 0.11, 5),
            (0.0, 10.0, 12),
            (-3.3, 7.9, 5),
        ] {
            let ticks = RangedCoordf64::from(lo..hi).key_points(n);
            let fmt = tick_formatter((lo, hi), n);
            let labels: Vec<String> = ticks.iter().map(&fmt).collect();
            for (t, l) in ticks.iter().zip(&labels) {
                let back: f64 = l.parse().unwrap();
                assert!((back - t).abs() < 1e-9, "{lo}..{hi}: {t} printed {l}");
            }
            let mut distinct = labels.clone();
            distinct.dedup();
            assert_eq!(distinct.len(), labels.len(), "{labels:?}");
        }
        assert_eq!(exact_decimals(&[-0.1, -0.05, 0.0, 0.05]), Some(2));
        assert_eq!(exact_decimals(&[0.0, 0.25, 0.5]), Some(2));
        assert_eq!(exact_decimals(&[0.0]), None);
    }

    #[test]
    fn huge_and_tiny_axes_use_scientific_notation() {
        assert_eq!(tick_formatter((-1e300, 1e300), 5)(&5e299), "5.00e299");
        assert_eq!(tick_formatter((0.0, 1e-9), 5)(&5e-10), "5.00e-10");
        assert_eq!(tick_formatter((0.0, 600.0), 12)(&100.0), "100");
    }

    #[test]
    fn degenerate_ranges_get_a_span() {
        let (lo, hi) = widen((2.0, 2.0), 0.06);
        assert!(lo < 2.0 && hi > 2.0);
        let (lo, hi) = widen((0.0, 0.0), 0.06);
        assert!(lo < 0.0 && hi > 0.0);
        let p = Panel {
            title: "x",
            lines: vec![],
        };
        assert_eq!(y_range(&p, false, None), (-1.0, 1.0));
        let p = Panel {
            title: "x",
            lines: vec![Line {
                points: vec![(0.0, f64::MAX), (1.0, -f64::MAX)],
                role: Role::Measured,
            }],
        };
        let (lo, hi) = y_range(&p, false, None);
        assert!((hi - lo).is_finite(), "{lo} {hi}");
    }
}
