//! External contours by border following, and bounding boxes.
