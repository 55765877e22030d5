//! Free-space Green's convolution by zero-padded FFT.
