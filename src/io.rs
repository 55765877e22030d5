//! File formats: Middlebury `.flo`, 2-D `.npy`, PNG images and sequences, JSON
//! Lines of contacts, the characterization dataset's `tests.csv` and `poses.csv`.
//!
//! The formats are specified in docs/formats.md; they are interfaces with
//! other tools, so they are written exactly and read strictly: every error
//! names the file (and the line, for line-oriented files).

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use ndarray::{Array2, ArrayRef2};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::flow::FlowField;
use crate::frame::{Channel, MAX_FRAME_PIXELS, frame_size_problem, gray_from_dynamic, to_u8};

mod finite;

pub use finite::check_finite;

/// The magic number at the start of a Middlebury `.flo` file ("PIEH" as a float).
pub const FLO_MAGIC: f32 = 202021.25;

/// Largest PNG file read: 512 MiB (a frame of [`MAX_FRAME_PIXELS`] pixels in
/// 16-bit RGBA, uncompressed, is 256 MiB).
pub const MAX_IMAGE_BYTES: u64 = 512 << 20;

/// Largest JSON Lines file read (contacts, truth): 512 MiB, about a day of
/// frames at 50 fps with a few contacts each.
pub const MAX_JSONL_BYTES: u64 = 512 << 20;

/// Largest CSV file read (`tests.csv`, `poses.csv`): 256 MiB.
pub const MAX_CSV_BYTES: u64 = 256 << 20;

/// Largest calibration file read: 64 MiB (the largest valid calibration,
/// every map and the profile model at their bounds, is a few MB).
pub const MAX_CALIBRATION_BYTES: u64 = 64 << 20;

/// Longest line of a JSON Lines or CSV file: 16 MiB.
pub const MAX_LINE_BYTES: usize = 16 << 20;

/// Largest `.npy` header (version 2 and 3 allow 4 GiB; numpy writes a few
/// hundred bytes).
const MAX_NPY_HEADER: usize = 1 << 16;

/// Opens `path` for reading if it is a regular file of at most `max_bytes`,
/// returning the file and its length. A directory, a FIFO, a socket or a
/// device is refused before it is opened (opening a FIFO would wait for a
/// writer; a device such as `/dev/zero` never ends), and so is a larger file.
pub(crate) fn open_regular(path: &Path, max_bytes: u64) -> Result<(File, u64)> {
    let not_a_file = |meta: &std::fs::Metadata| -> Option<Error> {
        if meta.is_dir() {
            Some(Error::io(
                path,
                std::io::Error::new(
                    std::io::ErrorKind::IsADirectory,
                    "is a directory, where a file is expected",
                ),
            ))
        } else if !meta.is_file() {
            Some(Error::io(
                path,
                std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "is not a regular file (a FIFO, socket or device), where a file is expected",
                ),
            ))
        } else if meta.len() > max_bytes {
            Some(Error::format(
                path,
                None,
                format!(
                    "{} bytes, more than the {max_bytes} bytes a file of this kind may have",
                    meta.len()
                ),
            ))
        } else {
            None
        }
    };
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if let Some(e) = not_a_file(&meta) {
        return Err(e);
    }
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    // The path may have been replaced between the two looks: check what was
    // opened.
    let meta = file.metadata().map_err(|e| Error::io(path, e))?;
    if let Some(e) = not_a_file(&meta) {
        return Err(e);
    }
    Ok((file, meta.len()))
}

/// Reads a whole regular file of at most `max_bytes` (a file that grows
/// while it is read is cut at `max_bytes + 1` and refused).
pub(crate) fn read_capped(path: &Path, max_bytes: u64) -> Result<Vec<u8>> {
    let (file, len) = open_regular(path, max_bytes)?;
    let mut buf = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    file.take(max_bytes.saturating_add(1))
        .read_to_end(&mut buf)
        .map_err(|e| Error::io(path, e))?;
    if buf.len() as u64 > max_bytes {
        return Err(Error::format(
            path,
            None,
            format!("grew past {max_bytes} bytes while it was read"),
        ));
    }
    Ok(buf)
}

