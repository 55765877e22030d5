//! Debug pictures: an RGB [`Canvas`] with the few drawing operations the
//! paper's GUI needs (scalar fields in false colour, grayscale images, boxes,
//! contours, dots, arrows), written as PNG.
//!
//! Drawing never panics: anything outside the canvas is clipped.
//!
//! ```
//! use optical_tactile::viz::{Canvas, Rgb};
//! let mut c = Canvas::new(40, 20, Rgb::BLACK);
//! c.rect(2, 2, 10, 8, Rgb::GREEN);
//! c.arrow(20.0, 10.0, 35.0, 10.0, Rgb::RED);
//! c.dot(-5.0, -5.0, 3.0, Rgb::WHITE); // off the canvas: clipped, no panic
//! assert_eq!(c.get(2, 5), Some(Rgb::GREEN));
//! ```

use std::path::Path;

use ndarray::ArrayRef2;

use crate::error::Result;

/// An 8-bit RGB colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rgb(pub u8, pub u8, pub u8);

impl Rgb {
    /// Black.
    pub const BLACK: Rgb = Rgb(0, 0, 0);
    /// White.
    pub const WHITE: Rgb = Rgb(255, 255, 255);
    /// Red.
    pub const RED: Rgb = Rgb(230, 40, 40);
    /// Green.
    pub const GREEN: Rgb = Rgb(40, 220, 60);
    /// Blue.
    pub const BLUE: Rgb = Rgb(50, 110, 255);
    /// Yellow.
    pub const YELLOW: Rgb = Rgb(250, 220, 30);
    /// Cyan.
    pub const CYAN: Rgb = Rgb(40, 220, 230);
    /// Magenta.
    pub const MAGENTA: Rgb = Rgb(230, 50, 230);
}

/// A perceptual colour map (viridis, dark blue -> green -> yellow) at `t` in 0..=1.
pub fn colormap(t: f64) -> Rgb {
    // Viridis sampled at 9 points, linearly interpolated.
    const STOPS: [[f64; 3]; 9] = [
        [68.0, 1.0, 84.0],
        [71.0, 44.0, 122.0],
        [59.0, 81.0, 139.0],
        [44.0, 113.0, 142.0],
        [33.0, 144.0, 141.0],
        [39.0, 173.0, 129.0],
        [92.0, 200.0, 99.0],
        [170.0, 220.0, 50.0],
        [253.0, 231.0, 37.0],
    ];
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) } * 8.0;
    let k = (t.floor() as usize).min(7);
    let f = t - k as f64;
    let c = |i: usize| (STOPS[k][i] * (1.0 - f) + STOPS[k + 1][i] * f).round() as u8;
    Rgb(c(0), c(1), c(2))
}

/// A diverging colour map (blue -> white -> red) at `t` in -1..=1.
pub fn diverging(t: f64) -> Rgb {
    let t = if t.is_nan() { 0.0 } else { t.clamp(-1.0, 1.0) };
    let a = (255.0 * (1.0 - t.abs())).round() as u8;
    if t >= 0.0 {
        Rgb(255, a, a)
    } else {
        Rgb(a, a, 255)
    }
}

