//! NumPy frames as the library's grey images.
//!
//! A frame is an `ndarray` of `uint8`, `uint16` or `float32`, grey `(H, W)`
//! or colour `(H, W, 3)` (also `(H, W, 1)` and RGBA `(H, W, 4)`). Each row's
//! pixels must lie contiguously in memory (a C-contiguous array, or a crop of
//! one such as `frame[y0:y1, x0:x1]`); rows may be any distance apart. A grey
//! `float32` frame and the green channel of a colour `float32` frame are read
//! in place, without a copy; other frames are converted into a reused buffer
//! by the library's own conversion (`frame::gray_from_u8_into`, ...), so the
//! grey values are exactly those of a PNG read by the library.

use ndarray::{Array2, ArrayView2, ArrayView3, ArrayViewD, ArrayViewMut2, Axis, Ix3, s};
use numpy::{PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray};
use optical_tactile::frame::{
    Channel, PixelLayout, Roi, check_frame_size, gray_from_u8_into, gray_from_u16_into,
};
use pyo3::prelude::*;

use crate::errors::Failure;

/// How a colour frame becomes grey.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Colour {
    /// Green (the markers) or luma.
    pub channel: Channel,
    /// Whether colour frames are BGR (OpenCV's order) rather than RGB.
    pub bgr: bool,
}

impl Colour {
    /// From the Python arguments `channel` ("green" or "luma") and
    /// `color_order` ("rgb" or "bgr").
    pub fn parse(channel: &str, order: &str) -> Result<Self, Failure> {
        let channel = match channel.to_ascii_lowercase().as_str() {
            "green" => Channel::Green,
            "luma" => Channel::Luma,
            _ => {
                return Err(Failure::Invalid(format!(
                    "invalid parameter `channel`: expected \"green\" or \"luma\", got {channel:?}"
                )));
            }
        };
        let bgr = match order.to_ascii_lowercase().as_str() {
            "rgb" => false,
            "bgr" => true,
            _ => {
                return Err(Failure::Invalid(format!(
                    "invalid parameter `color_order`: expected \"rgb\" or \"bgr\", got {order:?}"
                )));
            }
        };
        Ok(Colour { channel, bgr })
    }
}