/// The lines of a regular file of at most `max_bytes`, each of at most
/// [`MAX_LINE_BYTES`], with their 1-based numbers; `f` is called on each
/// (without its line ending). Errors name the file and line.
fn for_each_line(
    path: &Path,
    max_bytes: u64,
    mut f: impl FnMut(usize, &str) -> Result<()>,
) -> Result<()> {
    let (file, _) = open_regular(path, max_bytes)?;
    let mut reader = BufReader::new(file.take(max_bytes.saturating_add(1)));
    let mut buf = Vec::new();
    let mut total = 0u64;
    for number in 1.. {
        buf.clear();
        let n = (&mut reader)
            .take(MAX_LINE_BYTES as u64 + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        total += n as u64;
        if total > max_bytes {
            return Err(Error::format(
                path,
                Some(number),
                format!("grew past {max_bytes} bytes while it was read"),
            ));
        }
        if buf.last() == Some(&b'\n') {
            buf.pop();
            if buf.last() == Some(&b'\r') {
                buf.pop();
            }
        } else if buf.len() > MAX_LINE_BYTES {
            return Err(Error::format(
                path,
                Some(number),
                format!("a line longer than {MAX_LINE_BYTES} bytes"),
            ));
        }
        let line = std::str::from_utf8(&buf)
            .map_err(|e| Error::format(path, Some(number), format!("not UTF-8 text: {e}")))?;
        f(number, line)?;
    }
    Ok(())
}

fn create(path: &Path) -> Result<BufWriter<File>> {
    File::create(path)
        .map(BufWriter::new)
        .map_err(|e| Error::io(path, e))
}

// ---------------------------------------------------------------- images

/// Reads a PNG (8- or 16-bit; gray, gray+alpha, RGB or RGBA) as f32 grayscale on
/// the 8-bit scale; colour images give their green channel.
pub fn read_gray(path: impl AsRef<Path>) -> Result<Array2<f32>> {
    read_gray_channel(path, Channel::Green)
}

/// Like [`read_gray`], choosing the channel of colour images.
///
/// The file must be a regular file of at most [`MAX_IMAGE_BYTES`]; the
/// image's declared size is checked against [`crate::frame::MAX_FRAME_SIDE`]
/// and [`MAX_FRAME_PIXELS`] from its header, before anything is decoded.
pub fn read_gray_channel(path: impl AsRef<Path>, channel: Channel) -> Result<Array2<f32>> {
    use ::image::ImageDecoder as _;
    let path = path.as_ref();
    let image_err = |source| Error::Image {
        path: path.to_path_buf(),
        source,
    };
    let too_large = |w: u32, h: u32| match frame_size_problem(w as usize, h as usize) {
        Some(m) => Err(Error::format(path, None, m)),
        None => Ok(()),
    };
    let (file, _) = open_regular(path, MAX_IMAGE_BYTES)?;
    let mut file = BufReader::new(file);
    // A PNG's size is in its first chunk (IHDR, bytes 16..24): refused there
    // with a clear message, before the decoder sees it.
    let head = file.fill_buf().map_err(|e| Error::io(path, e))?;
    if head.len() >= 24 && head.starts_with(b"\x89PNG\r\n\x1a\n") && &head[12..16] == b"IHDR" {
        let be = |k: usize| u32::from_be_bytes([head[k], head[k + 1], head[k + 2], head[k + 3]]);
        too_large(be(16), be(20))?;
    }
    let mut reader = ::image::ImageReader::new(file)
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    let mut limits = ::image::Limits::default();
    limits.max_image_width = Some(crate::frame::MAX_FRAME_SIDE as u32);
    limits.max_image_height = Some(crate::frame::MAX_FRAME_SIDE as u32);
    // 16-bit RGBA at the largest frame, and the decoder's own buffers.
    limits.max_alloc = Some(8 * MAX_FRAME_PIXELS as u64 + (64 << 20));
    reader.limits(limits);
    let decoder = reader.into_decoder().map_err(image_err)?;
    let (w, h) = decoder.dimensions();
    too_large(w, h)?;
    let img = ::image::DynamicImage::from_decoder(decoder).map_err(image_err)?;
    gray_from_dynamic(&img, channel)
}

/// Writes an f32 grayscale image as an 8-bit gray PNG (rounded, clamped to 0..=255).
pub fn write_gray_png(path: impl AsRef<Path>, image: &ArrayRef2<f32>) -> Result<()> {
    let path = path.as_ref();
    let (h, w) = image.dim();
    write_png(path, &to_u8(image), w, h, ::image::ExtendedColorType::L8)
}

/// Writes an 8-bit RGB image (`3 * width * height` bytes, row-major) as PNG.
pub fn write_rgb_png(
    path: impl AsRef<Path>,
    rgb: &[u8],
    width: usize,
    height: usize,
) -> Result<()> {
    if rgb.len() != 3 * width * height {
        return Err(Error::param(
            "rgb",
            format!("{} bytes for a {width}x{height} RGB image", rgb.len()),
        ));
    }
    write_png(
        path.as_ref(),
        rgb,
        width,
        height,
        ::image::ExtendedColorType::Rgb8,
    )
}

fn write_png(
    path: &Path,
    data: &[u8],
    width: usize,
    height: usize,
    color: ::image::ExtendedColorType,
) -> Result<()> {
    use ::image::ImageEncoder;
    if width == 0 || height == 0 {
        return Err(Error::TooSmall {
            what: format!("image for {}", path.display()),
            width,
            height,
            min_w: 1,
            min_h: 1,
        });
    }
    let mut out = create(path)?;
    ::image::codecs::png::PngEncoder::new(&mut out)
        .write_image(data, width as u32, height as u32, color)
        .map_err(|source| Error::Image {
            path: path.to_path_buf(),
            source,
        })?;
    out.flush().map_err(|e| Error::io(path, e))
}

/// The frames of an image sequence: the `.png` files of `dir` (case-insensitive
/// extension) in lexicographic order, which is time order. Other files
/// (`truth.jsonl`, `poses.csv`, ...) are ignored. Errors if there is none.
pub fn list_frames(dir: impl AsRef<Path>) -> Result<Vec<PathBuf>> {
    let dir = dir.as_ref();
    let mut frames = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        let is_png = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if is_png && path.is_file() {
            frames.push(path);
        }
    }
    if frames.is_empty() {
        return Err(Error::format(dir, None, "no .png frames in this directory"));
    }
    frames.sort();
    Ok(frames)
}

