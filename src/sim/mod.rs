//! Physics-based synthetic tactile sensor: elastic layer, markers, rendering, scenarios.
