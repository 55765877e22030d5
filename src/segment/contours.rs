//! External contours by border following, and bounding boxes.
//!
//! [`ContourFinder`] traces the **outer borders of the outermost regions**
//! of a [`Mask`], like OpenCV's `findContours(RETR_EXTERNAL)`: foreground is
//! 8-connected (background 4-connected); holes are not traced, and anything
//! inside a hole (an island) is ignored, because a contact cannot lie inside
//! another contact. So each external contour's bounding box is the bounding box
//! of one 8-connected component with its holes filled.
//!
//! ## Algorithm
//! Suzuki and Abe (1985), "Topological structural analysis of digitized binary
//! images by border following", algorithm 1 restricted to outer borders as
//! OpenCV does for `RETR_EXTERNAL`: a raster scan starts a border at an
//! unlabelled foreground pixel whose left neighbour is background, unless the
//! last labelled pixel passed on this row says the scan is inside a traced
//! region. Border pixels are labelled `-1` when the pixel to their right is a
//! background pixel examined while following (the scan leaves the region
//! there) and `+1` otherwise (the scan is inside).
//!
//! The scan only visits *edge* pixels (foreground with a background
//! 8-neighbour), found 64 at a time from the packed mask, and the labels it
//! writes are cleared again from the list of traced pixels, so the cost is
//! `O(words + border length)`, not `O(pixels)`.

use crate::segment::morphology::Mask;

/// An axis-aligned box of pixels: columns `x .. x + width`, rows `y .. y + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct BoundingBox {
    /// Left column.
    pub x: usize,
    /// Top row.
    pub y: usize,
    /// Width in pixels (>= 1 for a box from a contour).
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
}

impl BoundingBox {
    /// Box from its left column, top row, width and height.
    pub const fn new(x: usize, y: usize, width: usize, height: usize) -> Self {
        BoundingBox {
            x,
            y,
            width,
            height,
        }
    }

    /// One past the right column.
    pub fn x_end(&self) -> usize {
        self.x + self.width
    }

    /// One past the bottom row.
    pub fn y_end(&self) -> usize {
        self.y + self.height
    }

    /// Number of pixels `width * height`.
    pub fn area(&self) -> usize {
        self.width * self.height
    }

    /// Whether the boxes share at least one pixel.
    pub fn intersects(&self, other: &BoundingBox) -> bool {
        self.x < other.x_end()
            && other.x < self.x_end()
            && self.y < other.y_end()
            && other.y < self.y_end()
    }

    /// The smallest box holding both.
    pub fn union(&self, other: &BoundingBox) -> BoundingBox {
        let (x, y) = (self.x.min(other.x), self.y.min(other.y));
        let (xe, ye) = (
            self.x_end().max(other.x_end()),
            self.y_end().max(other.y_end()),
        );
        BoundingBox::new(x, y, xe - x, ye - y)
    }

    /// Grown by `margin` pixels on every side, clamped to a
    /// `width x height` image.
    pub fn expand(&self, margin: usize, width: usize, height: usize) -> BoundingBox {
        let (x, y) = (self.x.saturating_sub(margin), self.y.saturating_sub(margin));
        let xe = (self.x_end() + margin).min(width);
        let ye = (self.y_end() + margin).min(height);
        BoundingBox::new(x, y, xe.saturating_sub(x), ye.saturating_sub(y))
    }

    /// Whether pixel `(x, y)` lies in the box.
    pub fn contains(&self, x: usize, y: usize) -> bool {
        x >= self.x && x < self.x_end() && y >= self.y && y < self.y_end()
    }
}

/// One external contour: its border pixels in tracing order and their box.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Contour {
    /// Border pixels `(x, y)` in the order followed (counter-clockwise on
    /// screen, starting at the top-left pixel; a pixel may appear more than
    /// once where the region is one pixel thin).
    pub points: Vec<(usize, usize)>,
    /// Bounding box of the points.
    pub bbox: BoundingBox,
}

// Neighbour directions, counter-clockwise on screen (y points down):
// E, NE, N, NW, W, SW, S, SE.
const DX: [i64; 8] = [1, 1, 0, -1, -1, -1, 0, 1];
const DY: [i64; 8] = [0, -1, -1, -1, 0, 1, 1, 1];
const WEST: usize = 4;
const EAST: usize = 0;