// ---------------------------------------------------------------- .flo

/// Writes a flow as Middlebury `.flo`.
pub fn write_flo(path: impl AsRef<Path>, flow: &FlowField) -> Result<()> {
    let path = path.as_ref();
    let (w, h) = flow.size();
    let mut buf = Vec::with_capacity(12 + 8 * w * h);
    buf.extend_from_slice(&FLO_MAGIC.to_le_bytes());
    buf.extend_from_slice(&(w as i32).to_le_bytes());
    buf.extend_from_slice(&(h as i32).to_le_bytes());
    for (u, v) in flow.u.iter().zip(flow.v.iter()) {
        buf.extend_from_slice(&u.to_le_bytes());
        buf.extend_from_slice(&v.to_le_bytes());
    }
    let mut out = create(path)?;
    out.write_all(&buf)
        .and_then(|_| out.flush())
        .map_err(|e| Error::io(path, e))
}

/// Reads a Middlebury `.flo` file. The file must be a regular file; its
/// declared size is checked against the largest frame
/// ([`crate::frame::MAX_FRAME_SIDE`], [`MAX_FRAME_PIXELS`]) and against the
/// file's length before the data is read.
pub fn read_flo(path: impl AsRef<Path>) -> Result<FlowField> {
    let path = path.as_ref();
    let (file, len) = open_regular(path, 12 + 8 * MAX_FRAME_PIXELS as u64)?;
    let mut head = [0u8; 12];
    let mut file = BufReader::new(file);
    if len < 12 {
        return Err(Error::format(
            path,
            None,
            "shorter than a .flo header (12 bytes)",
        ));
    }
    file.read_exact(&mut head).map_err(|e| Error::io(path, e))?;
    let word = |b: &[u8], k: usize| [b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]];
    let magic = f32::from_le_bytes(word(&head, 0));
    if magic != FLO_MAGIC {
        return Err(Error::format(
            path,
            None,
            format!("bad magic {magic} (a .flo file starts with {FLO_MAGIC})"),
        ));
    }
    let (w, h) = (
        i32::from_le_bytes(word(&head, 1)),
        i32::from_le_bytes(word(&head, 2)),
    );
    if w <= 0 || h <= 0 {
        return Err(Error::format(
            path,
            None,
            format!("implausible size {w}x{h}"),
        ));
    }
    let (w, h) = (w as usize, h as usize);
    if let Some(m) = frame_size_problem(w, h) {
        return Err(Error::format(path, None, m));
    }
    // Cannot overflow: w * h <= MAX_FRAME_PIXELS.
    let need = 12 + 8 * w * h;
    if len != need as u64 {
        return Err(Error::format(
            path,
            None,
            format!("{len} bytes, but a {w}x{h} flow takes {need}"),
        ));
    }
    let mut buf = vec![0u8; need - 12];
    file.read_exact(&mut buf).map_err(|e| Error::io(path, e))?;
    let mut u = Array2::zeros((h, w));
    let mut v = Array2::zeros((h, w));
    for (k, (pu, pv)) in u.iter_mut().zip(v.iter_mut()).enumerate() {
        *pu = f32::from_le_bytes(word(&buf, 2 * k));
        *pv = f32::from_le_bytes(word(&buf, 2 * k + 1));
    }
    FlowField::from_planes(u, v)
}

// ---------------------------------------------------------------- .npy

