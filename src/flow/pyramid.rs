//! Area-averaged image pyramids and gradients.
