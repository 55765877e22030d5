//! Regions of interest, channel selection and conversion to f32 grayscale.
//!
//! The markers glow green under UV light, so the green channel carries them;
//! gray (luma) input is used as it is. Every conversion produces an
//! `Array2<f32>` of shape `(height, width)` on the 8-bit scale `0..=255`
//! (16-bit samples are divided by 257, so 65535 maps to 255).
//!
//! ```
//! use optical_tactile::frame::{Channel, PixelLayout, Roi, gray_from_u8};
//! // A 2x2 RGB frame: the green channel is taken.
//! let rgb = [10, 20, 30, 11, 21, 31, 12, 22, 32, 13, 23, 33];
//! let g = gray_from_u8(&rgb, 2, 2, 6, PixelLayout::Rgb, Channel::Green).unwrap();
//! assert_eq!(g[[1, 0]], 22.0);
//! let roi = Roi::new(1, 0, 1, 2);
//! assert_eq!(roi.crop(&g).unwrap().dim(), (2, 1));
//! ```

use ndarray::{Array2, ArrayRef2, ArrayView2, s};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest width or height of a frame, image or dense field the library
/// reads: 16384 px, four times a 4K camera's width. Files declaring more are
/// refused before anything is decoded or allocated.
pub const MAX_FRAME_SIDE: usize = 1 << 14;

/// Largest number of pixels of a frame, image or dense field the library
/// reads: 2^25 (33.5 Mpx, e.g. 8192x4096), so that a decoded frame and its
/// f32 copy stay within a few hundred MB.
pub const MAX_FRAME_PIXELS: usize = 1 << 25;

/// Errors unless `width x height` is within [`MAX_FRAME_SIDE`] and
/// [`MAX_FRAME_PIXELS`] (`what` names the image in the message).
pub fn check_frame_size(what: &str, width: usize, height: usize) -> Result<()> {
    match frame_size_problem(width, height) {
        Some(m) => Err(Error::param(what, m)),
        None => Ok(()),
    }
}

/// What is wrong with a `width x height` frame's size, if anything
/// ([`check_frame_size`]).
pub(crate) fn frame_size_problem(width: usize, height: usize) -> Option<String> {
    let pixels = width.checked_mul(height);
    (width > MAX_FRAME_SIDE
        || height > MAX_FRAME_SIDE
        || pixels.is_none_or(|n| n > MAX_FRAME_PIXELS))
    .then(|| {
        format!(
            "{width}x{height} is larger than the largest frame read \
                 ({MAX_FRAME_SIDE} px a side, {MAX_FRAME_PIXELS} pixels)"
        )
    })
}

/// Which channel of a colour image becomes the grayscale image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Channel {
    /// The green channel (the markers' fluorescence); for gray input, the gray value.
    #[default]
    Green,
    /// Luma, `0.299 R + 0.587 G + 0.114 B` (Rec. 601); for YUYV input, the Y samples.
    ///
    /// (For YUYV input, `Green` is computed from Y, U and V.)
    Luma,
}

/// How the pixels of a raw buffer are laid out.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelLayout {
    /// One gray sample per pixel.
    Gray,
    /// Red, green, blue.
    Rgb,
    /// Red, green, blue, alpha.
    Rgba,
    /// Blue, green, red (OpenCV's order).
    Bgr,
    /// Packed YUV 4:2:2, two pixels in four bytes `Y0 U Y1 V` (8-bit only).
    Yuyv,
}

impl PixelLayout {
    /// Samples per pixel (YUYV: 2 bytes per pixel on average).
    pub fn samples_per_pixel(self) -> usize {
        match self {
            PixelLayout::Gray => 1,
            PixelLayout::Yuyv => 2,
            PixelLayout::Rgb | PixelLayout::Bgr => 3,
            PixelLayout::Rgba => 4,
        }
    }
}

/// A rectangular region of interest in pixels: left column `x`, top row `y`,
/// width `w`, height `h`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Roi {
    /// Left column.
    pub x: usize,
    /// Top row.
    pub y: usize,
    /// Width in pixels.
    pub w: usize,
    /// Height in pixels.
    pub h: usize,
}