/// An RGB image to draw on.
#[derive(Debug, Clone, PartialEq)]
pub struct Canvas {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl Canvas {
    /// A canvas filled with one colour.
    pub fn new(width: usize, height: usize, fill: Rgb) -> Self {
        let mut data = Vec::with_capacity(3 * width * height);
        for _ in 0..width * height {
            data.extend_from_slice(&[fill.0, fill.1, fill.2]);
        }
        Canvas {
            width,
            height,
            data,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The RGB bytes, row-major.
    pub fn as_bytes(&self) -> &[u8] {
        &self.data
    }

    /// The colour at `(x, y)`, if inside.
    pub fn get(&self, x: usize, y: usize) -> Option<Rgb> {
        (x < self.width && y < self.height).then(|| {
            let k = 3 * (y * self.width + x);
            Rgb(self.data[k], self.data[k + 1], self.data[k + 2])
        })
    }

    /// Sets one pixel; outside the canvas does nothing.
    pub fn set(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            let k = 3 * (y as usize * self.width + x as usize);
            self.data[k..k + 3].copy_from_slice(&[c.0, c.1, c.2]);
        }
    }

    /// Draws a grayscale image (8-bit scale) at `(x0, y0)`, each source pixel
    /// as a `scale x scale` block.
    pub fn gray(&mut self, img: &ArrayRef2<f32>, x0: i64, y0: i64, scale: usize) {
        self.field(img, x0, y0, scale, |v| {
            let g = if v.is_nan() {
                0
            } else {
                v.round().clamp(0.0, 255.0) as u8
            };
            Rgb(g, g, g)
        });
    }

    /// Draws a scalar field in false colour, mapped linearly from its own
    /// minimum (dark) to maximum (bright); a constant field is drawn dark.
    pub fn scalar(&mut self, f: &ArrayRef2<f64>, x0: i64, y0: i64, scale: usize) {
        let (lo, hi) = f
            .iter()
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let span = if hi > lo { hi - lo } else { 1.0 };
        self.field(f, x0, y0, scale, |v| colormap((v - lo) / span));
    }

    /// Draws a signed scalar field with the diverging map, symmetric about 0.
    pub fn signed(&mut self, f: &ArrayRef2<f64>, x0: i64, y0: i64, scale: usize) {
        let m = f
            .iter()
            .filter(|v| v.is_finite())
            .fold(0.0f64, |a, &v| a.max(v.abs()));
        let m = if m > 0.0 { m } else { 1.0 };
        self.field(f, x0, y0, scale, |v| diverging(v / m));
    }

    fn field<T: Copy>(
        &mut self,
        f: &ArrayRef2<T>,
        x0: i64,
        y0: i64,
        scale: usize,
        color: impl Fn(T) -> Rgb,
    ) {
        let s = scale.max(1) as i64;
        for ((y, x), &v) in f.indexed_iter() {
            let c = color(v);
            for dy in 0..s {
                for dx in 0..s {
                    self.set(x0 + x as i64 * s + dx, y0 + y as i64 * s + dy, c);
                }
            }
        }
    }

    /// Copies another canvas in at `(x0, y0)` (clipped).
    pub fn blit(&mut self, other: &Canvas, x0: i64, y0: i64) {
        for y in 0..other.height {
            for x in 0..other.width {
                let c = other.get(x, y).expect("inside");
                self.set(x0 + x as i64, y0 + y as i64, c);
            }
        }
    }

    /// A straight line from `(x0, y0)` to `(x1, y1)` (Bresenham on rounded ends).
    pub fn line(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, c: Rgb) {
        if ![x0, y0, x1, y1]
            .iter()
            .all(|v| v.is_finite() && v.abs() < 1e7)
        {
            return;
        }
        let (mut x, mut y) = (x0.round() as i64, y0.round() as i64);
        let (xe, ye) = (x1.round() as i64, y1.round() as i64);
        let (dx, dy) = ((xe - x).abs(), -(ye - y).abs());
        let (sx, sy) = (if x < xe { 1 } else { -1 }, if y < ye { 1 } else { -1 });
        let mut err = dx + dy;
        loop {
            self.set(x, y, c);
            if x == xe && y == ye {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// The outline of the rectangle with top-left `(x, y)`, width `w`, height `h`.
    pub fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, c: Rgb) {
        if w <= 0 || h <= 0 {
            return;
        }
        let (x1, y1) = ((x + w - 1) as f64, (y + h - 1) as f64);
        let (x0, y0) = (x as f64, y as f64);
        self.line(x0, y0, x1, y0, c);
        self.line(x0, y1, x1, y1, c);
        self.line(x0, y0, x0, y1, c);
        self.line(x1, y0, x1, y1, c);
    }

    /// A filled disc of radius `r` centred at `(x, y)`.
    pub fn dot(&mut self, x: f64, y: f64, r: f64, c: Rgb) {
        // Far-off centres would overflow the pixel arithmetic: clip them early.
        if !(x.abs() < 1e7 && y.abs() < 1e7 && (0.0..=1e4).contains(&r)) {
            return;
        }
        let ri = r.ceil() as i64;
        let (cx, cy) = (x.round() as i64, y.round() as i64);
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                if ((dx * dx + dy * dy) as f64) <= r * r + 0.25 {
                    self.set(cx + dx, cy + dy, c);
                }
            }
        }
    }

    /// An arrow from `(x0, y0)` to `(x1, y1)` with a head at the end.
    pub fn arrow(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, c: Rgb) {
        self.line(x0, y0, x1, y1, c);
        let (dx, dy) = (x1 - x0, y1 - y0);
        let len = dx.hypot(dy);
        if !(len.is_finite() && len > 1.0) {
            return;
        }
        let head = (len * 0.3).clamp(3.0, 12.0);
        let (ux, uy) = (dx / len, dy / len);
        for side in [-1.0, 1.0] {
            // Two strokes at +-30 degrees back from the tip.
            let (cs, sn) = (0.866, 0.5 * side);
            let bx = -(ux * cs - uy * sn) * head;
            let by = -(uy * cs + ux * sn) * head;
            self.line(x1, y1, x1 + bx, y1 + by, c);
        }
    }

    /// A closed polyline through `points` (e.g. a contour), each scaled by `scale`.
    pub fn polygon(&mut self, points: &[(f64, f64)], scale: f64, c: Rgb) {
        for k in 0..points.len() {
            let (a, b) = (points[k], points[(k + 1) % points.len()]);
            self.line(a.0 * scale, a.1 * scale, b.0 * scale, b.1 * scale, c);
        }
    }

    /// Writes the canvas as an RGB PNG.
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<()> {
        crate::io::write_rgb_png(path, &self.data, self.width, self.height)
    }
}

/// Pixels of arrow per newton of shear force in [`debug_panel`].
pub const ARROW_PX_PER_N: f64 = 60.0;

/// Gap between the four views of [`debug_panel`], pixels.
const PANEL_GAP: usize = 4;

/// The debug panel of the paper's GUI for the last frame `sensor` processed:
/// four views of the cropped strip (each `w x h`, full resolution), stacked
/// top to bottom with a 4-px gap:
///
/// 1. the optical flow in colour (hue = direction, saturation = magnitude
///    relative to the frame's largest, at least 0.5 px) with the outlines of
///    the segmentation mask in black;
/// 2. the divergent (curl-free) field `d` of each patch as `|d|` (viridis,
///    normalised per patch), with the patch box (green), the contact point
///    (red dot; its radius grows by 4 px per newton of `|Fz|`), and the shear
///    force `(Fx, Fy)` as an arrow ([`ARROW_PX_PER_N`] px per newton,
///    yellow); only tracked, live contacts are marked;
/// 3. the divergence potential `D` of each patch (viridis, per patch);
/// 4. the cropped grayscale image.
///
/// Before any frame has been processed the fields are empty (black).
pub fn debug_panel(sensor: &crate::sensor::TactileSensor) -> Canvas {
    let live = sensor
        .contacts()
        .iter()
        .filter(|c| c.missed == 0)
        .map(|c| (c.raw, Some(c.force_n)));
    panel(sensor.cropped(), sensor.extractor(), live)
}

/// [`debug_panel`] without a calibration (raw mode): the same four views of
/// the last frame `extractor` processed (`cropped` is that frame, as given
/// to [`ContactExtractor::extract`](crate::sensor::ContactExtractor::extract)),
/// each patch marked with its box and contact point and no force arrow.
pub fn raw_debug_panel(
    extractor: &crate::sensor::ContactExtractor,
    cropped: &ndarray::ArrayRef2<f32>,
) -> Canvas {
    panel(
        cropped,
        extractor,
        extractor.raws().iter().map(|r| (*r, None)),
    )
}

/// The four views; `marks` are the patches to mark, with their force when calibrated.
fn panel(
    img: &ndarray::ArrayRef2<f32>,
    ex: &crate::sensor::ContactExtractor,
    marks: impl Iterator<Item = (crate::contact::RawContact, Option<[f64; 3]>)>,
) -> Canvas {
    let (w, h) = (img.ncols(), img.nrows());
    let row = (h + PANEL_GAP) as i64;
    let mut c = Canvas::new(w, 4 * h + 3 * PANEL_GAP, Rgb::BLACK);
    let (flow, scale) = ex.flow();
    let s = scale.max(1);
    let sf = s as f64;
    // Grey gaps between the views.
    for k in 1..4 {
        let y0 = k * (h + PANEL_GAP) - PANEL_GAP;
        for y in y0..y0 + PANEL_GAP {
            for x in 0..w {
                c.set(x as i64, y as i64, Rgb(40, 40, 40));
            }
        }
    }

    // 1. Flow in colour, with the mask's contours.
    if flow.size() != (0, 0) {
        let maxm = flow
            .u
            .iter()
            .zip(flow.v.iter())
            .map(|(u, v)| u.hypot(*v))
            .filter(|m| m.is_finite())
            .fold(0.5f32, f32::max);
        let rgb = crate::flow::color::flow_to_rgb(flow, Some(maxm));
        let fw = flow.width();
        for ((y, x), _) in flow.u.indexed_iter() {
            let k = 3 * (y * fw + x);
            let col = Rgb(rgb[k], rgb[k + 1], rgb[k + 2]);
            for dy in 0..s {
                for dx in 0..s {
                    c.set((x * s + dx) as i64, (y * s + dy) as i64, col);
                }
            }
        }
        let mask = ex.segmenter().mask();
        if mask.width() == flow.width() && mask.height() == flow.height() {
            for contour in crate::segment::contours::external_contours(mask) {
                let pts: Vec<(f64, f64)> = contour
                    .points
                    .iter()
                    .map(|&(x, y)| (x as f64 + 0.5, y as f64 + 0.5))
                    .collect();
                c.polygon(&pts, sf, Rgb::BLACK);
            }
        }
    }

    // 2. and 3. Per patch: |d| and D.
    for (k, patch) in ex.patches().iter().enumerate() {
        let Some(dec) = ex.divergent_part(k) else {
            continue;
        };
        let b = patch.bbox;
        if dec.potential_d.dim() != (b.height, b.width) {
            continue;
        }
        let mag = ndarray::Zip::from(&dec.d.u)
            .and(&dec.d.v)
            .map_collect(|u, v| u.hypot(*v));
        let (x0, y0) = ((b.x * s) as i64, (b.y * s) as i64);
        c.scalar(&mag, x0, row + y0, s);
        c.scalar(&dec.potential_d, x0, 2 * row + y0, s);
    }
    for (r, force) in marks {
        let bx = r.bbox;
        for dy in [row, 2 * row] {
            c.rect(
                bx.x as i64,
                dy + bx.y as i64,
                bx.w as i64,
                bx.h as i64,
                Rgb::GREEN,
            );
        }
        let (x, y) = (r.x_px, r.y_px + row as f64);
        if let Some([fx, fy, fz]) = force {
            // The arrow first: the dot on top keeps the contact point visible.
            c.arrow(
                x,
                y,
                x + ARROW_PX_PER_N * fx,
                y + ARROW_PX_PER_N * fy,
                Rgb::YELLOW,
            );
            c.dot(x, y, 3.0 + 4.0 * fz.abs().min(10.0), Rgb::RED);
        } else {
            c.dot(x, y, 3.0, Rgb::RED);
        }
        c.dot(r.x_px, r.y_px + 2.0 * row as f64, 2.0, Rgb::RED);
    }

    // 4. The cropped grayscale image.
    c.gray(img, 0, 3 * row, 1);
    c
}

/// A 3x5 bitmap glyph: five rows of three bits (bit 2 = left column).
fn glyph(ch: char) -> [u8; 5] {
    match ch.to_ascii_uppercase() {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '-' => [0, 0, 7, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        '.' => [0, 0, 0, 0, 2],
        ',' => [0, 0, 0, 2, 4],
        ':' => [0, 2, 0, 2, 0],
        '=' => [0, 7, 0, 7, 0],
        '/' => [1, 1, 2, 4, 4],
        '(' => [2, 4, 4, 4, 2],
        ')' => [2, 1, 1, 1, 2],
        '_' => [0, 0, 0, 0, 7],
        '|' => [2, 2, 2, 2, 2],
        'A' => [2, 5, 7, 5, 5],
        'B' => [6, 5, 6, 5, 6],
        'C' => [3, 4, 4, 4, 3],
        'D' => [6, 5, 5, 5, 6],
        'E' => [7, 4, 6, 4, 7],
        'F' => [7, 4, 6, 4, 4],
        'G' => [3, 4, 5, 5, 3],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'J' => [1, 1, 1, 5, 2],
        'K' => [5, 5, 6, 5, 5],
        'L' => [4, 4, 4, 4, 7],
        'M' => [5, 7, 7, 5, 5],
        'N' => [6, 5, 5, 5, 5],
        'O' => [2, 5, 5, 5, 2],
        'P' => [6, 5, 6, 4, 4],
        'Q' => [2, 5, 5, 6, 3],
        'R' => [6, 5, 6, 5, 5],
        'S' => [3, 4, 2, 1, 6],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'W' => [5, 5, 7, 7, 5],
        'X' => [5, 5, 2, 5, 5],
        'Y' => [5, 5, 2, 2, 2],
        'Z' => [7, 1, 2, 4, 7],
        _ => [0; 5], // space and anything unknown
    }
}

impl Canvas {
    /// Writes `text` with a 3x5 pixel font (upper case, digits, `- + . , : =
    /// / ( ) _ |`; other characters are blank), each font pixel a
    /// `scale x scale` block, top-left at `(x, y)`. Returns the width drawn.
    pub fn text(&mut self, x: i64, y: i64, text: &str, scale: usize, c: Rgb) -> i64 {
        let s = scale.max(1) as i64;
        let mut cx = x;
        for ch in text.chars() {
            for (row, bits) in glyph(ch).iter().enumerate() {
                for col in 0..3 {
                    if bits & (4 >> col) != 0 {
                        for dy in 0..s {
                            for dx in 0..s {
                                self.set(cx + col * s + dx, y + row as i64 * s + dy, c);
                            }
                        }
                    }
                }
            }
            cx += 4 * s;
        }
        cx - x
    }
}

/// How a [`Series`] is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Style {
    /// Straight segments between consecutive points.
    Line,
    /// A dashed line (for truth next to measurements).
    Dashed,
    /// A filled dot of this radius (pixels) at every point.
    Dots(f64),
    /// A cross of this half-size (pixels) at every point.
    Cross(f64),
    /// A circle outline of this radius in **data units** of x (e.g. a
    /// cluster's spread), at least 3 px.
    Circle(f64),
}

/// One data series of a [`Plot`].
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text.
    pub label: String,
    /// `(x, y)` in data units; non-finite points are skipped.
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub color: Rgb,
    /// How it is drawn.
    pub style: Style,
}

/// A 2D plot with axes, tick labels and a legend: line plots over time and
/// maps alike. Ranges default to the data's (padded by 5%); `equal_aspect`
/// gives x and y the same scale (for maps).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plot {
    /// Title, above the plot.
    pub title: String,
    /// x axis label.
    pub x_label: String,
    /// y axis label.
    pub y_label: String,
    /// Fixed x range, or `None` for the data's.
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range, or `None` for the data's.
    pub y_range: Option<(f64, f64)>,
    /// Same scale on both axes.
    pub equal_aspect: bool,
    /// The data.
    pub series: Vec<Series>,
}