fn npy_header(descr: &str, h: usize, w: usize) -> Vec<u8> {
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    // Pad with spaces so that magic + len + header + '\n' is a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

fn write_npy<T: Copy>(
    path: &Path,
    a: &ArrayRef2<T>,
    descr: &str,
    bytes: impl Fn(T) -> Vec<u8>,
) -> Result<()> {
    let (h, w) = a.dim();
    let mut buf = npy_header(descr, h, w);
    for &x in a.iter() {
        buf.extend_from_slice(&bytes(x));
    }
    let mut out = create(path)?;
    out.write_all(&buf)
        .and_then(|_| out.flush())
        .map_err(|e| Error::io(path, e))
}

/// Writes a 2-D f32 array as `.npy` (`<f4`, C order).
pub fn write_npy_f32(path: impl AsRef<Path>, a: &ArrayRef2<f32>) -> Result<()> {
    write_npy(path.as_ref(), a, "<f4", |x| x.to_le_bytes().to_vec())
}

/// Writes a 2-D f64 array as `.npy` (`<f8`, C order).
pub fn write_npy_f64(path: impl AsRef<Path>, a: &ArrayRef2<f64>) -> Result<()> {
    write_npy(path.as_ref(), a, "<f8", |x| x.to_le_bytes().to_vec())
}

/// Reads a 2-D `.npy` of little-endian f4 or f8 (C or Fortran order) as f64.
pub fn read_npy_f64(path: impl AsRef<Path>) -> Result<Array2<f64>> {
    let path = path.as_ref();
    let buf = read_capped(path, (12 + MAX_NPY_HEADER + 8 * MAX_FRAME_PIXELS) as u64)?;
    let bad = |m: String| Error::format(path, None, m);
    if buf.len() < 10 || &buf[..6] != b"\x93NUMPY" {
        return Err(bad("not a .npy file (bad magic)".into()));
    }
    let (hlen, start) = match buf[6] {
        1 => (u16::from_le_bytes([buf[8], buf[9]]) as usize, 10),
        2 | 3 if buf.len() >= 12 => (
            u32::from_le_bytes([buf[8], buf[9], buf[10], buf[11]]) as usize,
            12,
        ),
        v => return Err(bad(format!("unsupported .npy version {v}"))),
    };
    if hlen > MAX_NPY_HEADER {
        return Err(bad(format!(
            "a header of {hlen} bytes (at most {MAX_NPY_HEADER} are read)"
        )));
    }
    let header = buf
        .get(start..start + hlen)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| bad("truncated or non-text header".into()))?;
    let field = |key: &str| -> Option<&str> {
        let at = header.find(&format!("'{key}'"))? + key.len() + 2;
        let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest)
    };
    let descr = field("descr")
        .and_then(|r| r.strip_prefix('\''))
        .and_then(|r| r.split('\'').next())
        .ok_or_else(|| bad("header has no 'descr'".into()))?;
    let size = match descr {
        "<f4" => 4,
        "<f8" => 8,
        d => return Err(bad(format!("dtype {d} is not supported (need <f4 or <f8)"))),
    };
    let fortran = field("fortran_order")
        .map(|r| r.starts_with("True"))
        .ok_or_else(|| bad("header has no 'fortran_order'".into()))?;
    let shape = field("shape")
        .and_then(|r| r.strip_prefix('('))
        .and_then(|r| r.split(')').next())
        .ok_or_else(|| bad("header has no 'shape'".into()))?;
    let dims: Vec<usize> = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| bad(format!("bad shape ({shape})")))?;
    let [h, w] = dims[..] else {
        return Err(bad(format!("expected a 2-D array, got shape ({shape})")));
    };
    if let Some(m) = frame_size_problem(w, h) {
        return Err(bad(format!("shape ({h}, {w}): {m}")));
    }
    let data = &buf[start + hlen..];
    // Cannot overflow: h * w <= MAX_FRAME_PIXELS.
    if data.len() != h * w * size {
        return Err(bad(format!(
            "{} data bytes, but shape ({h}, {w}) of {descr} takes {}",
            data.len(),
            h * w * size
        )));
    }
    let values: Vec<f64> = if size == 4 {
        data.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
            .collect()
    } else {
        data.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("chunk of 8")))
            .collect()
    };
    let a = if fortran {
        Array2::from_shape_vec((w, h), values)
            .map(|a| a.reversed_axes().as_standard_layout().into_owned())
    } else {
        Array2::from_shape_vec((h, w), values)
    };
    a.map_err(|e| bad(e.to_string()))
}

/// Reads a 2-D `.npy` of f4 or f8 as f32.
pub fn read_npy_f32(path: impl AsRef<Path>) -> Result<Array2<f32>> {
    Ok(read_npy_f64(path)?.mapv(|x| x as f32))
}

// ---------------------------------------------------------------- JSON Lines

