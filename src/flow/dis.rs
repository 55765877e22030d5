//! Dense Inverse Search (Kroeger et al. 2016) optical flow.