/// Reusable external-contour tracer (keeps its label image and point buffer).
#[derive(Debug, Default, Clone)]
pub struct ContourFinder {
    /// Per-pixel label: 0 untraced, +1 / -1 traced (see the module docs).
    /// All zero between calls.
    labels: Vec<i8>,
    size: (usize, usize),
    /// Flat indices of every traced pixel of the current call (to clear labels).
    touched: Vec<usize>,
}

impl ContourFinder {
    /// A finder with empty buffers (they grow on first use).
    pub fn new() -> Self {
        Self::default()
    }

    /// The bounding boxes of the external contours of `mask`, in raster order
    /// of their top-left pixel, written into `out` (cleared first).
    pub fn external_boxes(&mut self, mask: &Mask, out: &mut Vec<BoundingBox>) {
        out.clear();
        self.scan(mask, |bbox, _| out.push(bbox));
    }

    /// The external contours of `mask` with their points, in raster order of
    /// their top-left pixel.
    pub fn external_contours(&mut self, mask: &Mask) -> Vec<Contour> {
        let w = mask.width();
        let mut out = Vec::new();
        self.scan(mask, |bbox, pts| {
            out.push(Contour {
                points: pts.iter().map(|&i| (i % w, i / w)).collect(),
                bbox,
            })
        });
        out
    }

    fn scan(&mut self, mask: &Mask, mut emit: impl FnMut(BoundingBox, &[usize])) {
        let (w, h) = mask.size();
        if self.size != (w, h) {
            self.labels.clear();
            self.labels.resize(w * h, 0);
            self.size = (w, h);
        }
        self.touched.clear();
        let wds = mask.words_per_row();
        for y in 0..h {
            let row = mask.row(y);
            let up = (y > 0).then(|| mask.row(y - 1));
            let dn = (y + 1 < h).then(|| mask.row(y + 1));
            let vert = |k: usize| -> u64 {
                if k >= wds {
                    return 0;
                }
                row[k] & up.map_or(0, |r| r[k]) & dn.map_or(0, |r| r[k])
            };
            // Label state of the last labelled pixel passed on this row.
            let mut inside = false;
            for k in 0..wds {
                let m = row[k];
                if m == 0 {
                    continue;
                }
                // Interior = foreground whose 8 neighbours are all foreground
                // (outside the image counts as background).
                let v = vert(k);
                let vl = (v << 1) | if k > 0 { vert(k - 1) >> 63 } else { 0 };
                let vr = (v >> 1) | (vert(k + 1) << 63);
                let mut edge = m & !(v & vl & vr);
                while edge != 0 {
                    let x = k * 64 + edge.trailing_zeros() as usize;
                    edge &= edge - 1;
                    let idx = y * w + x;
                    if self.labels[idx] == 0 && !inside && (x == 0 || !mask.get(x - 1, y)) {
                        let start = self.touched.len();
                        let bbox = self.follow(mask, x, y);
                        emit(bbox, &self.touched[start..]);
                    }
                    match self.labels[idx] {
                        0 => {}
                        l => inside = l > 0,
                    }
                }
            }
        }
        for &i in &self.touched {
            self.labels[i] = 0;
        }
    }