/// One contact as written to (and read from) contacts JSON Lines and `truth.jsonl`.
///
/// `x_mm..fz_n` are in the sensor frame; `x_px, y_px` in the cropped image;
/// `dx, dy, dz` the raw displacements rotated into the sensor frame. Keys that are
/// `None` are left out when writing and may be absent when reading.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ContactRecord {
    /// Stable contact id (tracking), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u64>,
    /// Location along the chord, mm.
    pub x_mm: f64,
    /// Location across the width, mm.
    pub y_mm: f64,
    /// Height on the skin, mm.
    pub z_mm: f64,
    /// Force along x, N.
    pub fx_n: f64,
    /// Force along y, N.
    pub fy_n: f64,
    /// Force along z, N (a press is negative).
    pub fz_n: f64,
    /// Contact point column in the cropped image, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_px: Option<f64>,
    /// Contact point row in the cropped image, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_px: Option<f64>,
    /// Potential spread `max D - min D`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub d_pf: Option<f64>,
    /// Raw displacement along sensor x.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dx: Option<f64>,
    /// Raw displacement along sensor y.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dy: Option<f64>,
    /// Raw displacement along sensor z.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dz: Option<f64>,
    /// Patch area in pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub area_px: Option<u64>,
    /// Whether the force came from the calibration's low-order fallback maps
    /// (`Contact::fallback`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fallback: Option<bool>,
    /// Whether the contact lies outside what the calibration knows
    /// (`Contact::out_of_domain`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub out_of_domain: Option<bool>,
    /// Frames in a row the tracker has held this contact without a
    /// detection (`Contact::missed`): 0 for a contact detected in this
    /// frame; a held contact repeats its last reading (the filter's
    /// prediction when the tracker filters).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub missed: Option<u32>,
    /// Standard deviation of the force error along x, N
    /// (`Contact::force_sigma_n`; absent without a fitted uncertainty).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fx_sigma_n: Option<f64>,
    /// Standard deviation of the force error along y, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fy_sigma_n: Option<f64>,
    /// Standard deviation of the force error along z, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fz_sigma_n: Option<f64>,
}

/// One patch of an uncalibrated (raw) run: where it is in the cropped image
/// and its raw quantities (docs/pipeline.md, step 7), all in full-resolution
/// pixels of the cropped image.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct RawContactRecord {
    /// Contact point column, px.
    pub x_px: f64,
    /// Contact point row, px.
    pub y_px: f64,
    /// The patch's bounding box `[x, y, w, h]`, px.
    pub box_px: [usize; 4],
    /// Detection strength: the patch's summed flow magnitude.
    pub strength: f64,
    /// Shear raw displacement along image x (sum of the flow's u), px.
    pub ds1: f64,
    /// Shear raw displacement along image y (sum of the flow's v), px.
    pub ds2: f64,
    /// Normal raw displacement (sum of the curl-free part's magnitude), px.
    pub dn: f64,
    /// Spread of the divergence potential, `max D - min D`.
    pub d_pf: f64,
    /// Patch area in pixels.
    pub area_px: u64,
}

/// One line of a contacts JSON Lines file: a processed frame and its
/// contacts, calibrated ([`ContactRecord`], the default) or raw
/// ([`RawContactRecord`]), with the same layout.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct FrameRecord<C = ContactRecord> {
    /// Frame name (file name within the sequence, or a path).
    pub frame: String,
    /// Time stamp in seconds.
    pub t_s: f64,
    /// Contacts seen in this frame (empty if none).
    pub contacts: Vec<C>,
    /// Processing time of this frame in ms, if recorded (optional extension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latency_ms: Option<f64>,
}

/// Writes JSON Lines, one record per line, flushed after every line so that
/// nothing already written is lost if the run stops.
pub struct JsonlWriter {
    path: PathBuf,
    out: BufWriter<File>,
}

impl JsonlWriter {
    /// Creates (truncates) the file.
    pub fn create(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let out = create(&path)?;
        Ok(JsonlWriter { path, out })
    }

    /// Appends one record as one line. A record holding a NaN or infinite
    /// number is refused ([`Error::NonFinite`] naming the field; JSON has no
    /// such numbers) and nothing is written.
    pub fn write<T: Serialize>(&mut self, record: &T) -> Result<()> {
        check_finite(record, &self.path)?;
        let line = serde_json::to_string(record)
            .map_err(|e| Error::format(&self.path, None, format!("cannot serialize: {e}")))?;
        writeln!(self.out, "{line}")
            .and_then(|_| self.out.flush())
            .map_err(|e| Error::io(&self.path, e))
    }
}

/// Reads a JSON Lines file (blank lines are skipped); errors name the line.
/// The file must be a regular file of at most [`MAX_JSONL_BYTES`], with
/// lines of at most [`MAX_LINE_BYTES`].
pub fn read_jsonl<T: DeserializeOwned>(path: impl AsRef<Path>) -> Result<Vec<T>> {
    let path = path.as_ref();
    let mut out = Vec::new();
    for_each_line(path, MAX_JSONL_BYTES, |number, line| {
        if !line.trim().is_empty() {
            let rec = serde_json::from_str(line)
                .map_err(|e| Error::format(path, Some(number), e.to_string()))?;
            out.push(rec);
        }
        Ok(())
    })?;
    Ok(out)
}

