//! Pictures a person would rather look at than read: fields as heat maps in a perceptually
//! uniform colour map (viridis) with a colour bar, stacked panels that share one scale, sensing
//! disks drawn over them, and whole sequences as GIFs. Row 0 of a field is drawn at the bottom
//! (y up, as the workspace's metres).
//!
//! Text uses DejaVu Sans from the system (`HETFLEET_FONT` to point elsewhere); without a font
//! the pictures are drawn without labels rather than not at all.

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use std::path::Path;
use std::sync::OnceLock;

#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("{0}")]
    Input(String),
    #[error("drawing {path}: {msg}")]
    Draw { path: String, msg: String },
}

/// One heat map panel.
#[derive(Debug, Clone)]
pub struct Panel<'a> {
    pub values: &'a [f64],
    pub rows: usize,
    pub cols: usize,
    pub title: String,
    /// Circles `(row, col, radius)` in cells, drawn in white.
    pub disks: Vec<(f64, f64, f64)>,
}

impl Panel<'_> {
    fn check(&self) -> Result<(), PlotError> {
        if self.rows == 0 || self.cols == 0 || self.values.len() != self.rows * self.cols {
            return Err(PlotError::Input(format!(
                "panel {:?}: {} values for a {} x {} grid",
                self.title,
                self.values.len(),
                self.rows,
                self.cols
            )));
        }
        Ok(())
    }
}

const FONT: &str = "sans-serif";
const TITLE_H: u32 = 26;
const BAR_W: u32 = 96;
const PAD: u32 = 8;

