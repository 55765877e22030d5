//! Cutting a flow into contact patches.