// ---------------------------------------------------------------- CSV

/// A minimal CSV table: a header and rows of fields (no quoting: the dataset
/// formats contain no commas inside fields).
struct Csv {
    path: PathBuf,
    header: Vec<String>,
    rows: Vec<(usize, Vec<String>)>,
}

impl Csv {
    fn read(path: &Path) -> Result<Csv> {
        let mut header: Option<Vec<String>> = None;
        let mut rows = Vec::new();
        for_each_line(path, MAX_CSV_BYTES, |number, l| {
            if l.trim().is_empty() {
                return Ok(());
            }
            let Some(header) = &header else {
                header = Some(
                    l.trim_start_matches('\u{feff}')
                        .split(',')
                        .map(|s| s.trim().to_string())
                        .collect(),
                );
                return Ok(());
            };
            let fields: Vec<String> = l.split(',').map(|s| s.trim().to_string()).collect();
            if fields.len() != header.len() {
                return Err(Error::format(
                    path,
                    Some(number),
                    format!(
                        "{} fields, but the header has {}",
                        fields.len(),
                        header.len()
                    ),
                ));
            }
            rows.push((number, fields));
            Ok(())
        })?;
        let header =
            header.ok_or_else(|| Error::format(path, None, "empty file: no header line"))?;
        Ok(Csv {
            path: path.to_path_buf(),
            header,
            rows,
        })
    }

    /// Indices of required columns, in the order of `names`.
    fn cols<const N: usize>(&self, names: &[&str; N]) -> Result<[usize; N]> {
        let mut c = [0usize; N];
        for (k, name) in names.iter().enumerate() {
            c[k] = self.col(name)?;
        }
        Ok(c)
    }

    /// Index of a required column.
    fn col(&self, name: &str) -> Result<usize> {
        self.header.iter().position(|h| h == name).ok_or_else(|| {
            Error::format(
                &self.path,
                Some(1),
                format!(
                    "missing column `{name}` (header: {})",
                    self.header.join(",")
                ),
            )
        })
    }

    fn parse<T: std::str::FromStr>(&self, line: usize, row: &[String], col: usize) -> Result<T> {
        row[col].parse().map_err(|_| {
            Error::format(
                &self.path,
                Some(line),
                format!("column `{}`: cannot parse `{}`", self.header[col], row[col]),
            )
        })
    }

    /// A finite number (NaN and infinities are errors naming the column).
    fn finite(&self, line: usize, row: &[String], col: usize) -> Result<f64> {
        let x: f64 = self.parse(line, row, col)?;
        if !x.is_finite() {
            return Err(Error::format(
                &self.path,
                Some(line),
                format!(
                    "column `{}`: `{}` is not a finite number",
                    self.header[col], row[col]
                ),
            ));
        }
        Ok(x)
    }
}

/// Which part of the characterization dataset a test belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Used to fit the polynomials.
    Train,
    /// Used to choose each polynomial's order.
    Val,
    /// Held out; the reported errors.
    Test,
    /// Spot checks: presses at places of their own rather than the
    /// protocol's points, held out like the tests. They say how the maps do
    /// between the points, and the per-contact force uncertainty is fitted
    /// on them when there are enough
    /// ([`crate::calibration::uncertainty`]).
    Spot,
}

impl Split {
    /// The name used in `tests.csv`.
    pub fn as_str(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
            Split::Spot => "spot",
        }
    }
}

impl std::str::FromStr for Split {
    type Err = ();
    fn from_str(s: &str) -> std::result::Result<Self, ()> {
        match s {
            "train" => Ok(Split::Train),
            "val" => Ok(Split::Val),
            "test" => Ok(Split::Test),
            "spot" => Ok(Split::Spot),
            _ => Err(()),
        }
    }
}

/// One row of a characterization dataset's `tests.csv` (docs/formats.md).
#[derive(Debug, Clone, PartialEq)]
pub struct TestRow {
    /// Test number.
    pub test: usize,
    /// Loaded frame, relative to the CSV's directory.
    pub frame: String,
    /// Unloaded reference frame taken just before, relative to the CSV's directory.
    pub reference: String,
    /// Measuring point of the protocol (from 1); 0 for a press at a place
    /// of its own (a spot check or a sweep image).
    pub point: u32,
    /// Indenter (cylinder) diameter, mm.
    pub indenter_mm: f64,
    /// Sensor yaw during the test, degrees (label only).
    pub yaw_deg: f64,
    /// Sensor pitch during the test, degrees (label only).
    pub pitch_deg: f64,
    /// Repetition, from 1.
    pub repeat: u32,
    /// Commanded force magnitude, N.
    pub force_n: f64,
    /// Train / val / test.
    pub split: Split,
    /// True contact location along the chord, mm.
    pub x_mm: f64,
    /// True contact location across, mm.
    pub y_mm: f64,
    /// True force along x, N.
    pub fx_n: f64,
    /// True force along y, N.
    pub fy_n: f64,
    /// True force along z, N.
    pub fz_n: f64,
}

