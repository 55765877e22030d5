//! Regions of interest, channel selection and conversion to f32 grayscale.
