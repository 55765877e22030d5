//! Helpers shared by the integration tests of the whole sensor.

use optical_tactile::calibration::poly::Polynomial;
use optical_tactile::calibration::{Calibration, PipelineSettings, SensorSetup};
use optical_tactile::frame::Roi;
use optical_tactile::geometry::SensorGeometry;
use optical_tactile::segment::{Shape, Thresholds};

/// A hand-made calibration: x = (x_px - 799.5) / 5 mm, y = 0, F = 1e-4 * D,
/// recorded with thresholds 0.2 px / 600 and the given pipeline settings.
pub fn linear_calibration(crop: Roi, pipeline: Option<PipelineSettings>) -> Calibration {
    let g1 = Polynomial::raw(&["x2d"], vec![vec![0], vec![1]], vec![-799.5 / 5.0, 0.2]).unwrap();
    let g2 = Polynomial::raw(&["y2d"], vec![vec![0]], vec![0.0]).unwrap();
    let vars = ["dx", "dy", "dz", "x2d", "y2d", "d_pf"];
    let lin = |k: usize| {
        let mut e = vec![0u32; 6];
        e[k] = 1;
        Polynomial::raw(&vars, vec![e], vec![1e-4]).unwrap()
    };
    let setup = SensorSetup {
        geometry: SensorGeometry::default(),
        crop,
        thresholds: Thresholds {
            magnitude: 0.2,
            sum: 600.0,
            erode: 5,
            dilate: 15,
            shape: Shape::Rect,
        },
        pipeline,
    };
    Calibration::new(setup, [g1, g2, lin(0), lin(1), lin(2)], None).unwrap()
}