impl Roi {
    /// A region from its left column, top row, width and height.
    pub fn new(x: usize, y: usize, w: usize, h: usize) -> Self {
        Roi { x, y, w, h }
    }

    /// The whole of a `width x height` frame.
    pub fn full(width: usize, height: usize) -> Self {
        Roi::new(0, 0, width, height)
    }

    /// Whether the point `[x, y]` (pixels, sub-pixel) lies in the region:
    /// from its left column and top row up to, not including, its right
    /// and bottom edges. False for a non-finite point.
    pub fn holds(&self, p: [f64; 2]) -> bool {
        let (x0, y0) = (self.x as f64, self.y as f64);
        p[0] >= x0 && p[0] < x0 + self.w as f64 && p[1] >= y0 && p[1] < y0 + self.h as f64
    }

    /// The region as `"x,y,w,h"` (the form [`Roi::parse`] reads).
    pub fn to_arg(&self) -> String {
        format!("{},{},{},{}", self.x, self.y, self.w, self.h)
    }

    /// Parses `"x,y,w,h"` (as given on a command line).
    pub fn parse(text: &str) -> Result<Self> {
        let parts: Vec<&str> = text.split(',').map(str::trim).collect();
        let bad = || {
            Error::param(
                "crop",
                format!("expected x,y,w,h with whole numbers, got `{text}`"),
            )
        };
        if parts.len() != 4 {
            return Err(bad());
        }
        let mut v = [0usize; 4];
        for (k, p) in parts.iter().enumerate() {
            v[k] = p.parse().map_err(|_| bad())?;
        }
        Ok(Roi::new(v[0], v[1], v[2], v[3]))
    }

    /// Errors with [`Error::CropOutside`] unless the region is non-empty and
    /// lies inside a `width x height` frame.
    pub fn check(&self, width: usize, height: usize) -> Result<()> {
        let inside = self.w > 0
            && self.h > 0
            && self.x.checked_add(self.w).is_some_and(|r| r <= width)
            && self.y.checked_add(self.h).is_some_and(|b| b <= height);
        if inside {
            Ok(())
        } else {
            Err(Error::CropOutside {
                x: self.x,
                y: self.y,
                w: self.w,
                h: self.h,
                frame_w: width,
                frame_h: height,
            })
        }
    }

    /// A view of this region of `image` (no copy).
    pub fn crop<'a>(&self, image: &'a ArrayRef2<f32>) -> Result<ArrayView2<'a, f32>> {
        self.check(image.ncols(), image.nrows())?;
        Ok(image.slice(s![self.y..self.y + self.h, self.x..self.x + self.w]))
    }
}

/// Checks the buffer of a `width x height` image with `row_stride` elements per
/// row and `spp` elements per pixel.
fn check_buffer(
    len: usize,
    width: usize,
    height: usize,
    row_stride: usize,
    spp: usize,
) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::TooSmall {
            what: "frame".into(),
            width,
            height,
            min_w: 1,
            min_h: 1,
        });
    }
    let row = width
        .checked_mul(spp)
        .ok_or_else(|| Error::param("width", "too large"))?;
    if row_stride < row {
        return Err(Error::param(
            "row_stride",
            format!("{row_stride} is shorter than a row of {width} pixels ({row} samples)"),
        ));
    }
    let need = (height - 1)
        .checked_mul(row_stride)
        .and_then(|n| n.checked_add(row))
        .ok_or_else(|| Error::param("height", "too large"))?;
    if len < need {
        return Err(Error::param(
            "buffer",
            format!("{len} samples for a {width}x{height} frame that needs {need}"),
        ));
    }
    Ok(())
}

