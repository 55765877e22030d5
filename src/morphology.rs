//! Binary threshold, erosion and dilation with structuring elements.