/// A frame argument, borrowed read-only from NumPy (the borrow is held while
/// the frame is processed).
pub enum FrameArg<'py> {
    /// 8-bit samples.
    U8(PyReadonlyArrayDyn<'py, u8>),
    /// 16-bit samples.
    U16(PyReadonlyArrayDyn<'py, u16>),
    /// Floating-point samples on the 8-bit scale.
    F32(PyReadonlyArrayDyn<'py, f32>),
}

/// The pixels of a frame as `(H, W, C)`, ready to cross into a thread
/// without the GIL.
pub enum Pixels<'a> {
    /// 8-bit samples.
    U8(ArrayView3<'a, u8>),
    /// 16-bit samples.
    U16(ArrayView3<'a, u16>),
    /// Floating-point samples.
    F32(ArrayView3<'a, f32>),
}

impl<'py> FrameArg<'py> {
    /// Checks `obj` (named `what` in messages) and borrows it.
    pub fn extract(obj: &Bound<'py, PyAny>, what: &str) -> Result<Self, Failure> {
        let Ok(array) = obj.cast::<PyUntypedArray>() else {
            return Err(Failure::Type(format!(
                "{what} must be a numpy.ndarray, got {}",
                type_name(obj)
            )));
        };
        let borrowed = |e: numpy::BorrowError| {
            Failure::Invalid(format!(
                "{what}: the array is borrowed mutably elsewhere ({e})"
            ))
        };
        let arg = if let Ok(a) = array.cast::<PyArrayDyn<u8>>() {
            FrameArg::U8(a.try_readonly().map_err(borrowed)?)
        } else if let Ok(a) = array.cast::<PyArrayDyn<u16>>() {
            FrameArg::U16(a.try_readonly().map_err(borrowed)?)
        } else if let Ok(a) = array.cast::<PyArrayDyn<f32>>() {
            FrameArg::F32(a.try_readonly().map_err(borrowed)?)
        } else {
            let dtype = array
                .getattr("dtype")
                .and_then(|d| d.str())
                .map(|s| s.to_string())
                .unwrap_or_else(|_| "?".into());
            return Err(Failure::Type(format!(
                "{what} must have dtype uint8, uint16 or float32 (native byte order), got {dtype}"
            )));
        };
        // The checks on the shape and layout, once, with the GIL held.
        arg.pixels(what)?;
        Ok(arg)
    }

    /// The pixels as `(H, W, C)`, after checking the shape, the size and
    /// that each row's pixels are contiguous.
    pub fn pixels(&self, what: &str) -> Result<Pixels<'_>, Failure> {
        Ok(match self {
            FrameArg::U8(a) => Pixels::U8(shaped(a.as_array(), what)?),
            FrameArg::U16(a) => Pixels::U16(shaped(a.as_array(), what)?),
            FrameArg::F32(a) => Pixels::F32(shaped(a.as_array(), what)?),
        })
    }
}

fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// `(H, W)` or `(H, W, C)` with `C` in 1, 3, 4, within the library's size
/// bounds, rows of contiguous pixels.
fn shaped<'a, T>(a: ArrayViewD<'a, T>, what: &str) -> Result<ArrayView3<'a, T>, Failure> {
    let shape = a.shape().to_vec();
    let a3 = match shape.len() {
        2 => a.insert_axis(Axis(2)),
        3 if matches!(shape[2], 1 | 3 | 4) => a,
        _ => {
            return Err(Failure::Invalid(format!(
                "{what}: expected shape (H, W) or (H, W, 3) (also (H, W, 1), (H, W, 4)), got {shape:?}"
            )));
        }
    };
    let a3 = a3
        .into_dimensionality::<Ix3>()
        .map_err(|e| Failure::Invalid(format!("{what}: {e}")))?;
    let (h, w, _) = a3.dim();
    check_frame_size(what, w, h)?;
    if h == 0 || w == 0 {
        return Err(Failure::Invalid(format!(
            "{what}: {w}x{h} is empty (need at least 1x1)"
        )));
    }
    if !a3.index_axis(Axis(0), 0).is_standard_layout() {
        return Err(Failure::Invalid(format!(
            "{what}: the pixels of a row are not contiguous in memory (strides {:?}); \
             pass numpy.ascontiguousarray(frame)",
            a3.strides()
        )));
    }
    Ok(a3)
}

impl Pixels<'_> {
    /// `(H, W, C)`.
    pub fn dim(&self) -> (usize, usize, usize) {
        match self {
            Pixels::U8(a) => a.dim(),
            Pixels::U16(a) => a.dim(),
            Pixels::F32(a) => a.dim(),
        }
    }

    /// The pixels of `r` (which must lie inside).
    fn window(&self, r: Roi) -> Pixels<'_> {
        let w = s![r.y..r.y + r.h, r.x..r.x + r.w, ..];
        match self {
            Pixels::U8(a) => Pixels::U8(a.slice(w)),
            Pixels::U16(a) => Pixels::U16(a.slice(w)),
            Pixels::F32(a) => Pixels::F32(a.slice(w)),
        }
    }

    /// Whether [`to_gray`] reads the frame in place (no conversion).
    fn in_place(&self, colour: Colour) -> bool {
        matches!(self, Pixels::F32(_)) && (self.dim().2 == 1 || colour.channel == Channel::Green)
    }
}

/// [`to_gray`] for a pipeline that reads only `roi` of the frame (the
/// sensor's crop): a frame that needs converting is converted there only,
/// into `buf` of the frame's size (the rest of `buf` is left as it is, zero
/// when first allocated, and never read); `row` is a reused row buffer. A
/// frame read in place, no `roi` or a `roi` not inside the frame: as
/// [`to_gray`].
pub fn to_gray_within<'a>(
    px: &'a Pixels<'_>,
    colour: Colour,
    roi: Option<Roi>,
    buf: &'a mut Array2<f32>,
    row: &mut Array2<f32>,
) -> Result<ArrayView2<'a, f32>, Failure> {
    let (h, w, _) = px.dim();
    let inside = |r: &Roi| {
        r.w > 0
            && r.h > 0
            && r.x.checked_add(r.w).is_some_and(|e| e <= w)
            && r.y.checked_add(r.h).is_some_and(|e| e <= h)
    };
    let Some(r) = roi.filter(|r| !px.in_place(colour) && inside(r)) else {
        return to_gray(px, colour, buf);
    };
    if buf.dim() != (h, w) {
        *buf = Array2::zeros((h, w));
    }
    let dest = buf.slice_mut(s![r.y..r.y + r.h, r.x..r.x + r.w]);
    convert_into(&px.window(r), colour, dest, row)?;
    Ok(buf.view())
}