/// Generic conversion into `out` (reshaped to `(height, width)` when it has
/// another shape, reusing its allocation when it can): `scale` maps a sample
/// to the 8-bit scale.
fn convert<T: Copy + Into<f32>>(
    data: &[T],
    width: usize,
    height: usize,
    row_stride: usize,
    layout: PixelLayout,
    channel: Channel,
    scale: f32,
    out: &mut Array2<f32>,
) -> Result<()> {
    check_buffer(
        data.len(),
        width,
        height,
        row_stride,
        layout.samples_per_pixel(),
    )?;
    if layout == PixelLayout::Yuyv && width % 2 == 1 {
        return Err(Error::param(
            "width",
            format!("YUYV needs an even width, got {width}"),
        ));
    }
    if out.dim() != (height, width) {
        let mut buf = std::mem::take(out).into_raw_vec_and_offset().0;
        buf.clear();
        buf.resize(height * width, 0.0);
        *out = Array2::from_shape_vec((height, width), buf).expect("length is height * width");
    }
    for (y, mut orow) in out.rows_mut().into_iter().enumerate() {
        let row = &data[y * row_stride..];
        let orow = orow
            .as_slice_mut()
            .expect("fresh array rows are contiguous");
        match layout {
            PixelLayout::Gray => {
                for (o, &g) in orow.iter_mut().zip(row) {
                    *o = g.into() * scale;
                }
            }
            // Y0 U Y1 V: two pixels share one chroma pair. Luma is the Y samples
            // as they are; green is R'G'B' green of full-range BT.601 (JFIF),
            // G = Y - 0.344136 (U - 128) - 0.714136 (V - 128), clamped to 0..=255.
            PixelLayout::Yuyv => {
                for (o, q) in orow.chunks_exact_mut(2).zip(row.chunks_exact(4)) {
                    let (y0, u, y1, v) = (q[0].into(), q[1].into(), q[2].into(), q[3].into());
                    match channel {
                        Channel::Luma => {
                            o[0] = y0 * scale;
                            o[1] = y1 * scale;
                        }
                        Channel::Green => {
                            let c = -0.344136 * (u - 128.0) - 0.714136 * (v - 128.0);
                            o[0] = (y0 + c).clamp(0.0, 255.0) * scale;
                            o[1] = (y1 + c).clamp(0.0, 255.0) * scale;
                        }
                    }
                }
            }
            PixelLayout::Rgb | PixelLayout::Rgba | PixelLayout::Bgr => {
                let spp = layout.samples_per_pixel();
                let (ri, bi) = if layout == PixelLayout::Bgr {
                    (2, 0)
                } else {
                    (0, 2)
                };
                for (o, px) in orow.iter_mut().zip(row.chunks_exact(spp)) {
                    *o = match channel {
                        Channel::Green => px[1].into(),
                        Channel::Luma => {
                            0.299 * px[ri].into() + 0.587 * px[1].into() + 0.114 * px[bi].into()
                        }
                    } * scale;
                }
            }
        }
    }
    Ok(())
}

/// Converts an 8-bit buffer (`row_stride` bytes per row) to f32 grayscale.
pub fn gray_from_u8(
    data: &[u8],
    width: usize,
    height: usize,
    row_stride: usize,
    layout: PixelLayout,
    channel: Channel,
) -> Result<Array2<f32>> {
    let mut out = Array2::zeros((0, 0));
    gray_from_u8_into(data, width, height, row_stride, layout, channel, &mut out)?;
    Ok(out)
}

/// [`gray_from_u8`] into `out`, reusing its buffer (a camera loop converts
/// every frame without allocating). `out` takes the frame's shape.
pub fn gray_from_u8_into(
    data: &[u8],
    width: usize,
    height: usize,
    row_stride: usize,
    layout: PixelLayout,
    channel: Channel,
    out: &mut Array2<f32>,
) -> Result<()> {
    convert(data, width, height, row_stride, layout, channel, 1.0, out)
}

/// Converts a 16-bit buffer (`row_stride` samples per row) to f32 grayscale on
/// the 8-bit scale.
pub fn gray_from_u16(
    data: &[u16],
    width: usize,
    height: usize,
    row_stride: usize,
    layout: PixelLayout,
    channel: Channel,
) -> Result<Array2<f32>> {
    let mut out = Array2::zeros((0, 0));
    gray_from_u16_into(data, width, height, row_stride, layout, channel, &mut out)?;
    Ok(out)
}

