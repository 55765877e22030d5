//! Natural Helmholtz-Hodge decomposition (Bhatia et al. 2014) of a flow patch.

pub mod direct;
pub mod fft;