/// Tick values at a "nice" step (1, 2 or 5 x 10^k), the smallest such step
/// that gives at most 8 ticks over `lo..=hi`.
pub fn nice_ticks(lo: f64, hi: f64) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo {
        return Vec::new();
    }
    let span = hi - lo;
    let mag = 10f64.powf((span / 8.0).log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| span / s <= 8.0)
        .unwrap_or(10.0 * mag);
    let k0 = (lo / step).ceil() as i64;
    let k1 = (hi / step + 1e-9).floor() as i64;
    // k * step, not a running sum, so that errors do not pile up.
    (k0..=k1).map(|k| k as f64 * step).collect()
}

fn tick_label(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    format!("{v:.decimals$}")
}

/// `r` if it is a finite, non-empty range; a unit range around a lone
/// finite value; otherwise `0..1`.
fn usable_range(r: (f64, f64)) -> (f64, f64) {
    match (r.0.is_finite(), r.1.is_finite()) {
        (true, true) if r.1 > r.0 => r,
        (true, true) => (r.0 - 0.5, r.0 + 0.5),
        _ => (0.0, 1.0),
    }
}

fn data_range(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = vals
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        0.5_f64.max(0.05 * lo.abs())
    };
    (lo - pad, hi + pad)
}

impl Plot {
    /// Draws the plot on a white `width x height` canvas (at least 120 x 80).
    pub fn render(&self, width: usize, height: usize) -> Canvas {
        let (width, height) = (width.max(120), height.max(80));
        let mut c = Canvas::new(width, height, Rgb::WHITE);
        let ink = Rgb(40, 40, 40);
        let grid = Rgb(225, 225, 225);
        // Plot area, leaving room for the title, tick labels and axis labels.
        // The legend goes right of the plot area, never over the data.
        let legend_w = self
            .series
            .iter()
            .filter(|s| !s.label.is_empty())
            .map(|s| 8.0 * s.label.len() as f64 + 34.0)
            .fold(0.0f64, f64::max)
            .min(0.5 * width as f64);
        let (left, right, top, bottom) = (
            64.0,
            width as f64 - 12.0 - legend_w,
            24.0,
            height as f64 - 34.0,
        );
        let mut xr = self.x_range.unwrap_or_else(|| {
            data_range(
                self.series
                    .iter()
                    .flat_map(|s| s.points.iter().map(|p| p.0)),
            )
        });
        let mut yr = self.y_range.unwrap_or_else(|| {
            data_range(
                self.series
                    .iter()
                    .flat_map(|s| s.points.iter().map(|p| p.1)),
            )
        });
        xr = usable_range(xr);
        yr = usable_range(yr);
        let (pw, ph) = (right - left, bottom - top);
        if self.equal_aspect {
            // Widen the range that is too small for the common scale.
            let s = ((xr.1 - xr.0) / pw).max((yr.1 - yr.0) / ph);
            let (cx, cy) = (0.5 * (xr.0 + xr.1), 0.5 * (yr.0 + yr.1));
            xr = (cx - 0.5 * s * pw, cx + 0.5 * s * pw);
            yr = (cy - 0.5 * s * ph, cy + 0.5 * s * ph);
        }
        let px = |x: f64| left + (x - xr.0) / (xr.1 - xr.0) * pw;
        let py = |y: f64| bottom - (y - yr.0) / (yr.1 - yr.0) * ph;
        let xt = nice_ticks(xr.0, xr.1);
        let yt = nice_ticks(yr.0, yr.1);
        let xstep = if xt.len() > 1 { xt[1] - xt[0] } else { 1.0 };
        let ystep = if yt.len() > 1 { yt[1] - yt[0] } else { 1.0 };
        for &t in &xt {
            c.line(px(t), top, px(t), bottom, grid);
            let l = tick_label(t, xstep);
            let w = 8.0 * l.len() as f64;
            c.text((px(t) - 0.5 * w) as i64, bottom as i64 + 5, &l, 2, ink);
        }
        for &t in &yt {
            c.line(left, py(t), right, py(t), grid);
            let l = tick_label(t, ystep);
            let w = 8 * l.len() as i64;
            c.text(left as i64 - 4 - w, py(t) as i64 - 5, &l, 2, ink);
        }
        c.rect(
            left as i64,
            top as i64,
            (pw + 1.0) as i64,
            (ph + 1.0) as i64,
            ink,
        );
        c.text(left as i64 + 8, 6, &self.title, 2, ink);
        let xl = 8 * self.x_label.len() as i64;
        c.text(
            (right as i64 - xl).max(0),
            height as i64 - 12,
            &self.x_label,
            2,
            ink,
        );
        c.text(4, 6, &self.y_label, 2, ink);
        // Clip the data to the plot area by drawing on a sub-canvas.
        let mut area = Canvas::new(pw as usize + 1, ph as usize + 1, Rgb::WHITE);
        for &t in &xt {
            area.line(px(t) - left, 0.0, px(t) - left, ph, grid);
        }
        for &t in &yt {
            area.line(0.0, py(t) - top, pw, py(t) - top, grid);
        }
        for s in &self.series {
            let pts: Vec<(f64, f64)> = s
                .points
                .iter()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .map(|&(x, y)| (px(x) - left, py(y) - top))
                .collect();
            match s.style {
                Style::Line | Style::Dashed => {
                    for (k, w) in pts.windows(2).enumerate() {
                        if s.style == Style::Line {
                            area.line(w[0].0, w[0].1, w[1].0, w[1].1, s.color);
                            area.line(w[0].0, w[0].1 + 1.0, w[1].0, w[1].1 + 1.0, s.color);
                        } else {
                            dashed(&mut area, w[0], w[1], s.color, k);
                        }
                    }
                }
                Style::Dots(r) => pts.iter().for_each(|p| area.dot(p.0, p.1, r, s.color)),
                Style::Cross(h) => {
                    for p in &pts {
                        area.line(p.0 - h, p.1 - h, p.0 + h, p.1 + h, s.color);
                        area.line(p.0 - h, p.1 + h, p.0 + h, p.1 - h, s.color);
                    }
                }
                Style::Circle(r) => {
                    let rpx = (r / (xr.1 - xr.0) * pw).max(3.0);
                    for p in &pts {
                        circle(&mut area, p.0, p.1, rpx, s.color);
                    }
                }
            }
        }
        c.blit(&area, left as i64, top as i64);
        c.rect(
            left as i64,
            top as i64,
            (pw + 1.0) as i64,
            (ph + 1.0) as i64,
            ink,
        );
        // Legend, right of the plot.
        let mut ly = top as i64 + 2;
        for s in self.series.iter().filter(|s| !s.label.is_empty()) {
            let lx = right as i64 + 34;
            let (sx, sy) = ((lx - 14) as f64, (ly + 4) as f64);
            match s.style {
                Style::Line => c.line(sx - 7.0, sy, sx + 7.0, sy, s.color),
                Style::Dashed => dashed(&mut c, (sx - 7.0, sy), (sx + 7.0, sy), s.color, 0),
                Style::Dots(_) => c.dot(sx, sy, 3.0, s.color),
                Style::Cross(_) => {
                    c.line(sx - 4.0, sy - 4.0, sx + 4.0, sy + 4.0, s.color);
                    c.line(sx - 4.0, sy + 4.0, sx + 4.0, sy - 4.0, s.color);
                }
                Style::Circle(_) => circle(&mut c, sx, sy, 4.0, s.color),
            }
            c.text(lx, ly, &s.label, 2, s.color);
            ly += 16;
        }
        c
    }
}