/// [`gray_from_u16`] into `out`, reusing its buffer.
pub fn gray_from_u16_into(
    data: &[u16],
    width: usize,
    height: usize,
    row_stride: usize,
    layout: PixelLayout,
    channel: Channel,
    out: &mut Array2<f32>,
) -> Result<()> {
    if layout == PixelLayout::Yuyv {
        return Err(Error::param("layout", "YUYV is 8-bit only"));
    }
    convert(
        data,
        width,
        height,
        row_stride,
        layout,
        channel,
        1.0 / 257.0,
        out,
    )
}

/// An 8-bit gray image of the `image` crate as f32 grayscale.
pub fn gray_from_gray_image(img: &::image::GrayImage) -> Result<Array2<f32>> {
    let mut out = Array2::zeros((0, 0));
    gray_from_gray_image_into(img, &mut out)?;
    Ok(out)
}

/// [`gray_from_gray_image`] into `out`, reusing its buffer.
pub fn gray_from_gray_image_into(img: &::image::GrayImage, out: &mut Array2<f32>) -> Result<()> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    gray_from_u8_into(
        img.as_raw(),
        w,
        h,
        w,
        PixelLayout::Gray,
        Channel::Green,
        out,
    )
}

/// An 8-bit RGB image of the `image` crate as f32 grayscale (`channel`:
/// green for the markers, or luma).
pub fn gray_from_rgb_image(img: &::image::RgbImage, channel: Channel) -> Result<Array2<f32>> {
    let mut out = Array2::zeros((0, 0));
    gray_from_rgb_image_into(img, channel, &mut out)?;
    Ok(out)
}

/// [`gray_from_rgb_image`] into `out`, reusing its buffer.
pub fn gray_from_rgb_image_into(
    img: &::image::RgbImage,
    channel: Channel,
    out: &mut Array2<f32>,
) -> Result<()> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    gray_from_u8_into(img.as_raw(), w, h, 3 * w, PixelLayout::Rgb, channel, out)
}

/// Converts a decoded image (8- or 16-bit, gray or RGB(A), or float) to f32 grayscale.
pub fn gray_from_dynamic(img: &::image::DynamicImage, channel: Channel) -> Result<Array2<f32>> {
    let mut out = Array2::zeros((0, 0));
    gray_from_dynamic_into(img, channel, &mut out)?;
    Ok(out)
}

/// [`gray_from_dynamic`] into `out`, reusing its buffer (formats other than
/// 8/16-bit gray, RGB and RGBA go through a converted copy).
pub fn gray_from_dynamic_into(
    img: &::image::DynamicImage,
    channel: Channel,
    out: &mut Array2<f32>,
) -> Result<()> {
    use ::image::DynamicImage as D;
    use PixelLayout::{Gray, Rgb, Rgba};
    let (w, h) = (img.width() as usize, img.height() as usize);
    match img {
        D::ImageLuma8(b) => gray_from_u8_into(b.as_raw(), w, h, w, Gray, channel, out),
        D::ImageRgb8(b) => gray_from_u8_into(b.as_raw(), w, h, 3 * w, Rgb, channel, out),
        D::ImageRgba8(b) => gray_from_u8_into(b.as_raw(), w, h, 4 * w, Rgba, channel, out),
        D::ImageLuma16(b) => gray_from_u16_into(b.as_raw(), w, h, w, Gray, channel, out),
        D::ImageRgb16(b) => gray_from_u16_into(b.as_raw(), w, h, 3 * w, Rgb, channel, out),
        D::ImageRgba16(b) => gray_from_u16_into(b.as_raw(), w, h, 4 * w, Rgba, channel, out),
        D::ImageLumaA8(_) => {
            let b = img.to_luma8();
            gray_from_u8_into(b.as_raw(), w, h, w, Gray, channel, out)
        }
        D::ImageLumaA16(_) => {
            let b = img.to_luma16();
            gray_from_u16_into(b.as_raw(), w, h, w, Gray, channel, out)
        }
        // Float or future formats: go through 16-bit RGBA, which keeps the channels apart.
        _ => {
            let b = img.to_rgba16();
            gray_from_u16_into(b.as_raw(), w, h, 4 * w, Rgba, channel, out)
        }
    }
}

