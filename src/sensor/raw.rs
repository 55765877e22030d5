//! The pipeline without a calibration: a crop and a [`ContactExtractor`],
//! patches in pixels.

use ndarray::{Array2, ArrayRef2};

use super::{ContactExtractor, ExtractorConfig};
use crate::contact::{ContactPointMethod, RawContact};
use crate::error::Result;
use crate::frame::Roi;
use crate::viz::{self, Canvas};

/// Raw patches of whole camera frames, without a calibration: the frame is
/// cropped (to a given region, or not at all), the extractor runs on the
/// crop, and every patch's contact point is measured by
/// [`ContactPointMethod::uncalibrated`]: the column as the strip's
/// calibration measures it by default, or, where the dots of a regular grid
/// are followed, both coordinates where the dots' motion lines meet.
///
/// What [`TactileSensor`](super::TactileSensor) is to a calibrated sensor,
/// for bringing up a sensor that has no calibration yet: the patches carry
/// their contact point and box in pixels and their raw displacements, no
/// millimetre or newton, no tracking.
///
/// ```
/// use optical_tactile::capture::SequenceSource;
/// use optical_tactile::sensor::{ExtractorConfig, RawSensor};
///
/// let mut sensor = RawSensor::new(ExtractorConfig::default(), None)?;
/// let mut frames = SequenceSource::open("fixtures/press")?;
/// sensor.set_reference(&frames.next().expect("a first frame")?.image)?;
/// for frame in frames {
///     for p in sensor.process(&frame?.image)? {
///         println!("patch at ({:.0}, {:.0}) px, strength {:.0}", p.x_px, p.y_px, p.strength);
///     }
/// }
/// # Ok::<(), optical_tactile::Error>(())
/// ```
#[derive(Debug)]
pub struct RawSensor {
    extractor: ContactExtractor,
    crop: Option<Roi>,
    cropped: Array2<f32>,
}

impl RawSensor {
    /// A raw sensor with the extractor `config` (checked here) on `crop` of
    /// every frame, or on the whole frame with `None`.
    pub fn new(config: ExtractorConfig, crop: Option<Roi>) -> Result<Self> {
        Ok(RawSensor {
            extractor: ContactExtractor::new(config)?,
            crop,
            cropped: Array2::zeros((0, 0)),
        })
    }

    /// Takes a whole camera frame as the reference (unloaded). Errors if the
    /// crop does not fit in the frame or the frame is empty or not finite.
    pub fn set_reference(&mut self, frame: &ArrayRef2<f32>) -> Result<()> {
        self.crop_from(frame)?;
        self.extractor.set_reference(&self.cropped)
    }

    /// The patches of a whole camera frame, strongest first. Errors without
    /// a reference, or if the frame is not the reference's size.
    pub fn process(&mut self, frame: &ArrayRef2<f32>) -> Result<&[RawContact]> {
        self.crop_from(frame)?;
        self.extractor.extract(&self.cropped)?;
        let method = ContactPointMethod::uncalibrated(self.extractor.follows_dots());
        self.extractor.locate(method)
    }

    /// The crop, `None` for the whole frame.
    pub fn crop(&self) -> Option<Roi> {
        self.crop
    }

    /// The extractor (configuration, flow, patches and timings of the last frame).
    pub fn extractor(&self) -> &ContactExtractor {
        &self.extractor
    }

    /// The cropped grayscale image of the last frame.
    pub fn cropped(&self) -> &Array2<f32> {
        &self.cropped
    }

    /// The debug panel of the last frame ([`viz::raw_debug_panel`]).
    pub fn debug_panel(&self) -> Canvas {
        viz::raw_debug_panel(&self.extractor, &self.cropped)
    }

    fn crop_from(&mut self, frame: &ArrayRef2<f32>) -> Result<()> {
        let crop = self
            .crop
            .unwrap_or_else(|| Roi::full(frame.ncols(), frame.nrows()));
        let view = crop.crop(frame)?;
        if self.cropped.dim() == view.dim() {
            self.cropped.assign(&view);
        } else {
            self.cropped = view.to_owned();
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::SequenceSource;
    use crate::error::Error;

    fn press() -> Vec<Array2<f32>> {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/press");
        SequenceSource::open(dir)
            .unwrap()
            .map(|f| f.unwrap().image)
            .collect()
    }

    #[test]
    fn finds_the_patches_the_extractor_finds_on_the_crop() {
        let frames = press();
        let crop = Roi::new(10, 5, frames[0].ncols() - 20, frames[0].nrows() - 10);
        let config = ExtractorConfig::default();
        let mut raw = RawSensor::new(config.clone(), Some(crop)).unwrap();
        let mut extractor = ContactExtractor::new(config).unwrap();
        raw.set_reference(&frames[0]).unwrap();
        extractor
            .set_reference(&crop.crop(&frames[0]).unwrap())
            .unwrap();
        let mut seen = 0;
        for f in &frames[1..] {
            let got = raw.process(f).unwrap().to_vec();
            extractor.extract(&crop.crop(f).unwrap()).unwrap();
            let want = extractor.locate(ContactPointMethod::DEFAULT).unwrap();
            assert_eq!(got, want);
            assert_eq!(raw.cropped().dim(), (crop.h, crop.w));
            seen += got.len();
        }
        assert!(seen > 0, "the press has patches");
    }

    #[test]
    fn refuses_a_crop_outside_the_frame_and_a_frame_of_another_size() {
        let frames = press();
        let (w, h) = (frames[0].ncols(), frames[0].nrows());
        let mut outside =
            RawSensor::new(ExtractorConfig::default(), Some(Roi::new(w, 0, 10, 10))).unwrap();
        assert!(outside.set_reference(&frames[0]).is_err());

        let mut whole = RawSensor::new(ExtractorConfig::default(), None).unwrap();
        assert!(matches!(whole.process(&frames[0]), Err(Error::NoReference)));
        whole.set_reference(&frames[0]).unwrap();
        let small = Array2::<f32>::zeros((h / 2, w / 2));
        assert!(whole.process(&small).is_err());
        // The sensor goes on with frames of the right size.
        assert!(whole.process(&frames[1]).is_ok());
    }
}
