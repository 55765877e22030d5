//! Variational refinement of a flow field (brightness + gradient constancy + smoothness).
