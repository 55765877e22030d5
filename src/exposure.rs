//! Compensation of the camera's gain and black level against the reference
//! (docs/pipeline.md, step 3).
//!
//! An auto-exposure step, a gain change or a slow drift of the camera
//! changes every pixel of a frame as `cur ≈ a ref + b` although nothing on the
//! skin moved. DIS's patches are mean-normalized, so a pure offset `b` barely
//! moves them, but a gain `a ≠ 1` scales each patch's contrast, and the
//! Gauss-Newton step of a patch whose texture is not symmetric then turns
//! that residual into motion: a fraction of a pixel over the whole skin, as
//! much as a light press. [`ExposureCompensator`] estimates `a` and `b` per
//! frame and maps the frame back onto the reference's exposure before the
//! flow: `cur' = (cur - b) / a`.
//!
//! The estimate is robust to contacts: the frame is cut into square tiles;
//! per tile, the reference's mean and standard deviation are computed once
//! ([`ExposureCompensator::set_reference`]). A press moves markers by a few
//! pixels, so a tile's mean and spread hardly change under it, and even the
//! tiles it does change are a minority, which the medians below ignore:
//!
//! - gain `a`: the median over textured tiles (reference standard deviation
//!   of at least [`MIN_TEXTURE`] grey levels) of `sd_cur / sd_ref`;
//! - offset `b`: the median over every tile of `mean_cur - a mean_ref`.
//!
//! [`ExposureCompensation::Offset`] estimates only `b` (with `a = 1`).
//!
//! The default, [`ExposureCompensation::Auto`], takes `a` and `b` out only
//! of a frame whose gain departs from the reference's by more than
//! [`AUTO_GAIN_BAND`] (1%): exposure steps and drift, not most of a lit
//! camera's flicker. On the strip's characterization protocol (1% flicker,
//! no exposure change) a calibration fitted and scored with it keeps the
//! accuracy of one without compensation (x 0.18 mm, Fx 0.0123, Fz 0.0445 N
//! against 0.18 mm, 0.0123, 0.0442 N), whereas compensating every frame
//! (`GainOffset`) reached 0.26 mm and Fx 0.0147 N (Fz 0.0422 N). A
//! calibration records the setting it was fitted with
//! (`PipelineSettings::exposure`), and a sensor built from it runs with that
//! one.

use ndarray::{Array2, ArrayRef2, Zip};

use crate::error::{Error, Result};

/// Side of the square tiles over which the frame's statistics are taken,
/// pixels.
pub const TILE_PX: usize = 32;

/// Reference standard deviation (grey levels) from which a tile counts as
/// textured and takes part in the gain estimate.
pub const MIN_TEXTURE: f32 = 4.0;

/// [`ExposureCompensation::Auto`] leaves a frame as it comes while its
/// estimated gain stays within this fraction of the reference's: the size
/// of a lit camera's frame-to-frame flicker (the simulator's: 1% per frame).
/// A band of 2% let a drift within it through as false contacts (3 of 80
/// rest frames at 1.5 grey levels of read noise); no band (`GainOffset`)
/// cost the strip's calibration accuracy (see the module docs).
pub const AUTO_GAIN_BAND: f64 = 0.01;

/// Which changes of the camera the extractor takes out of each frame before
/// the flow.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum ExposureCompensation {
    /// None: frames go to the flow as they come (the default).
    Off,
    /// The black level only: `cur' = cur - b`.
    Offset,
    /// Gain and black level: `cur' = (cur - b) / a`.
    GainOffset,
    /// Gain and black level as [`GainOffset`](Self::GainOffset), but only
    /// for a frame whose gain departs from the reference's by more than
    /// [`AUTO_GAIN_BAND`] (an exposure step, a drift): a frame within the
    /// band (flicker) goes to the flow as it comes.
    #[default]
    Auto,
}