/// Register the system font once; `false` when there is none.
fn font_ready() -> bool {
    static READY: OnceLock<bool> = OnceLock::new();
    *READY.get_or_init(|| {
        let candidates = [
            std::env::var("HETFLEET_FONT").unwrap_or_default(),
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf".into(),
            "/usr/share/fonts/TTF/DejaVuSans.ttf".into(),
            "/usr/share/fonts/dejavu/DejaVuSans.ttf".into(),
        ];
        for c in candidates.iter().filter(|c| !c.is_empty()) {
            if let Ok(bytes) = std::fs::read(c) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(FONT, FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

/// Finite min and max over all panels (a constant field gets a unit range around its value).
pub fn range_of(panels: &[Panel<'_>]) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in panels.iter().flat_map(|p| p.values.iter()).filter(|v| v.is_finite()) {
        lo = lo.min(*v);
        hi = hi.max(*v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-300 {
        return (lo - 0.5, hi + 0.5);
    }
    (lo, hi)
}

/// Pixels per cell so the widest panel is about 1,000-1,200 px wide.
fn scale_for(cols: usize) -> u32 {
    ((1152 / cols.max(1)) as u32).clamp(1, 24)
}

fn layout(panels: &[Panel<'_>]) -> (u32, u32, u32) {
    let s = scale_for(panels.iter().map(|p| p.cols).max().unwrap_or(1));
    let w = panels.iter().map(|p| p.cols as u32 * s).max().unwrap_or(1) + BAR_W + 2 * PAD;
    let h = panels.iter().map(|p| p.rows as u32 * s + TITLE_H).sum::<u32>() + 2 * PAD;
    (s, w, h)
}

/// A cell with no value (land, cloud): the live view's grey, outside the colour scale.
const NO_DATA: RGBColor = RGBColor(150, 150, 150);

fn draw<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panels: &[Panel<'_>],
    (lo, hi): (f64, f64),
    s: u32,
) -> Result<(), String> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    area.fill(&WHITE).map_err(err)?;
    let text = font_ready();
    let colour = |v: f64| {
        if v.is_finite() {
            ViridisRGB::get_color_normalized(v.clamp(lo, hi), lo, hi)
        } else {
            NO_DATA
        }
    };
    let mut y0 = PAD as i32;
    for p in panels {
        if text {
            area.draw_text(&p.title, &(FONT, 18).into_font().color(&BLACK), (PAD as i32, y0 + 3))
                .map_err(err)?;
        }
        y0 += TITLE_H as i32;
        let top = y0;
        let h = p.rows as i32 * s as i32;
        for r in 0..p.rows {
            for c in 0..p.cols {
                let col = colour(p.values[r * p.cols + c]);
                let (x, y) = (PAD as i32 + c as i32 * s as i32, top + h - (r as i32 + 1) * s as i32);
                for dy in 0..s as i32 {
                    for dx in 0..s as i32 {
                        area.draw_pixel((x + dx, y + dy), &col).map_err(err)?;
                    }
                }
            }
        }
        for &(r, c, rad) in &p.disks {
            let centre = (
                PAD as i32 + ((c + 0.5) * s as f64) as i32,
                top + h - ((r + 0.5) * s as f64) as i32,
            );
            area.draw(&Circle::new(
                centre,
                (rad * s as f64) as i32,
                ShapeStyle {
                    color: WHITE.to_rgba(),
                    filled: false,
                    stroke_width: 2,
                },
            ))
            .map_err(err)?;
        }
        y0 += h;
    }
    // Colour bar along the right, the full height of the panels.
    let (w, _) = area.dim_in_pixel();
    let bx = (w - BAR_W + PAD) as i32;
    let (by0, by1) = (PAD as i32 + TITLE_H as i32, y0);
    let span = (by1 - by0).max(1);
    for y in by0..by1 {
        let v = hi - (hi - lo) * (y - by0) as f64 / span as f64;
        area.draw(&Rectangle::new([(bx, y), (bx + 18, y + 1)], colour(v).filled()))
            .map_err(err)?;
    }
    if text {
        for k in 0..=4 {
            let f = k as f64 / 4.0;
            let v = hi - (hi - lo) * f;
            let y = by0 + (f * span as f64) as i32;
            area.draw_text(
                &format_tick(v),
                &(FONT, 14).into_font().color(&BLACK),
                (bx + 22, (y - 7).max(0)),
            )
            .map_err(err)?;
        }
    }
    Ok(())
}

/// Tick values for a log axis over `lo..hi` (> 0): 1, 2 and 5 x 10^k inside it (every
/// mantissa 1-9 when that gives fewer than 3), and the light lines at every mantissa 1-9.
fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>) {
    let decades = lo.log10().floor() as i32..=hi.log10().ceil() as i32;
    let at = |mantissas: &[f64]| -> Vec<f64> {
        decades
            .clone()
            .flat_map(|k| mantissas.iter().map(move |m| m * 10f64.powi(k)))
            .filter(|v| *v >= lo && *v <= hi)
            .collect()
    };
    let all = at(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
    let bold = at(&[1.0, 2.0, 5.0]);
    (if bold.len() >= 3 { bold } else { all.clone() }, all)
}

fn format_tick(v: f64) -> String {
    if v != 0.0 && (v.abs() < 1e-2 || v.abs() >= 1e4) {
        format!("{v:.2e}")
    } else {
        format!("{v:.3}")
    }
}

/// Write panels stacked top to bottom to a PNG, on one colour scale (`range`, or the data's).
pub fn png(path: impl AsRef<Path>, panels: &[Panel<'_>], range: Option<(f64, f64)>) -> Result<(), PlotError> {
    if panels.is_empty() {
        return Err(PlotError::Input("nothing to draw".into()));
    }
    for p in panels {
        p.check()?;
    }
    let path = path.as_ref();
    let range = range.unwrap_or_else(|| range_of(panels));
    let (s, w, h) = layout(panels);
    let fail = |msg: String| PlotError::Draw {
        path: path.display().to_string(),
        msg,
    };
    let root = BitMapBackend::new(path, (w, h)).into_drawing_area();
    draw(&root, panels, range, s).map_err(fail)?;
    root.present().map_err(|e| fail(e.to_string()))?;
    Ok(())
}

/// Write a sequence of frames (each a list of panels of the same shapes) as an animated GIF on
/// one colour scale; `on_frame` is called after each frame (for progress bars).
pub fn gif<'a>(
    path: impl AsRef<Path>,
    frames: impl IntoIterator<Item = Vec<Panel<'a>>>,
    range: (f64, f64),
    delay_ms: u32,
    mut on_frame: impl FnMut(),
) -> Result<(), PlotError> {
    let path = path.as_ref();
    let fail = |msg: String| PlotError::Draw {
        path: path.display().to_string(),
        msg,
    };
    let mut frames = frames.into_iter().peekable();
    let first = frames.peek().ok_or_else(|| PlotError::Input("no frames".into()))?;
    let (s, w, h) = layout(first);
    let root = BitMapBackend::gif(path, (w, h), delay_ms)
        .map_err(|e| fail(e.to_string()))?
        .into_drawing_area();
    for panels in frames {
        for p in &panels {
            p.check()?;
        }
        if layout(&panels) != (s, w, h) {
            return Err(PlotError::Input("every GIF frame must have the same shape".into()));
        }
        draw(&root, &panels, range, s).map_err(fail)?;
        root.present().map_err(|e| fail(e.to_string()))?;
        on_frame();
    }
    Ok(())
}

/// One named line of a chart.
#[derive(Debug, Clone)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

fn palette(i: usize) -> RGBColor {
    // Ten distinct colours (matplotlib's tab10): a report draws up to 8 teams.
    const C: [RGBColor; 10] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
    ];
    C[i % C.len()]
}

fn chart_fail(path: &Path) -> impl Fn(String) -> PlotError + '_ {
    move |msg| PlotError::Draw {
        path: path.display().to_string(),
        msg,
    }
}

fn need_font() -> Result<(), PlotError> {
    if font_ready() {
        Ok(())
    } else {
        Err(PlotError::Input(
            "charts need a font: install fonts-dejavu-core or set HETFLEET_FONT".into(),
        ))
    }
}

/// A line chart (log-scaled y when `log_y`, for errors spanning decades).
pub fn lines(
    path: impl AsRef<Path>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
    log_y: bool,
) -> Result<(), PlotError> {
    let bands: Vec<Band> = series
        .iter()
        .map(|s| Band {
            name: s.name.clone(),
            points: s.points.iter().map(|&(x, y)| (x, y, y, y)).collect(),
        })
        .collect();
    bands_chart(path, title, x_desc, y_desc, &bands, log_y, false)
}

/// A named line with a shaded band around it: `(x, y, lo, hi)`.
#[derive(Debug, Clone)]
pub struct Band {
    pub name: String,
    pub points: Vec<(f64, f64, f64, f64)>,
}

/// Lines (e.g. means over seeds) each with its shaded interval (e.g. 95%).
pub fn bands(
    path: impl AsRef<Path>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    bands: &[Band],
    log_y: bool,
) -> Result<(), PlotError> {
    bands_chart(path, title, x_desc, y_desc, bands, log_y, true)
}

/// The chart's size in pixels: the plot, and the strip right of it that holds the legend
/// (never over a line or a band, however many teams).
const CHART: (u32, u32) = (960, 520);
const LEGEND_W: u32 = 250;

fn bands_chart(
    path: impl AsRef<Path>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    bands: &[Band],
    log_y: bool,
    shade: bool,
) -> Result<(), PlotError> {
    need_font()?;
    let path = path.as_ref();
    let fail = chart_fail(path);
    let root = BitMapBackend::new(path, (CHART.0 + LEGEND_W, CHART.1)).into_drawing_area();
    draw_bands(&root, title, x_desc, y_desc, bands, log_y, shade).map_err(|m| match m {
        BandsError::Input(m) => PlotError::Input(m),
        BandsError::Draw(m) => fail(m),
    })?;
    root.present().map_err(|er| fail(er.to_string()))?;
    Ok(())
}

enum BandsError {
    Input(String),
    Draw(String),
}

/// [`bands`] on any drawing area `CHART.0 + LEGEND_W` wide: the plot on the left, the legend
/// in the strip on the right.
///
/// Long because it is one chart drawn in order (axes, bands, lines, legend strip), each layer over
/// the one before.
#[allow(clippy::too_many_arguments)]
fn draw_bands<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    bands: &[Band],
    log_y: bool,
    shade: bool,
) -> Result<(), BandsError> {
    let ok = |v: f64| v.is_finite() && (!log_y || v > 0.0);
    let pts = || {
        bands
            .iter()
            .flat_map(|s| s.points.iter())
            .flat_map(|p| [(p.0, p.1), (p.0, p.2), (p.0, p.3)])
            .filter(|p| p.0.is_finite() && ok(p.1))
    };
    let (x0, x1) = pts().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (y0, y1) = pts().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.1), b.max(p.1)));
    if !(x0.is_finite() && y0.is_finite()) {
        return Err(BandsError::Input(format!("{title}: no finite points")));
    }
    let (x1, y1) = (
        if x1 > x0 { x1 } else { x0 + 1.0 },
        if y1 > y0 { y1 } else { y0 + y0.abs().max(1e-12) },
    );
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| BandsError::Draw(e.to_string());
    root.fill(&WHITE).map_err(e)?;
    let (plot, legend) = root.split_horizontally(CHART.0);
    // The legend: one line and name per team, top down, beside the plot.
    for (i, s) in bands.iter().enumerate() {
        let y = 56 + 24 * i as i32;
        legend
            .draw(&PathElement::new(vec![(6, y), (32, y)], palette(i).stroke_width(3)))
            .map_err(e)?;
        legend
            .draw(&Text::new(
                s.name.clone(),
                (40, y - 8),
                (FONT, 14).into_font().color(&BLACK),
            ))
            .map_err(e)?;
    }
    macro_rules! draw_chart {
        ($chart:expr) => {{
            let mut chart = $chart;
            // Explicit tick text: the log axis's own labels print float noise (0.000000000001).
            let x_tick = |v: &f64| {
                if v.fract() == 0.0 {
                    format!("{v:.0}")
                } else {
                    format_tick(*v)
                }
            };
            let y_tick = |v: &f64| format_tick(*v);
            chart
                .configure_mesh()
                .x_desc(x_desc)
                .y_desc(y_desc)
                .x_label_formatter(&x_tick)
                .y_label_formatter(&y_tick)
                .label_style((FONT, 14))
                .draw()
                .map_err(e)?;
            for (i, s) in bands.iter().enumerate() {
                let c = palette(i);
                let p: Vec<&(f64, f64, f64, f64)> = s.points.iter().filter(|p| p.0.is_finite() && ok(p.1)).collect();
                if shade {
                    // The band: upper edge forward, lower edge back (clamped into the axis).
                    let floor = if log_y { y0 * 0.8 } else { f64::NEG_INFINITY };
                    let mut poly: Vec<(f64, f64)> = p.iter().map(|q| (q.0, q.3.min(y1 * 1.25).max(floor))).collect();
                    poly.extend(p.iter().rev().map(|q| (q.0, q.2.max(floor).min(y1 * 1.25))));
                    chart
                        .draw_series(std::iter::once(Polygon::new(poly, c.mix(0.18).filled())))
                        .map_err(e)?;
                }
                chart
                    .draw_series(LineSeries::new(p.iter().map(|q| (q.0, q.1)), c.stroke_width(2)))
                    .map_err(e)?;
            }
        }};
    }
    let builder = || {
        let mut b = ChartBuilder::on(&plot);
        b.caption(title, (FONT, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(80);
        b
    };
    if log_y {
        // Ticks at 1, 2, 5 x 10^k (plotters' own log ticks crowd and repeat a label near a
        // decade).
        let (bold, light) = log_ticks(y0 * 0.8, y1 * 1.25);
        draw_chart!(builder()
            .build_cartesian_2d(
                x0..x1,
                (y0 * 0.8..y1 * 1.25)
                    .log_scale()
                    .with_key_points(bold)
                    .with_light_points(light)
            )
            .map_err(e)?);
    } else {
        let pad = 0.05 * (y1 - y0);
        draw_chart!(builder()
            .build_cartesian_2d(x0..x1, (y0 - pad)..(y1 + pad))
            .map_err(e)?);
    }
    Ok(())
}

/// Box plots (quartile box, median line, whiskers to min and max, points on top) of named
/// groups of values, with a dashed reference line at `reference` when given.
///
/// Long because it is one chart drawn in order (axes, boxes, whiskers, reference line, labels),
/// each layer over the one before.
pub fn boxes(
    path: impl AsRef<Path>,
    title: &str,
    y_desc: &str,
    groups: &[(String, Vec<f64>)],
    reference: Option<f64>,
) -> Result<(), PlotError> {
    need_font()?;
    let path = path.as_ref();
    let fail = chart_fail(path);
    let all: Vec<f64> = groups
        .iter()
        .flat_map(|g| g.1.iter().copied())
        .filter(|v| v.is_finite())
        .chain(reference)
        .collect();
    if all.is_empty() {
        return Err(PlotError::Input(format!("{title}: no finite values")));
    }
    let (lo, hi) = all
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    let pad = 0.08 * (hi - lo).max(1e-9);
    let root = BitMapBackend::new(path, (960, 520)).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| fail(e.to_string());
    root.fill(&WHITE).map_err(e)?;
    let n = groups.len() as f64;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FONT, 20))
        .margin(12)
        .x_label_area_size(70)
        .y_label_area_size(80)
        .build_cartesian_2d(-0.5..n - 0.5, (lo - pad)..(hi + pad))
        .map_err(e)?;
    let names: Vec<String> = groups.iter().map(|g| g.0.clone()).collect();
    let fmt = |x: &f64| -> String {
        let i = x.round();
        if (x - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < names.len() {
            names[i as usize].clone()
        } else {
            String::new()
        }
    };
    chart
        .configure_mesh()
        .x_labels(groups.len().max(1) * 2 + 1)
        .x_label_formatter(&fmt)
        .y_desc(y_desc)
        .label_style((FONT, 13))
        .disable_x_mesh()
        .draw()
        .map_err(e)?;
    if let Some(r) = reference {
        chart
            .draw_series(DashedLineSeries::new(
                vec![(-0.5, r), (n - 0.5, r)],
                6,
                4,
                BLACK.stroke_width(1),
            ))
            .map_err(e)?;
    }
    for (i, (_, v)) in groups.iter().enumerate() {
        let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            continue;
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| {
            let t = p * (v.len() - 1) as f64;
            let (a, b) = (t.floor() as usize, t.ceil() as usize);
            v[a] + (v[b] - v[a]) * (t - a as f64)
        };
        let (x, c) = (i as f64, palette(i));
        let w = 0.25;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(x - w, q(0.25)), (x + w, q(0.75))],
                c.mix(0.35).filled(),
            )))
            .map_err(e)?;
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(x - w, q(0.25)), (x + w, q(0.75))],
                c.stroke_width(2),
            )))
            .map_err(e)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(x - w, q(0.5)), (x + w, q(0.5))],
                BLACK.stroke_width(2),
            )))
            .map_err(e)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(x, v[0]), (x, q(0.25))],
                c.stroke_width(1),
            )))
            .map_err(e)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(x, q(0.75)), (x, v[v.len() - 1])],
                c.stroke_width(1),
            )))
            .map_err(e)?;
        chart
            .draw_series(v.iter().map(|&y| Circle::new((x, y), 3, c.filled())))
            .map_err(e)?;
    }
    root.present().map_err(|er| fail(er.to_string()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_ticks_are_one_two_five_inside_the_range_and_never_repeat() {
        let (bold, light) = log_ticks(6e-5, 3.5e-3);
        assert_eq!(
            bold.iter().map(|v| format_tick(*v)).collect::<Vec<_>>(),
            ["1.00e-4", "2.00e-4", "5.00e-4", "1.00e-3", "2.00e-3"]
        );
        assert!(light.len() > bold.len() && light.iter().all(|v| (6e-5..=3.5e-3).contains(v)));
        // Inside one decade: every mantissa.
        let (bold, _) = log_ticks(2.5e-3, 4.5e-3);
        assert_eq!(
            bold.iter().map(|v| format_tick(*v)).collect::<Vec<_>>(),
            ["3.00e-3", "4.00e-3"]
        );
    }

    #[test]
    fn the_legend_is_beside_the_plot_with_every_team() {
        assert!(
            font_ready(),
            "charts need a font: install fonts-dejavu-core (scripts/test.sh does)"
        );
        // Lines all over the plot, as many as a report draws: every team's colour appears in
        // the legend strip, which no line reaches.
        let (w, h) = (CHART.0 + LEGEND_W, CHART.1);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        let bands: Vec<Band> = (0..8)
            .map(|i| Band {
                name: format!("team {i}"),
                points: (0..50)
                    .map(|k| (k as f64, 1.0 + ((k + 7 * i) % 13) as f64, 0.5, 15.0))
                    .collect(),
            })
            .collect();
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            assert!(draw_bands(&root, "t", "x", "y", &bands, false, true).is_ok());
            root.present().unwrap();
        }
        let at = |x: u32, y: u32| {
            let i = ((y * w + x) * 3) as usize;
            RGBColor(buf[i], buf[i + 1], buf[i + 2])
        };
        for i in 0..8 {
            let c = palette(i);
            assert!(
                (CHART.0..w).any(|x| (0..h).any(|y| at(x, y) == c)),
                "team {i}'s colour is not in the legend strip"
            );
        }
        // The strip's left edge is clear of the plot: nothing but white and the legend's own
        // marks there (the lines end inside the plot area).
        assert!(
            (0..h).all(|y| at(CHART.0, y) == WHITE),
            "the plot spills into the legend strip"
        );
    }

    /// A cell with no value is the live view's no-data grey in every panel (it was magenta in
    /// a truth and, at 0 on land, the colour bar's lowest in an estimate).
    #[test]
    fn a_cell_with_no_value_is_no_data_grey() {
        let values = [f64::NAN, 0.0, 1.0, 0.5];
        let panels = [Panel {
            values: &values,
            rows: 2,
            cols: 2,
            title: String::new(),
            disks: vec![],
        }];
        let (s, w, h) = layout(&panels);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            draw(&root, &panels, (0.0, 1.0), s).unwrap();
            root.present().unwrap();
        }
        // Cell 0 (row 0, the bottom; column 0), at its centre.
        let (x, y) = (PAD + s / 2, PAD + TITLE_H + 2 * s - s / 2);
        let i = ((y * w + x) * 3) as usize;
        assert_eq!(RGBColor(buf[i], buf[i + 1], buf[i + 2]), NO_DATA);
    }
}
