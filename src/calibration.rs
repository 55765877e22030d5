//! Calibration: the fitted maps from raw contact quantities to millimetres and newtons.