const TEST_COLUMNS: [&str; 15] = [
    "test",
    "frame",
    "reference",
    "point",
    "indenter_mm",
    "yaw_deg",
    "pitch_deg",
    "repeat",
    "force_n",
    "split",
    "x_mm",
    "y_mm",
    "fx_n",
    "fy_n",
    "fz_n",
];

/// Reads a characterization dataset's `tests.csv`. Columns may come in any
/// order and extra columns are ignored; a missing column, an unparsable or
/// non-finite value or an unknown split is an error naming the file and
/// line. The file must be a regular file of at most [`MAX_CSV_BYTES`].
pub fn read_tests_csv(path: impl AsRef<Path>) -> Result<Vec<TestRow>> {
    let csv = Csv::read(path.as_ref())?;
    let c = csv.cols(&TEST_COLUMNS)?;
    let mut out = Vec::with_capacity(csv.rows.len());
    for (line, r) in &csv.rows {
        let line = *line;
        let split = r[c[9]].parse().map_err(|_| {
            Error::format(
                &csv.path,
                Some(line),
                format!(
                    "unknown split `{}` (expected train, val, test or spot)",
                    r[c[9]]
                ),
            )
        })?;
        out.push(TestRow {
            test: csv.parse(line, r, c[0])?,
            frame: r[c[1]].clone(),
            reference: r[c[2]].clone(),
            point: csv.parse(line, r, c[3])?,
            indenter_mm: csv.finite(line, r, c[4])?,
            yaw_deg: csv.finite(line, r, c[5])?,
            pitch_deg: csv.finite(line, r, c[6])?,
            repeat: csv.parse(line, r, c[7])?,
            force_n: csv.finite(line, r, c[8])?,
            split,
            x_mm: csv.finite(line, r, c[10])?,
            y_mm: csv.finite(line, r, c[11])?,
            fx_n: csv.finite(line, r, c[12])?,
            fy_n: csv.finite(line, r, c[13])?,
            fz_n: csv.finite(line, r, c[14])?,
        });
    }
    Ok(out)
}

/// Writes a CSV file: the header of `columns`, then one line per row from
/// `line` (which ends it with a newline).
fn write_csv<T>(
    path: &Path,
    columns: &[&str],
    rows: &[T],
    mut line: impl FnMut(&mut String, &T),
) -> Result<()> {
    let mut s = columns.join(",");
    s.push('\n');
    for r in rows {
        line(&mut s, r);
    }
    std::fs::write(path, s).map_err(|e| Error::io(path, e))
}

/// Writes a characterization dataset's `tests.csv`.
pub fn write_tests_csv(path: impl AsRef<Path>, rows: &[TestRow]) -> Result<()> {
    write_csv(path.as_ref(), &TEST_COLUMNS, rows, |s, r| {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            r.test,
            r.frame,
            r.reference,
            r.point,
            r.indenter_mm,
            r.yaw_deg,
            r.pitch_deg,
            r.repeat,
            r.force_n,
            r.split.as_str(),
            r.x_mm,
            r.y_mm,
            r.fx_n,
            r.fy_n,
            r.fz_n
        );
    })
}

/// One row of a characterization dataset's `sweeps.csv` (docs/formats.md):
/// one image of a sweep, a constant load moved along the skin in small
/// steps, from which `calibrate` learns how the readings vary with the
/// marker pattern under the contact ([`crate::calibration::correction`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SweepRow {
    /// Which sweep the image belongs to (any number; rows of one sweep share it).
    pub sweep: u32,
    /// Loaded frame, relative to the CSV's directory.
    pub frame: String,
    /// Unloaded reference frame, relative to the CSV's directory.
    pub reference: String,
    /// Indenter diameter, mm.
    pub indenter_mm: f64,
    /// Commanded force magnitude, N.
    pub force_n: f64,
    /// True contact location along the chord, mm.
    pub x_mm: f64,
    /// True contact location across, mm.
    pub y_mm: f64,
    /// True force along x, N.
    pub fx_n: f64,
    /// True force along y, N.
    pub fy_n: f64,
    /// True force along z, N.
    pub fz_n: f64,
}