/// The grey image of `px`: a view into the frame itself (grey `float32`, or
/// the green channel of colour `float32`) or into `buf`, converted.
pub fn to_gray<'a>(
    px: &'a Pixels<'_>,
    colour: Colour,
    buf: &'a mut Array2<f32>,
) -> Result<ArrayView2<'a, f32>, Failure> {
    if let Pixels::F32(a) = px {
        if a.dim().2 == 1 {
            return Ok(a.index_axis(Axis(2), 0));
        }
        if colour.channel == Channel::Green {
            return Ok(a.index_axis(Axis(2), 1));
        }
    }
    let (h, w, c) = px.dim();
    // A C-contiguous integer frame: one call of the library's conversion.
    let whole = match px {
        Pixels::U8(a) => a
            .as_slice()
            .map(|all| gray_from_u8_into(all, w, h, w * c, layout(c, colour)?, colour.channel, buf))
            .transpose()?,
        Pixels::U16(a) => a
            .as_slice()
            .map(|all| {
                gray_from_u16_into(all, w, h, w * c, layout(c, colour)?, colour.channel, buf)
            })
            .transpose()?,
        Pixels::F32(_) => None,
    };
    if whole.is_none() {
        if buf.dim() != (h, w) {
            *buf = Array2::zeros((h, w));
        }
        let mut row = Array2::zeros((0, 0));
        convert_into(px, colour, buf.view_mut(), &mut row)?;
    }
    Ok(buf.view())
}

/// The library's layout of `c` samples per pixel.
fn layout(c: usize, colour: Colour) -> optical_tactile::Result<PixelLayout> {
    Ok(match (c, colour.bgr) {
        (1, _) => PixelLayout::Gray,
        (3, false) => PixelLayout::Rgb,
        (3, true) => PixelLayout::Bgr,
        (4, false) => PixelLayout::Rgba,
        // BGRA: green is where RGBA has it; luma would mix the wrong channels.
        (4, true) if colour.channel == Channel::Green => PixelLayout::Rgba,
        _ => {
            return Err(optical_tactile::Error::param(
                "color_order",
                "luma of a BGRA frame is not supported: pass (H, W, 3) or RGBA",
            ));
        }
    })
}

/// The library's conversion of a buffer (`data, width, height, row_stride,
/// layout, channel, out`).
type Convert<T> = fn(
    &[T],
    usize,
    usize,
    usize,
    PixelLayout,
    Channel,
    &mut Array2<f32>,
) -> optical_tactile::Result<()>;

/// Converts `px` into `dest` (of its height and width) row by row, each row
/// through `row`.
fn convert_into(
    px: &Pixels<'_>,
    colour: Colour,
    mut dest: ArrayViewMut2<'_, f32>,
    row: &mut Array2<f32>,
) -> Result<(), Failure> {
    match px {
        Pixels::U8(a) => rows_into(a, colour, dest, row, gray_from_u8_into),
        Pixels::U16(a) => rows_into(a, colour, dest, row, gray_from_u16_into),
        Pixels::F32(a) => {
            let c = a.dim().2;
            if c == 1 || colour.channel == Channel::Green {
                dest.assign(&a.index_axis(Axis(2), if c == 1 { 0 } else { 1 }));
                return Ok(());
            }
            layout(c, colour)?;
            let (ri, bi) = if colour.bgr { (2, 0) } else { (0, 2) };
            // Rec. 601 luma, as the library computes it for integer frames.
            ndarray::Zip::from(dest)
                .and(a.lanes(Axis(2)))
                .for_each(|o, p| *o = 0.299 * p[ri] + 0.587 * p[1] + 0.114 * p[bi]);
            Ok(())
        }
    }
}

fn rows_into<T: Copy>(
    a: &ArrayView3<'_, T>,
    colour: Colour,
    mut dest: ArrayViewMut2<'_, f32>,
    row: &mut Array2<f32>,
    convert: Convert<T>,
) -> Result<(), Failure> {
    let (h, w, c) = a.dim();
    let layout = layout(c, colour)?;
    for y in 0..h {
        let r = a.index_axis(Axis(0), y);
        let s = r
            .as_slice()
            .ok_or_else(|| Failure::Invalid("a row's pixels are not contiguous".into()))?;
        convert(s, w, 1, w * c, layout, colour.channel, row)?;
        dest.row_mut(y).assign(&row.row(0));
    }
    Ok(())
}