/// Converts an f32 grayscale image to 8-bit samples (rounded and clamped to 0..=255;
/// NaN becomes 0).
pub fn to_u8(image: &ArrayRef2<f32>) -> Vec<u8> {
    image
        .iter()
        .map(|&v| {
            if v.is_nan() {
                0
            } else {
                v.round().clamp(0.0, 255.0) as u8
            }
        })
        .collect()
}

/// Writes into `out` the mean of `image` over the box of half-side `r`
/// about each pixel (clipped at the borders): window sums along each row,
/// then running sums of those down the columns (`work` and `out` resized as
/// needed, so that a frame of the same size allocates nothing).
pub fn box_mean_into(image: &ArrayRef2<f32>, r: usize, work: &mut Vec<f64>, out: &mut Array2<f32>) {
    let (h, w) = image.dim();
    if out.dim() != (h, w) {
        *out = Array2::zeros((h, w));
    }
    if h == 0 || w == 0 {
        return;
    }
    work.clear();
    work.resize(h * w + 3 * w + 1, 0.0);
    let (rows, rest) = work.split_at_mut(h * w);
    let (prefix, rest) = rest.split_at_mut(w + 1);
    // `scale`: the reciprocal of each column's box width.
    let (columns, scale) = rest.split_at_mut(w);
    // Each row's window sums, from its prefix sums.
    for (i, sums) in rows.chunks_exact_mut(w).enumerate() {
        let mut acc = 0.0;
        for (p, &v) in prefix[1..].iter_mut().zip(image.row(i)) {
            acc += f64::from(v);
            *p = acc;
        }
        for (j, o) in sums.iter_mut().enumerate() {
            *o = prefix[(j + r + 1).min(w)] - prefix[j.saturating_sub(r)];
        }
    }
    for (j, n) in scale.iter_mut().enumerate() {
        *n = 1.0 / ((j + r + 1).min(w) - j.saturating_sub(r)) as f64;
    }
    // The column sums over rows a..b, moved down a row at a time.
    let (mut a, mut b) = (0, 0);
    for (i, mut line) in out.rows_mut().into_iter().enumerate() {
        let (a1, b1) = (i.saturating_sub(r), (i + r + 1).min(h));
        for k in b..b1 {
            for (c, &v) in columns.iter_mut().zip(&rows[k * w..(k + 1) * w]) {
                *c += v;
            }
        }
        for k in a..a1 {
            for (c, &v) in columns.iter_mut().zip(&rows[k * w..(k + 1) * w]) {
                *c -= v;
            }
        }
        (a, b) = (a1, b1);
        let height = 1.0 / (b - a) as f64;
        for ((o, &c), &n) in line.iter_mut().zip(columns.iter()).zip(scale.iter()) {
            *o = (c * height * n) as f32;
        }
    }
}