impl SweepRow {
    /// The row as a test of the dataset (point 0, no tilt, `train` split;
    /// `test` is the row's index), so that the pipeline that extracts tests
    /// extracts it.
    pub fn as_test(&self, index: usize) -> TestRow {
        TestRow {
            test: index,
            frame: self.frame.clone(),
            reference: self.reference.clone(),
            point: 0,
            indenter_mm: self.indenter_mm,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
            repeat: self.sweep,
            force_n: self.force_n,
            split: Split::Train,
            x_mm: self.x_mm,
            y_mm: self.y_mm,
            fx_n: self.fx_n,
            fy_n: self.fy_n,
            fz_n: self.fz_n,
        }
    }
}

const SWEEP_COLUMNS: [&str; 10] = [
    "sweep",
    "frame",
    "reference",
    "indenter_mm",
    "force_n",
    "x_mm",
    "y_mm",
    "fx_n",
    "fy_n",
    "fz_n",
];

/// Reads a characterization dataset's `sweeps.csv`, with the rules of
/// [`read_tests_csv`] (columns by name, extra columns ignored, errors
/// naming the file and line, at most [`MAX_CSV_BYTES`]); `force_n` must be
/// positive.
pub fn read_sweeps_csv(path: impl AsRef<Path>) -> Result<Vec<SweepRow>> {
    let csv = Csv::read(path.as_ref())?;
    let c = csv.cols(&SWEEP_COLUMNS)?;
    let mut out = Vec::with_capacity(csv.rows.len());
    for (line, r) in &csv.rows {
        let line = *line;
        let force_n = csv.finite(line, r, c[4])?;
        if force_n <= 0.0 {
            return Err(Error::format(
                &csv.path,
                Some(line),
                format!("column `force_n`: must be > 0, got {force_n}"),
            ));
        }
        out.push(SweepRow {
            sweep: csv.parse(line, r, c[0])?,
            frame: r[c[1]].clone(),
            reference: r[c[2]].clone(),
            indenter_mm: csv.finite(line, r, c[3])?,
            force_n,
            x_mm: csv.finite(line, r, c[5])?,
            y_mm: csv.finite(line, r, c[6])?,
            fx_n: csv.finite(line, r, c[7])?,
            fy_n: csv.finite(line, r, c[8])?,
            fz_n: csv.finite(line, r, c[9])?,
        });
    }
    Ok(out)
}

/// Writes a characterization dataset's `sweeps.csv`.
pub fn write_sweeps_csv(path: impl AsRef<Path>, rows: &[SweepRow]) -> Result<()> {
    write_csv(path.as_ref(), &SWEEP_COLUMNS, rows, |s, r| {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{}",
            r.sweep,
            r.frame,
            r.reference,
            r.indenter_mm,
            r.force_n,
            r.x_mm,
            r.y_mm,
            r.fx_n,
            r.fy_n,
            r.fz_n
        );
    })
}

/// One row of `poses.csv`: the body pose in the world frame at a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseRow {
    /// Frame file name.
    pub frame: String,
    /// Time stamp, s.
    pub t_s: f64,
    /// Position x, m.
    pub x_m: f64,
    /// Position y, m.
    pub y_m: f64,
    /// Position z, m.
    pub z_m: f64,
    /// Orientation quaternion, scalar part.
    pub qw: f64,
    /// Orientation quaternion, x.
    pub qx: f64,
    /// Orientation quaternion, y.
    pub qy: f64,
    /// Orientation quaternion, z.
    pub qz: f64,
}

const POSE_COLUMNS: [&str; 9] = ["frame", "t_s", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"];

/// Reads `poses.csv` (docs/formats.md); errors name the file and line. Every
/// number must be finite (a NaN time is an error).
pub fn read_poses_csv(path: impl AsRef<Path>) -> Result<Vec<PoseRow>> {
    let csv = Csv::read(path.as_ref())?;
    let c = csv.cols(&POSE_COLUMNS)?;
    csv.rows
        .iter()
        .map(|(line, r)| {
            let f = |k: usize| csv.finite(*line, r, c[k]);
            Ok(PoseRow {
                frame: r[c[0]].clone(),
                t_s: f(1)?,
                x_m: f(2)?,
                y_m: f(3)?,
                z_m: f(4)?,
                qw: f(5)?,
                qx: f(6)?,
                qy: f(7)?,
                qz: f(8)?,
            })
        })
        .collect()
}

/// Writes `poses.csv`.
pub fn write_poses_csv(path: impl AsRef<Path>, rows: &[PoseRow]) -> Result<()> {
    write_csv(path.as_ref(), &POSE_COLUMNS, rows, |s, r| {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{}",
            r.frame, r.t_s, r.x_m, r.y_m, r.z_m, r.qw, r.qx, r.qy, r.qz
        );
    })
}