impl ExposureCompensation {
    /// Parses `off`, `offset` or `gain-offset` (case-insensitive).
    pub fn parse(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "off" => Ok(ExposureCompensation::Off),
            "offset" => Ok(ExposureCompensation::Offset),
            "gain-offset" => Ok(ExposureCompensation::GainOffset),
            "auto" => Ok(ExposureCompensation::Auto),
            _ => Err(Error::param(
                "exposure",
                format!("unknown exposure compensation `{name}` (off, offset, gain-offset, auto)"),
            )),
        }
    }

    /// Lower-case name, as accepted by [`ExposureCompensation::parse`].
    pub fn name(self) -> &'static str {
        match self {
            ExposureCompensation::Off => "off",
            ExposureCompensation::Offset => "offset",
            ExposureCompensation::GainOffset => "gain-offset",
            ExposureCompensation::Auto => "auto",
        }
    }
}

/// Mean and standard deviation of one tile.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct TileStats {
    mean: f64,
    sd: f64,
}

/// Estimates each frame's gain and offset against the reference and takes
/// them out (see the module docs). Built once; nothing is allocated per
/// frame once the first frame has been seen.
#[derive(Debug, Clone)]
pub struct ExposureCompensator {
    mode: ExposureCompensation,
    reference: Vec<TileStats>,
    size: (usize, usize),
    current: Vec<TileStats>,
    ratios: Vec<f64>,
    offsets: Vec<f64>,
    last: (f64, f64),
}

impl ExposureCompensator {
    /// A compensator of `mode`, with no reference yet.
    pub fn new(mode: ExposureCompensation) -> Self {
        ExposureCompensator {
            mode,
            reference: Vec::new(),
            size: (0, 0),
            current: Vec::new(),
            ratios: Vec::new(),
            offsets: Vec::new(),
            last: (1.0, 0.0),
        }
    }

    /// The mode.
    pub fn mode(&self) -> ExposureCompensation {
        self.mode
    }

    /// Takes the reference's tile statistics.
    pub fn set_reference(&mut self, reference: &ArrayRef2<f32>) {
        self.size = (reference.ncols(), reference.nrows());
        tile_stats(reference, &mut self.reference);
        self.last = (1.0, 0.0);
    }

    /// The `(gain, offset)` estimated for the last frame (`cur ≈ gain ref +
    /// offset`); `(1, 0)` before any frame or when off.
    pub fn last(&self) -> (f64, f64) {
        self.last
    }

    /// The `(gain, offset)` of `frame` against the reference. Errors if the
    /// frame's size differs from the reference's.
    pub fn estimate(&mut self, frame: &ArrayRef2<f32>) -> Result<(f64, f64)> {
        if self.mode == ExposureCompensation::Off || self.reference.is_empty() {
            return Ok((1.0, 0.0));
        }
        if (frame.ncols(), frame.nrows()) != self.size {
            return Err(Error::shape(
                "frame against the reference",
                self.size,
                (frame.ncols(), frame.nrows()),
            ));
        }
        tile_stats(frame, &mut self.current);
        let mut gain = 1.0;
        let gains = matches!(
            self.mode,
            ExposureCompensation::GainOffset | ExposureCompensation::Auto
        );
        if gains {
            self.ratios.clear();
            for (r, c) in self.reference.iter().zip(&self.current) {
                if r.sd >= f64::from(MIN_TEXTURE) {
                    self.ratios.push(c.sd / r.sd);
                }
            }
            if let Some(m) = median(&mut self.ratios) {
                if m.is_finite() && m > 0.0 {
                    gain = m;
                }
            }
        }
        self.offsets.clear();
        for (r, c) in self.reference.iter().zip(&self.current) {
            self.offsets.push(c.mean - gain * r.mean);
        }
        let offset = median(&mut self.offsets)
            .filter(|b| b.is_finite())
            .unwrap_or(0.0);
        if self.mode == ExposureCompensation::Auto && (gain - 1.0).abs() <= AUTO_GAIN_BAND {
            return Ok((1.0, 0.0));
        }
        Ok((gain, offset))
    }