/// Writes into `out` `image` divided by its own local light (its mean over
/// the box of half-side `r` about each pixel, [`box_mean_into`], into
/// `light`), times `level`: a frame whose light changes from place to place
/// (a contact's shading, a darker region) keeps its markers' contrast and
/// loses the change. `level` sets the result's grey levels (the mean light
/// of a reference, so that its frames compare with it); a local light
/// under a hundredth of it counts as that hundredth. `work`, `light` and
/// `out` are resized as needed.
pub fn divide_by_light_into(
    image: &ArrayRef2<f32>,
    r: usize,
    level: f32,
    work: &mut Vec<f64>,
    light: &mut Array2<f32>,
    out: &mut Array2<f32>,
) {
    box_mean_into(image, r, work, light);
    if out.dim() != image.dim() {
        *out = Array2::zeros(image.dim());
    }
    let floor = (0.01 * level).max(f32::MIN_POSITIVE);
    ndarray::Zip::from(&mut *out)
        .and(image)
        .and(&*light)
        .for_each(|o, &v, &l| *o = v * level / l.max(floor));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_region_holds_the_points_of_its_half_open_box() {
        let r = Roi::new(10, 20, 5, 4);
        assert!(r.holds([10.0, 20.0]) && r.holds([14.99, 23.99]));
        assert!(!r.holds([15.0, 21.0]) && !r.holds([12.0, 24.0]));
        assert!(!r.holds([9.99, 21.0]) && !r.holds([12.0, 19.99]));
        assert!(!r.holds([f64::NAN, 21.0]) && !r.holds([12.0, f64::INFINITY]));
        assert!(!Roi::new(3, 3, 0, 0).holds([3.0, 3.0]));
    }

    #[test]
    fn rgb_green_luma_and_bgr() {
        let rgb = [100u8, 50, 200];
        let g = gray_from_u8(&rgb, 1, 1, 3, PixelLayout::Rgb, Channel::Green).unwrap();
        assert_eq!(g[[0, 0]], 50.0);
        let l = gray_from_u8(&rgb, 1, 1, 3, PixelLayout::Rgb, Channel::Luma).unwrap();
        assert!((l[[0, 0]] - (29.9 + 29.35 + 22.8)).abs() < 1e-3);
        let bgr = [200u8, 50, 100];
        let l2 = gray_from_u8(&bgr, 1, 1, 3, PixelLayout::Bgr, Channel::Luma).unwrap();
        assert_eq!(l[[0, 0]], l2[[0, 0]]);
    }

    #[test]
    fn stride_padding_is_skipped() {
        // 2x2 gray with one byte of padding per row.
        let data = [1u8, 2, 99, 3, 4, 99];
        let g = gray_from_u8(&data, 2, 2, 3, PixelLayout::Gray, Channel::Green).unwrap();
        assert_eq!(g.into_raw_vec_and_offset().0, vec![1.0, 2.0, 3.0, 4.0]);
    }

    #[test]
    fn yuyv_luma_and_green() {
        // Neutral chroma: green equals luma.
        let data = [10u8, 128, 20, 128, 30, 128, 40, 128];
        let g = gray_from_u8(&data, 4, 1, 8, PixelLayout::Yuyv, Channel::Green).unwrap();
        assert_eq!(g.into_raw_vec_and_offset().0, vec![10.0, 20.0, 30.0, 40.0]);
        // Pure green (R=0, G=255, B=0) in full-range BT.601: Y=150, U=44, V=21.
        let data = [150u8, 44, 150, 21];
        let g = gray_from_u8(&data, 2, 1, 4, PixelLayout::Yuyv, Channel::Green).unwrap();
        assert!((g[[0, 0]] - 255.0).abs() < 1.5 && (g[[0, 1]] - 255.0).abs() < 1.5);
        let l = gray_from_u8(&data, 2, 1, 4, PixelLayout::Yuyv, Channel::Luma).unwrap();
        assert_eq!(l[[0, 1]], 150.0);
        assert!(gray_from_u8(&[0u8; 6], 3, 1, 6, PixelLayout::Yuyv, Channel::Green).is_err());
    }

    #[test]
    fn sixteen_bit_maps_to_eight_bit_scale() {
        let g =
            gray_from_u16(&[65535, 0, 257], 3, 1, 3, PixelLayout::Gray, Channel::Green).unwrap();
        assert_eq!(g.into_raw_vec_and_offset().0, vec![255.0, 0.0, 1.0]);
    }

    #[test]
    fn bad_buffers_are_errors() {
        assert!(gray_from_u8(&[], 0, 0, 0, PixelLayout::Gray, Channel::Green).is_err());
        assert!(gray_from_u8(&[1, 2, 3], 2, 2, 2, PixelLayout::Gray, Channel::Green).is_err());
        assert!(gray_from_u8(&[1, 2, 3, 4], 2, 2, 1, PixelLayout::Gray, Channel::Green).is_err());
        assert!(
            gray_from_u8(
                &[1; 4],
                usize::MAX,
                2,
                usize::MAX,
                PixelLayout::Rgb,
                Channel::Green
            )
            .is_err()
        );
    }

    #[test]
    fn crop_inside_and_outside() {
        let img = Array2::from_shape_fn((4, 5), |(y, x)| (10 * y + x) as f32);
        let c = Roi::new(1, 2, 3, 2).crop(&img).unwrap();
        assert_eq!(c[[0, 0]], 21.0);
        assert_eq!(c.dim(), (2, 3));
        assert!(matches!(
            Roi::new(3, 0, 3, 1).crop(&img),
            Err(Error::CropOutside { .. })
        ));
        assert!(Roi::new(0, 0, 0, 1).crop(&img).is_err());
        assert!(Roi::new(usize::MAX, 0, 2, 1).crop(&img).is_err());
    }

    #[test]
    fn roi_parsing() {
        assert_eq!(Roi::parse("1, 2,3,4").unwrap(), Roi::new(1, 2, 3, 4));
        assert!(Roi::parse("1,2,3").is_err());
        assert!(Roi::parse("1,2,3,-4").is_err());
    }

    #[test]
    fn to_u8_rounds_and_clamps() {
        let a = ndarray::arr2(&[[-3.0f32, 0.4, 0.6, 300.0, f32::NAN]]);
        assert_eq!(to_u8(&a), vec![0, 0, 1, 255, 0]);
    }

    /// The box mean by its running sums against a direct mean over each
    /// box, on images of several sizes and radii, the buffers kept from one
    /// image to the next (a smaller image, then a larger one).
    #[test]
    fn the_box_mean_matches_a_direct_mean() {
        let (mut sat, mut out) = (Vec::new(), Array2::zeros((0, 0)));
        let mut state = 9_u64;
        for (w, h, r) in [(37, 23, 5), (9, 4, 7), (64, 48, 0), (50, 61, 11)] {
            let img = Array2::from_shape_fn((h, w), |_| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                60.0 + ((state >> 40) as f32) / 200_000.0
            });
            box_mean_into(&img, r, &mut sat, &mut out);
            assert_eq!(out.dim(), (h, w));
            for i in 0..h {
                for j in 0..w {
                    let (a, b) = (i.saturating_sub(r), (i + r + 1).min(h));
                    let (c, d) = (j.saturating_sub(r), (j + r + 1).min(w));
                    let mut s = 0.0f64;
                    for y in a..b {
                        for x in c..d {
                            s += f64::from(img[[y, x]]);
                        }
                    }
                    let want = s / ((b - a) * (d - c)) as f64;
                    let got = f64::from(out[[i, j]]);
                    assert!(
                        (got - want).abs() < 1e-3,
                        "{w}x{h} r {r} at ({i}, {j}): {got} against {want}"
                    );
                }
            }
        }
    }

    /// A frame whose light falls by 40% over a Gaussian of 30 px reads,
    /// divided by its own light over a box of 9 px, as the unscaled frame
    /// does within 3% (2.2% at worst: the light's curvature and its slope
    /// against the texture within a box), and a uniform frame reads
    /// `level`.
    #[test]
    fn dividing_by_the_light_takes_out_a_smooth_change_of_it() {
        let (h, w) = (60, 80);
        let mut state = 3_u64;
        let img = Array2::from_shape_fn((h, w), |_| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            40.0 + ((state >> 40) as f32) / 100_000.0
        });
        let lit = Array2::from_shape_fn((h, w), |(i, j)| {
            let (dx, dy) = (j as f32 - 40.0, i as f32 - 30.0);
            img[[i, j]] * (1.0 - 0.4 * (-(dx * dx + dy * dy) / (2.0 * 30.0 * 30.0)).exp())
        });
        let (mut work, mut light) = (Vec::new(), Array2::zeros((0, 0)));
        let (mut a, mut b) = (Array2::zeros((0, 0)), Array2::zeros((0, 0)));
        divide_by_light_into(&img, 4, 100.0, &mut work, &mut light, &mut a);
        divide_by_light_into(&lit, 4, 100.0, &mut work, &mut light, &mut b);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs() / x)
            .fold(0.0f32, f32::max);
        assert!(worst < 0.03, "{worst}");
        let flat = Array2::from_elem((5, 7), 37.0f32);
        divide_by_light_into(&flat, 2, 100.0, &mut work, &mut light, &mut a);
        assert!(a.iter().all(|&v| (v - 100.0).abs() < 1e-3), "{a:?}");
        let dark = Array2::zeros((4, 4));
        divide_by_light_into(&dark, 1, 100.0, &mut work, &mut light, &mut a);
        assert!(a.iter().all(|v| *v == 0.0));
    }
}