    /// Follows the outer border that starts at `(x0, y0)` (its left neighbour
    /// is background), labelling it; returns its bounding box.
    fn follow(&mut self, mask: &Mask, x0: usize, y0: usize) -> BoundingBox {
        let w = mask.width();
        let fg = |x: i64, y: i64| x >= 0 && y >= 0 && mask.get(x as usize, y as usize);
        let (sx, sy) = (x0 as i64, y0 as i64);
        let (mut xmin, mut xmax, mut ymin, mut ymax) = (sx, sx, sy, sy);
        // 3.1: clockwise from the west neighbour, the first foreground pixel.
        let first = (0..8)
            .map(|k| (WEST + 8 - k) % 8)
            .find(|&d| fg(sx + DX[d], sy + DY[d]));
        let Some(d1) = first else {
            // An isolated pixel.
            let idx = y0 * w + x0;
            self.labels[idx] = -1;
            self.touched.push(idx);
            return BoundingBox::new(x0, y0, 1, 1);
        };
        let (x1, y1) = (sx + DX[d1], sy + DY[d1]);
        // 3.2: (x3, y3) the current pixel, d2 the direction to the previous one.
        let (mut x3, mut y3, mut d2) = (sx, sy, d1);
        loop {
            // 3.3: counter-clockwise from just after the previous pixel.
            let mut east_zero = false;
            let mut d4 = d2;
            for k in 1..=8 {
                let d = (d2 + k) % 8;
                if fg(x3 + DX[d], y3 + DY[d]) {
                    d4 = d;
                    break;
                }
                if d == EAST {
                    east_zero = true;
                }
            }
            // 3.4: label the current pixel.
            let idx = y3 as usize * w + x3 as usize;
            if east_zero {
                self.labels[idx] = -1;
            } else if self.labels[idx] == 0 {
                self.labels[idx] = 1;
            }
            self.touched.push(idx);
            xmin = xmin.min(x3);
            xmax = xmax.max(x3);
            ymin = ymin.min(y3);
            ymax = ymax.max(y3);
            let (x4, y4) = (x3 + DX[d4], y3 + DY[d4]);
            // 3.5: back at the start, about to repeat the first step.
            if (x4, y4) == (sx, sy) && (x3, y3) == (x1, y1) {
                break;
            }
            d2 = (d4 + 4) % 8;
            x3 = x4;
            y3 = y4;
        }
        BoundingBox::new(
            xmin as usize,
            ymin as usize,
            (xmax - xmin + 1) as usize,
            (ymax - ymin + 1) as usize,
        )
    }
}

/// The boxes of `mask`'s external contours (allocating convenience).
pub fn external_boxes(mask: &Mask) -> Vec<BoundingBox> {
    let mut out = Vec::new();
    ContourFinder::new().external_boxes(mask, &mut out);
    out
}

/// The external contours of `mask` with their points (allocating convenience).
pub fn external_contours(mask: &Mask) -> Vec<Contour> {
    ContourFinder::new().external_contours(mask)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(rows: &[&str]) -> Mask {
        let h = rows.len();
        let w = rows[0].len();
        Mask::from_fn(w, h, |x, y| rows[y].as_bytes()[x] == b'#')
    }

    #[test]
    fn a_square_traced_counter_clockwise() {
        let m = mask(&["....", ".##.", ".##.", "...."]);
        let c = external_contours(&m);
        assert_eq!(c.len(), 1);
        assert_eq!(c[0].points, vec![(1, 1), (1, 2), (2, 2), (2, 1)]);
        assert_eq!(c[0].bbox, BoundingBox::new(1, 1, 2, 2));
    }

    #[test]
    fn island_in_a_hole_is_ignored_but_a_neighbour_is_not() {
        let m = mask(&[
            "#######....",
            "#.....#...#",
            "#.###.#....",
            "#.#.#.#.##.",
            "#.###.#.##.",
            "#.....#....",
            "#######....",
        ]);
        let b = external_boxes(&m);
        assert_eq!(
            b,
            vec![
                BoundingBox::new(0, 0, 7, 7),
                BoundingBox::new(10, 1, 1, 1),
                BoundingBox::new(8, 3, 2, 2)
            ]
        );
    }

    #[test]
    fn diagonal_pixels_are_one_region() {
        let m = mask(&["#..", ".#.", "..#"]);
        assert_eq!(external_boxes(&m), vec![BoundingBox::new(0, 0, 3, 3)]);
        let empty = Mask::new(5, 4);
        assert!(external_boxes(&empty).is_empty());
        assert!(external_boxes(&Mask::new(0, 0)).is_empty());
    }

    #[test]
    fn box_helpers() {
        let a = BoundingBox::new(2, 3, 4, 5);
        assert_eq!(a.expand(3, 8, 9), BoundingBox::new(0, 0, 8, 9));
        assert_eq!(a.expand(1, 100, 100), BoundingBox::new(1, 2, 6, 7));
        let b = BoundingBox::new(6, 3, 1, 1);
        assert!(!a.intersects(&b));
        assert!(a.intersects(&BoundingBox::new(5, 7, 1, 1)));
        assert_eq!(a.union(&b), BoundingBox::new(2, 3, 5, 5));
        assert!(a.contains(5, 7) && !a.contains(6, 7));
    }
}
