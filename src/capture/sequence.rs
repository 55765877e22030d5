//! An ordered directory of PNG frames (docs/formats.md, "Image sequence").

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::{Frame, FrameSource};
use crate::error::{Error, Result};
use crate::frame::Channel;
use crate::io;

/// Frames read one by one from a directory of PNG files in lexicographic order.
///
/// Time stamps come from `poses.csv` beside the frames when it names the frame,
/// otherwise from the frame index divided by the frame rate (50 Hz unless set).
/// An unreadable frame yields an error naming the file, and the sequence goes
/// on with the next file.
#[derive(Debug)]
pub struct SequenceSource {
    frames: Vec<PathBuf>,
    next: usize,
    channel: Channel,
    fps: f64,
    times: HashMap<String, f64>,
}

impl SequenceSource {
    /// Opens a sequence directory (errors if it holds no PNG frame, or if a
    /// `poses.csv` beside the frames is malformed).
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        let frames = io::list_frames(dir)?;
        let poses = dir.join("poses.csv");
        let times = if poses.is_file() {
            io::read_poses_csv(&poses)?
                .into_iter()
                .map(|p| (p.frame, p.t_s))
                .collect()
        } else {
            HashMap::new()
        };
        Ok(SequenceSource {
            frames,
            next: 0,
            channel: Channel::Green,
            fps: 50.0,
            times,
        })
    }

    /// Which channel of colour frames to use (default: green).
    pub fn with_channel(mut self, channel: Channel) -> Self {
        self.channel = channel;
        self
    }

    /// Frame rate used for time stamps of frames not in `poses.csv` (default 50).
    pub fn with_fps(mut self, fps: f64) -> Result<Self> {
        if !(fps.is_finite() && fps > 0.0) {
            return Err(Error::param("fps", format!("must be > 0, got {fps}")));
        }
        self.fps = fps;
        Ok(self)
    }

    /// The frame files, in order.
    pub fn paths(&self) -> &[PathBuf] {
        &self.frames
    }

    /// Total number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frame (never true for an opened sequence).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

impl FrameSource for SequenceSource {
    fn next_frame(&mut self) -> Option<Result<Frame>> {
        let path = self.frames.get(self.next)?;
        let index = self.next;
        self.next += 1;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let t_s = self
            .times
            .get(&name)
            .copied()
            .unwrap_or(index as f64 / self.fps);
        Some(
            io::read_gray_channel(path, self.channel).map(|image| Frame {
                image,
                name,
                index,
                t_s,
            }),
        )
    }

    fn remaining(&self) -> Option<usize> {
        Some(self.frames.len() - self.next)
    }
}

/// The frames in order; an unreadable frame is an `Err` and the iteration
/// goes on with the next file.
impl Iterator for SequenceSource {
    type Item = Result<Frame>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_frame()
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = self.frames.len() - self.next;
        (n, Some(n))
    }
}