/// A dashed segment (6 px on, 4 off; `phase` shifts the pattern so that
/// consecutive segments do not all start "on").
fn dashed(c: &mut Canvas, a: (f64, f64), b: (f64, f64), color: Rgb, phase: usize) {
    let len = (b.0 - a.0).hypot(b.1 - a.1);
    if !(len.is_finite() && len < 1e6) {
        return;
    }
    let n = len.ceil() as usize;
    for i in 0..=n {
        if (i + 3 * phase) % 10 < 6 {
            let t = if n == 0 { 0.0 } else { i as f64 / n as f64 };
            let (x, y) = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
            c.set(x.round() as i64, y.round() as i64, color);
            c.set(x.round() as i64, y.round() as i64 + 1, color);
        }
    }
}

/// A circle outline of radius `r` pixels.
fn circle(c: &mut Canvas, x: f64, y: f64, r: f64, color: Rgb) {
    if !(x.is_finite() && y.is_finite() && r.is_finite() && r < 1e4) {
        return;
    }
    let n = ((2.0 * std::f64::consts::PI * r).ceil() as usize).max(8);
    for k in 0..n {
        let a = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
        c.set(
            (x + r * a.cos()).round() as i64,
            (y + r * a.sin()).round() as i64,
            color,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_draws_digits_and_skips_unknown() {
        let mut c = Canvas::new(20, 8, Rgb::BLACK);
        let w = c.text(0, 0, "1~", 1, Rgb::WHITE);
        assert_eq!(w, 8);
        // '1': column 1 set in every row, row 4 full.
        assert!((0..5).all(|y| c.get(1, y) == Some(Rgb::WHITE)));
        assert_eq!(c.get(0, 0), Some(Rgb::BLACK));
        assert_eq!(c.get(0, 4), Some(Rgb::WHITE));
        assert!((4..8).all(|x| (0..5).all(|y| c.get(x, y) == Some(Rgb::BLACK))));
    }

    #[test]
    fn nice_ticks_cover_the_range() {
        let t = nice_ticks(0.0, 1.0);
        assert_eq!(t.len(), 6);
        assert!(
            t.iter()
                .zip([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
                .all(|(a, b)| (a - b).abs() < 1e-12)
        );
        let t = nice_ticks(-95.0, 42.0);
        assert_eq!(t, vec![-80.0, -60.0, -40.0, -20.0, 0.0, 20.0, 40.0]);
        assert!(nice_ticks(1.0, 1.0).is_empty() && nice_ticks(f64::NAN, 1.0).is_empty());
    }

    #[test]
    fn plot_puts_points_where_the_axes_say() {
        let plot = Plot {
            x_range: Some((0.0, 10.0)),
            y_range: Some((0.0, 10.0)),
            series: vec![Series {
                label: String::new(),
                points: vec![(5.0, 5.0), (f64::NAN, 1.0), (1e300, 2.0)],
                color: Rgb::RED,
                style: Style::Dots(2.0),
            }],
            ..Plot::default()
        };
        let c = plot.render(300, 200);
        // Plot area: x 64..288, y 24..166; (5, 5) is at its centre.
        let (cx, cy) = ((64.0 + 288.0) / 2.0, (24.0 + 166.0) / 2.0);
        assert_eq!(c.get(cx as usize, cy as usize), Some(Rgb::RED));
        let reds = c
            .as_bytes()
            .chunks(3)
            .filter(|p| p == &[230, 40, 40])
            .count();
        assert!(reds <= 13, "only the one finite, in-range dot: {reds}");
        // Empty plots and tiny sizes do not panic.
        let _ = Plot::default().render(0, 0);
    }

    #[test]
    fn lines_hit_both_ends_and_are_clipped() {
        let mut c = Canvas::new(10, 10, Rgb::BLACK);
        c.line(1.0, 1.0, 8.0, 5.0, Rgb::WHITE);
        assert_eq!(c.get(1, 1), Some(Rgb::WHITE));
        assert_eq!(c.get(8, 5), Some(Rgb::WHITE));
        // A line far outside, or with NaN, changes nothing and does not panic.
        let before = c.clone();
        c.line(-100.0, -100.0, -50.0, -3.0, Rgb::RED);
        c.line(f64::NAN, 0.0, 3.0, 3.0, Rgb::RED);
        c.dot(f64::INFINITY, 0.0, 2.0, Rgb::RED);
        assert_eq!(c, before);
    }

    #[test]
    fn rect_outline_only() {
        let mut c = Canvas::new(10, 10, Rgb::BLACK);
        c.rect(2, 3, 5, 4, Rgb::GREEN);
        assert_eq!(c.get(2, 3), Some(Rgb::GREEN));
        assert_eq!(c.get(6, 6), Some(Rgb::GREEN));
        assert_eq!(c.get(4, 5), Some(Rgb::BLACK));
        assert_eq!(c.get(7, 6), Some(Rgb::BLACK));
    }

    #[test]
    fn dot_is_round() {
        let mut c = Canvas::new(11, 11, Rgb::BLACK);
        c.dot(5.0, 5.0, 3.0, Rgb::RED);
        assert_eq!(c.get(8, 5), Some(Rgb::RED));
        assert_eq!(c.get(8, 8), Some(Rgb::BLACK));
    }

    #[test]
    fn colormaps_span_their_ends() {
        assert_eq!(colormap(0.0), Rgb(68, 1, 84));
        assert_eq!(colormap(1.0), Rgb(253, 231, 37));
        assert_eq!(colormap(f64::NAN), colormap(0.0));
        assert_eq!(diverging(0.0), Rgb::WHITE);
        assert_eq!(diverging(1.0), Rgb(255, 0, 0));
        assert_eq!(diverging(-1.0), Rgb(0, 0, 255));
    }

    #[test]
    fn fields_scale_up() {
        let f = ndarray::arr2(&[[0.0f64, 1.0]]);
        let mut c = Canvas::new(4, 2, Rgb::BLACK);
        c.scalar(&f, 0, 0, 2);
        assert_eq!(c.get(1, 1), Some(colormap(0.0)));
        assert_eq!(c.get(3, 0), Some(colormap(1.0)));
    }
}
