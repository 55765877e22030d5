//! A contact's point from the followed dots: where the lines along their
//! motion meet.
//!
//! A normal press spreads the gel outward from the load: each dot near it
//! moves along the line from the contact point through the dot, whatever
//! the load's profile. So the point nearest every such line (least
//! squares, each line weighted by its dot's squared motion) is the contact
//! point, read from the directions of the few dots that moved, not from
//! their interpolation between the dots. On a grid whose pitch is about the
//! size of a light contact only the four dots around it move; the slope
//! peak of the flow between them falls towards a row of dots, while the
//! lines meet where the load is.
//!
//! A tangential load adds motion common to the dots under the contact,
//! which tilts every line the same way; the mean motion of the contact's
//! region (its box) is taken out first. What remains of the shear's pull
//! is the location maps' to take out, through their shear input, as with
//! any contact point.
//!
//! Measured on the simulated fingertip sensor and a second one with a
//! denser grid (docs/results.md, "A flat fingertip sensor").

use crate::frame::Roi;

/// A dot's line counts when its motion, less the region's mean, reaches
/// this fraction of the region's largest motion: the dots at rest have no
/// direction to give.
pub const LINE_FRACTION: f64 = 0.2;

/// The lines must cross, not run side by side: the smaller eigenvalue of
/// their normal equations must reach this fraction of the larger.
pub const MIN_SPREAD_OF_DIRECTIONS: f64 = 0.01;

/// The point where the lines along the dots' motion meet, for one contact
/// of several.
///
/// `dots` are the dots' reference centres and `moved` their motion (`None`:
/// lost), as [`crate::markers::DotTracker`] gives them, in full-resolution
/// pixels. `starts` holds every contact's current point (such as the slope
/// peak) and `k` says which is this one: its dots are those inside
/// `region` (its box) that lie nearer to `starts[k]` than to any other
/// contact's point. The answer is `None`, and the current point stands,
/// when fewer than two such dots moved, when their lines run nearly
/// parallel ([`MIN_SPREAD_OF_DIRECTIONS`]), or when the lines meet farther
/// than `reach_px` from `starts[k]`. `k` out of range or a non-finite input
/// also give `None`.
pub fn motion_centre(
    dots: &[[f64; 2]],
    moved: &[Option<[f64; 2]>],
    region: Roi,
    starts: &[[f64; 2]],
    k: usize,
    reach_px: f64,
) -> Option<[f64; 2]> {
    let start = *starts.get(k)?;
    if !(start[0].is_finite() && start[1].is_finite() && reach_px.is_finite()) {
        return None;
    }
    let own = |p: &[f64; 2]| {
        let d = dist2(*p, start);
        starts
            .iter()
            .enumerate()
            .all(|(j, o)| j == k || d <= dist2(*p, *o))
    };
    let selected = || {
        dots.iter().zip(moved).filter_map(move |(p, m)| {
            let m = (*m)?;
            (region.holds(*p) && m[0].is_finite() && m[1].is_finite() && own(p)).then_some((*p, m))
        })
    };
    // The region's mean motion and its largest.
    let (mut n, mut mean, mut largest) = (0usize, [0.0, 0.0], 0.0f64);
    for (_, m) in selected() {
        n += 1;
        mean[0] += m[0];
        mean[1] += m[1];
        largest = largest.max(m[0].hypot(m[1]));
    }
    if n == 0 || largest <= 0.0 {
        return None;
    }
    let mean = [mean[0] / n as f64, mean[1] / n as f64];
    // Normal equations of sum w (q . (c - p))^2, q the unit normal of a
    // dot's line: [a b; b c] c = [d; e].
    let (mut a, mut b, mut c, mut d, mut e, mut lines) = (0.0, 0.0, 0.0, 0.0, 0.0, 0);
    for (p, m) in selected() {
        let r = [m[0] - mean[0], m[1] - mean[1]];
        let len = r[0].hypot(r[1]);
        if len < LINE_FRACTION * largest {
            continue;
        }
        let w = len * len;
        let q = [-r[1] / len, r[0] / len];
        let qp = q[0] * p[0] + q[1] * p[1];
        a += w * q[0] * q[0];
        b += w * q[0] * q[1];
        c += w * q[1] * q[1];
        d += w * q[0] * qp;
        e += w * q[1] * qp;
        lines += 1;
    }
    if lines < 2 {
        return None;
    }
    // Eigenvalues of the symmetric 2 x 2 matrix.
    let (half_trace, gap) = (0.5 * (a + c), (0.25 * (a - c) * (a - c) + b * b).sqrt());
    let (small, large) = (half_trace - gap, half_trace + gap);
    if !(large > 0.0 && small >= MIN_SPREAD_OF_DIRECTIONS * large) {
        return None;
    }
    let det = a * c - b * b;
    let point = [(c * d - b * e) / det, (a * e - b * d) / det];
    let near = dist2(point, start).sqrt() <= reach_px;
    (point[0].is_finite() && point[1].is_finite() && near).then_some(point)
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

#[cfg(test)]
mod tests;