    /// `frame` brought onto the reference's exposure, into `out` (resized
    /// if needed): `(frame - offset) / gain` with the estimate of
    /// [`estimate`](Self::estimate), or a plain copy when off or before a
    /// reference. Errors if the frame's size differs from the reference's.
    pub fn compensate_into(&mut self, frame: &ArrayRef2<f32>, out: &mut Array2<f32>) -> Result<()> {
        let (gain, offset) = self.estimate(frame)?;
        self.last = (gain, offset);
        if out.dim() != frame.dim() {
            *out = Array2::zeros(frame.dim());
        }
        if (gain, offset) == (1.0, 0.0) {
            out.assign(frame);
            return Ok(());
        }
        let (inv, b) = ((1.0 / gain) as f32, offset as f32);
        map_rows(frame, out, |x| (x - b) * inv);
        Ok(())
    }
}

/// `out = f(frame)` element-wise (same shapes): over row slices when both
/// have contiguous rows (a loop the compiler vectorises), else through
/// `Zip`. The same `f` per element, so the same values either way.
fn map_rows(frame: &ArrayRef2<f32>, out: &mut Array2<f32>, f: impl Fn(f32) -> f32 + Copy) {
    let rows_ok = frame.rows().into_iter().all(|r| r.as_slice().is_some());
    if rows_ok && out.is_standard_layout() {
        for (src, mut dst) in frame.rows().into_iter().zip(out.rows_mut()) {
            let (src, dst) = (
                src.to_slice().expect("contiguous row"),
                dst.as_slice_mut().expect("standard layout"),
            );
            for (o, &x) in dst.iter_mut().zip(src) {
                *o = f(x);
            }
        }
    } else {
        Zip::from(out).and(frame).for_each(|o, &x| *o = f(x));
    }
}

/// Mean and standard deviation of every `TILE_PX` tile of `img` (the last
/// row and column of tiles possibly smaller), row-major, into `out`.
///
/// Each tile row is summed in `f32` from left to right (exact for 8-bit
/// values over a 32-pixel row), then the rows in `f64` from top to bottom;
/// the row sums of eight tiles side by side are computed together, so that
/// their chains of additions overlap instead of waiting on one another
/// (the same sums in the same order as one tile at a time; a test holds it
/// to those plain loops).
fn tile_stats(img: &ArrayRef2<f32>, out: &mut Vec<TileStats>) {
    let (h, w) = img.dim();
    out.clear();
    let tiles_x = w.div_ceil(TILE_PX);
    for ty in (0..h).step_by(TILE_PX) {
        let ye = (ty + TILE_PX).min(h);
        let base = out.len();
        // Sums of values and of squares, finished into the statistics below.
        out.resize(base + tiles_x, TileStats { mean: 0.0, sd: 0.0 });
        let band = &mut out[base..];
        for y in ty..ye {
            let row = img.row(y);
            let Some(row) = row.as_slice() else {
                for (t, acc) in band.iter_mut().enumerate() {
                    let (tx, xe) = (t * TILE_PX, ((t + 1) * TILE_PX).min(w));
                    let (mut rs, mut rs2) = (0.0f32, 0.0f32);
                    for x in tx..xe {
                        let v = row[x];
                        rs += v;
                        rs2 += v * v;
                    }
                    acc.mean += f64::from(rs);
                    acc.sd += f64::from(rs2);
                }
                continue;
            };
            let full = w / TILE_PX;
            let mut t0 = 0;
            while t0 < full {
                let n = (full - t0).min(8);
                let (mut rs, mut rs2) = ([0.0f32; 8], [0.0f32; 8]);
                for c in 0..TILE_PX {
                    for t in 0..n {
                        let v = row[(t0 + t) * TILE_PX + c];
                        rs[t] += v;
                        rs2[t] += v * v;
                    }
                }
                for t in 0..n {
                    band[t0 + t].mean += f64::from(rs[t]);
                    band[t0 + t].sd += f64::from(rs2[t]);
                }
                t0 += n;
            }
            if full < tiles_x {
                let (mut rs, mut rs2) = (0.0f32, 0.0f32);
                for &v in &row[full * TILE_PX..] {
                    rs += v;
                    rs2 += v * v;
                }
                band[full].mean += f64::from(rs);
                band[full].sd += f64::from(rs2);
            }
        }
        for (t, st) in band.iter_mut().enumerate() {
            let xe = ((t + 1) * TILE_PX).min(w);
            let n = ((ye - ty) * (xe - t * TILE_PX)) as f64;
            let (s, s2) = (st.mean, st.sd);
            let mean = s / n;
            let var = (s2 / n - mean * mean).max(0.0);
            *st = TileStats {
                mean,
                sd: var.sqrt(),
            };
        }
    }
}

