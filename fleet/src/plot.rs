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
            return Err(PlotError::Input(format!("panel {:?}: {} values for a {} x {} grid", self.title, self.values.len(), self.rows, self.cols)));
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

fn draw<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, panels: &[Panel<'_>], (lo, hi): (f64, f64), s: u32) -> Result<(), String> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    area.fill(&WHITE).map_err(err)?;
    let text = font_ready();
    let colour = |v: f64| if v.is_finite() { ViridisRGB::get_color_normalized(v.clamp(lo, hi), lo, hi) } else { RGBColor(255, 0, 255) };
    let mut y0 = PAD as i32;
    for p in panels {
        if text {
            area.draw_text(&p.title, &(FONT, 18).into_font().color(&BLACK), (PAD as i32, y0 + 3)).map_err(err)?;
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
            let centre = (PAD as i32 + ((c + 0.5) * s as f64) as i32, top + h - ((r + 0.5) * s as f64) as i32);
            area.draw(&Circle::new(centre, (rad * s as f64) as i32, ShapeStyle { color: WHITE.to_rgba(), filled: false, stroke_width: 2 }))
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
        area.draw(&Rectangle::new([(bx, y), (bx + 18, y + 1)], colour(v).filled())).map_err(err)?;
    }
    if text {
        for k in 0..=4 {
            let f = k as f64 / 4.0;
            let v = hi - (hi - lo) * f;
            let y = by0 + (f * span as f64) as i32;
            area.draw_text(&format_tick(v), &(FONT, 14).into_font().color(&BLACK), (bx + 22, (y - 7).max(0))).map_err(err)?;
        }
    }
    Ok(())
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
    let fail = |msg: String| PlotError::Draw { path: path.display().to_string(), msg };
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
    let fail = |msg: String| PlotError::Draw { path: path.display().to_string(), msg };
    let mut frames = frames.into_iter().peekable();
    let first = frames.peek().ok_or_else(|| PlotError::Input("no frames".into()))?;
    let (s, w, h) = layout(first);
    let root = BitMapBackend::gif(path, (w, h), delay_ms).map_err(|e| fail(e.to_string()))?.into_drawing_area();
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
