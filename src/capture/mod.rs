//! Where frames come from: a [`FrameSource`] trait, an image-sequence source
//! ([`SequenceSource`]) and, behind the `v4l` feature, a V4L2 camera.
//!
//! A source yields grayscale frames (green channel or luma, f32 on the 8-bit
//! scale) at their full size; cropping to the sensing area is the sensor's job.
//!
//! A [`SequenceSource`] is also an [`Iterator`] over `Result<Frame>`:
//!
//! ```no_run
//! use optical_tactile::capture::SequenceSource;
//! for frame in SequenceSource::open("fixtures/press")? {
//!     match frame {
//!         Ok(f) => println!("{} at {:.3} s: {:?}", f.name, f.t_s, f.image.dim()),
//!         // An unreadable frame is named; the sequence goes on with the next one.
//!         Err(e) => eprintln!("skipped: {e}"),
//!     }
//! }
//! # Ok::<(), optical_tactile::Error>(())
//! ```

mod sequence;
#[cfg(feature = "v4l")]
#[cfg_attr(docsrs, doc(cfg(feature = "v4l")))]
pub mod v4l;

use ndarray::Array2;

use crate::error::Result;

pub use sequence::SequenceSource;

/// One grayscale frame with its name and time stamp.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Grayscale image, shape `(height, width)`, 8-bit scale.
    pub image: Array2<f32>,
    /// A name for the frame: the file name in a sequence, the sequence number
    /// for a camera.
    pub name: String,
    /// Position in the stream, from 0.
    pub index: usize,
    /// Time stamp in seconds (from `poses.csv`, the frame rate, or the camera clock).
    pub t_s: f64,
}

/// A stream of frames.
///
/// `next_frame` returns `None` at the end of the stream, `Some(Err(..))` when
/// one frame could not be had. Whether the stream can go on after an error is
/// the source's to document: a [`SequenceSource`] skips to the next file, a
/// camera that has vanished keeps returning errors.
pub trait FrameSource {
    /// The next frame, an error for this frame, or `None` at the end.
    fn next_frame(&mut self) -> Option<Result<Frame>>;

    /// How many frames remain, if known.
    fn remaining(&self) -> Option<usize> {
        None
    }
}