/// The median of `v` (reordered), `None` when empty or not comparable.
pub(crate) fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() || v.iter().any(|x| x.is_nan()) {
        return None;
    }
    let n = v.len();
    let (_, &mut hi, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        return Some(hi);
    }
    let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(0.5 * (lo + hi))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_rows_matches_the_plain_map() {
        // Contiguous rows (a crop of a wider frame), strided ones (a
        // transposed view) and a whole standard-layout frame.
        let big = Array2::from_shape_fn((13, 21), |(y, x)| (y * 21 + x) as f32 * 1.7 - 40.0);
        let f = |x: f32| (x - 3.25) * 0.913;
        for view in [
            big.slice(ndarray::s![2..11, 3..19]),
            big.t().slice_move(ndarray::s![..12, ..]),
            big.view(),
        ] {
            let mut got = Array2::zeros(view.dim());
            map_rows(&view, &mut got, f);
            let want = view.mapv(f);
            let bits = |a: &Array2<f32>| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want));
        }
    }

    /// The tile statistics one tile and one pixel at a time: the oracle of
    /// `tile_stats`, which must give the same bits.
    fn tile_stats_plain(img: &ArrayRef2<f32>, out: &mut Vec<TileStats>) {
        let (h, w) = img.dim();
        out.clear();
        for ty in (0..h).step_by(TILE_PX) {
            for tx in (0..w).step_by(TILE_PX) {
                let (ye, xe) = ((ty + TILE_PX).min(h), (tx + TILE_PX).min(w));
                let (mut s, mut s2) = (0.0f64, 0.0f64);
                for y in ty..ye {
                    let (mut rs, mut rs2) = (0.0f32, 0.0f32);
                    for x in tx..xe {
                        let v = img[[y, x]];
                        rs += v;
                        rs2 += v * v;
                    }
                    s += f64::from(rs);
                    s2 += f64::from(rs2);
                }
                let n = ((ye - ty) * (xe - tx)) as f64;
                let mean = s / n;
                let var = (s2 / n - mean * mean).max(0.0);
                out.push(TileStats {
                    mean,
                    sd: var.sqrt(),
                });
            }
        }
    }

    #[test]
    fn tile_stats_match_the_plain_loops_bit_for_bit() {
        let mut rnd = crate::flow::unit_stream(0x2f1d_94b3_07c6_5ea1u64);
        for &(w, h) in &[(1, 1), (31, 7), (32, 32), (33, 65), (300, 70), (1600, 200)] {
            // Non-integer values, so that any change of order would show.
            let img = Array2::from_shape_fn((h, w), |_| 255.0 * rnd() + 0.1234);
            let bits = |v: &[TileStats]| {
                v.iter()
                    .map(|t| (t.mean.to_bits(), t.sd.to_bits()))
                    .collect::<Vec<_>>()
            };
            let (mut got, mut want) = (Vec::new(), Vec::new());
            tile_stats(&img, &mut got);
            tile_stats_plain(&img, &mut want);
            assert_eq!(bits(&got), bits(&want), "{w}x{h}");
            // A view whose rows are not contiguous takes the per-pixel path.
            let t = img.t();
            tile_stats(&t, &mut got);
            tile_stats_plain(&t, &mut want);
            assert_eq!(bits(&got), bits(&want), "{w}x{h} transposed");
        }
    }

    fn texture(w: usize, h: usize) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(y, x)| {
            let v = ((x * 37 + y * 91) % 23) as f32 * 6.0 + ((x / 5 + y / 7) % 3) as f32 * 20.0;
            10.0 + v
        })
    }

    #[test]
    fn gain_and_offset_are_recovered_and_taken_out() {
        let r = texture(320, 96);
        let mut c = ExposureCompensator::new(ExposureCompensation::GainOffset);
        c.set_reference(&r);
        let cur = r.mapv(|v| 1.07 * v - 3.0);
        let mut out = Array2::zeros((0, 0));
        c.compensate_into(&cur, &mut out).unwrap();
        let (a, b) = c.last();
        assert!((a - 1.07).abs() < 1e-4 && (b + 3.0).abs() < 1e-3, "{a} {b}");
        let worst = (&out - &r).mapv(f32::abs).fold(0.0f32, |m, &v| m.max(v));
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn a_changed_minority_of_tiles_does_not_bias_the_estimate() {
        let r = texture(320, 96);
        let mut c = ExposureCompensator::new(ExposureCompensation::GainOffset);
        c.set_reference(&r);
        // A quarter of the tiles replaced by something else entirely.
        let mut cur = r.clone();
        cur.slice_mut(ndarray::s![.., 0..80]).fill(250.0);
        let (a, b) = c.estimate(&cur).unwrap();
        assert!((a - 1.0).abs() < 1e-9 && b.abs() < 1e-9, "{a} {b}");
    }

    #[test]
    fn off_copies_and_offset_keeps_the_gain() {
        let r = texture(64, 64);
        let cur = r.mapv(|v| v + 2.0);
        let mut out = Array2::zeros((0, 0));
        let mut off = ExposureCompensator::new(ExposureCompensation::Off);
        off.set_reference(&r);
        off.compensate_into(&cur, &mut out).unwrap();
        assert_eq!(out, cur);
        let mut c = ExposureCompensator::new(ExposureCompensation::Offset);
        c.set_reference(&r);
        c.compensate_into(&cur, &mut out).unwrap();
        assert_eq!(c.last(), (1.0, 2.0));
        assert!(c.estimate(&Array2::zeros((3, 3))).is_err());
        for m in [
            ExposureCompensation::Off,
            ExposureCompensation::Offset,
            ExposureCompensation::GainOffset,
            ExposureCompensation::Auto,
        ] {
            assert_eq!(ExposureCompensation::parse(m.name()).unwrap(), m);
        }
        assert!(ExposureCompensation::parse("gain").is_err());
    }

    #[test]
    fn auto_leaves_frames_within_the_band_as_they_come() {
        let r = texture(320, 96);
        let mut c = ExposureCompensator::new(ExposureCompensation::Auto);
        c.set_reference(&r);
        let mut out = Array2::zeros((0, 0));
        // Within the band (gain 1.008, any offset): a plain copy.
        let flicker = r.mapv(|v| 1.008 * v + 2.0);
        c.compensate_into(&flicker, &mut out).unwrap();
        assert_eq!(c.last(), (1.0, 0.0));
        assert_eq!(out, flicker);
        // Beyond it (gain 0.96): taken out as with `GainOffset`.
        let step = r.mapv(|v| 0.96 * v + 1.0);
        c.compensate_into(&step, &mut out).unwrap();
        let (a, b) = c.last();
        assert!((a - 0.96).abs() < 1e-4 && (b - 1.0).abs() < 1e-3, "{a} {b}");
        let worst = (&out - &r).mapv(f32::abs).fold(0.0f32, |m, &v| m.max(v));
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn median_of_even_and_odd_counts() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut []), None);
    }
}
