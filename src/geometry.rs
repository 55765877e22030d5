//! Sensor geometry: the curved skin, local surface frames, rotations.
