//! A round contact's motion, fitted to the followed dots about it.
//!
//! A regular grid samples the gel's motion only at its dots, one pitch
//! apart. Under a round contact of a few pitches the motion has two parts:
//! the gel squeezed outward from under the load (a radial field, odd about
//! the contact's centre, whose sum over a symmetric region is nought) and
//! the shear (a field along the tangential load, even about the centre).
//! Summed over the dots, the radial part does not cancel unless the contact
//! sits symmetrically among them: with the contact moved by a fraction of a
//! pitch the sum of the dots' motion swings by tens of percent (on the
//! simulated fingertip sensor, a 5 mm sphere pressed with 2 N and sheared
//! by 0.72 N: from 0.6 to 1.3 times its mean over one pitch), and the shear
//! read from it swings with it.
//!
//! [`fit_round_field`] fits the dots' motion with the field of a round load
//! of unknown centre `c`, radius `a` and profile `S`:
//! `u(x) = alpha grad S(x - c) + beta S(x - c)`, the radial squeeze along
//! the profile's gradient and the shear `beta` with the profile's shape.
//! The profile is one of a few bell shapes ([`Profile`]), `(1 - r^2/a^2)^n`
//! for `n` from 2 to 4 in steps of a half and a Gaussian, the one that
//! fits best; `alpha` and
//! `beta` are linear (least squares), `c` and `a` found by a compass
//! search. The shear's integral `beta * integral(S)` does not depend on
//! where the contact sits against the dots, as the gradient part
//! integrates to nought by construction.
//!
//! Measured on the simulated fingertip sensor (a press moved across one
//! pitch in steps of a tenth of a millimetre, docs/results.md): the fitted
//! shear of a 5 mm sphere, an 8 mm punch and an 18 mm fingertip varies by
//! about 1% (standard deviation over mean) where the patch's sum varies by
//! 22%, 5% and 5%, and the three read the same shear within 0.4%. On
//! fields smoother than a grid's pitch (a thicker gel's motion fading
//! beyond the contact: the simulator's fields blurred by 0.5-1 pitch) the
//! sum is already steady, and so is the fit, within 1-4% of the sum.

/// Radius, in pitches, of the dots the fit reads about the contact's
/// starting point.
pub const WINDOW_OF_PITCH: f64 = 4.5;

/// Fewest dots with a motion the fit takes.
pub const MIN_DOTS: usize = 12;

/// Largest residual the fit accepts, as a fraction of the dots' motion
/// (root of the squared residuals over the root of the squared motions).
pub const MAX_RESIDUAL: f64 = 0.5;

/// A fit whose shear or normal exceeds this many times the dots' summed
/// motion (over a pitch's square each, and for the normal weighted by half
/// the distance from the centre) does not hold: no field explains motion by
/// more motion than the dots show.
const MAX_OF_SUMS: f64 = 2.0;

/// Radii the search covers, in pitches.
const RADIUS_RANGE: (f64, f64) = (0.4, 5.0);

/// How far, in pitches, the fitted centre may lie from the starting point.
const MAX_CENTRE_SHIFT: f64 = 1.5;

/// Radii (in pitches) tried before the compass search refines the best.
const START_RADII: [f64; 9] = [0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 2.5, 3.0, 3.6];

/// The compass search stops when its centre step falls below this (px).
const MIN_STEP_PX: f64 = 0.01;

/// Most evaluations of the compass search per profile.
const MAX_EVALUATIONS: usize = 300;

/// A profile `S(r)` of the round load, radius `a`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Profile {
    /// `(1 - r^2/a^2)^(k/2)` inside `a`, nought outside: `Compact(k)` for
    /// exponents from 2 to 4 in steps of a half (`k` = 4 to 8).
    Compact(u8),
    /// `exp(-2 r^2 / a^2)`: a Gaussian of standard deviation `a / 2`.
    Gaussian,
}

impl Profile {
    /// The profiles the fit chooses among.
    pub const ALL: [Profile; 6] = [
        Profile::Compact(4),
        Profile::Compact(5),
        Profile::Compact(6),
        Profile::Compact(7),
        Profile::Compact(8),
        Profile::Gaussian,
    ];

    /// `S` and the factor `k` of its gradient, `grad S = k (dx, dy)`, at
    /// squared radius `r2` for radius `a`.
    fn value(self, r2: f64, a: f64) -> (f64, f64) {
        let a2 = a * a;
        match self {
            Profile::Compact(halves) => {
                let one = 1.0 - r2 / a2;
                if one <= 0.0 {
                    return (0.0, 0.0);
                }
                let whole = one.powi(i32::from(halves / 2));
                let s = if halves % 2 == 1 {
                    whole * one.sqrt()
                } else {
                    whole
                };
                let m = 0.5 * f64::from(halves);
                // d S / d(r^2) = -m S / (a^2 one), and grad S = 2 (dx, dy) dS/d(r^2).
                (s, -2.0 * m * s / (one * a2))
            }
            Profile::Gaussian => {
                let s = (-2.0 * r2 / a2).exp();
                (s, -4.0 * s / a2)
            }
        }
    }

    /// `integral(S)` over the plane for radius `a`.
    pub fn integral(self, a: f64) -> f64 {
        let area = std::f64::consts::PI * a * a;
        match self {
            Profile::Compact(halves) => area / (0.5 * f64::from(halves) + 1.0),
            Profile::Gaussian => area / 2.0,
        }
    }
}

/// A round load's field fitted to the dots about a contact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoundFit {
    /// The load's centre, pixels.
    pub centre: [f64; 2],
    /// Its radius `a`, pixels.
    pub radius_px: f64,
    /// The profile that fitted best.
    pub profile: Profile,
    /// `alpha`: the squeeze's amplitude (negative where the gel spreads
    /// outward from under the load, as a press makes it).
    pub squeeze: f64,
    /// `beta * integral(S)`: the shear's motion integrated over the plane,
    /// `[along x, along y]`, in pixels times square pixels (the units of a
    /// patch's summed flow, [`crate::contact::RawContact::ds1`]).
    pub shear: [f64; 2],
    /// `-alpha * integral(S)`: the squeeze's strength, positive where the
    /// gel spreads outward from under the load (a press), in the units of
    /// `shear`. In a thin layer bonded to a rigid base the squeeze follows
    /// the pressure's gradient, and this grows in proportion to the normal
    /// load whatever the contact's size, where the patch's summed
    /// divergent motion ([`crate::contact::RawContact::dn`]) grows with
    /// the size too.
    pub normal: f64,
    /// Root of the squared residuals over the root of the squared motions.
    pub residual: f64,
    /// Whether the radius ended at the search's bounds (a field narrower
    /// than 0.4 pitches or wider than 5): the fit then does not describe
    /// the contact.
    pub at_bound: bool,
    /// The dots' own sums in the units of `shear` and `normal`, without a
    /// model: `pitch^2 * sum(d_i)` and `pitch^2 / 2 * sum(d_i . (x_i - c))`
    /// (the plane's integrals of `u` and of `u . (x - c) / 2`, which equal
    /// `beta integral(S)` and `-alpha integral(S)` for the model's field)
    /// over the dots read, about the fitted centre. They swing with where
    /// the contact sits against the dots; the caller falls back on them
    /// where the fit does not hold, so that its quantities keep their units.
    pub sums: ([f64; 2], f64),
    /// Whether the fit's shear and normal stay within twice what the dots'
    /// summed motion allows (`pitch^2 * sum|d_i|`, and half of
    /// `pitch^2 * sum(|d_i| |x_i - c|)`): no field explains motion by more
    /// motion than the dots show.
    pub bounded: bool,
    /// How many dots the fit read.
    pub dots: usize,
}

impl RoundFit {
    /// Whether the fit describes the contact: its radius within the
    /// search's bounds, its integrals within what the dots' motion allows
    /// ([`RoundFit::bounded`]) and at most [`MAX_RESIDUAL`] of the dots'
    /// motion unexplained.
    pub fn holds(&self) -> bool {
        !self.at_bound && self.bounded && self.residual <= MAX_RESIDUAL
    }
}

/// The dots the fit reads: their reference centres, their motion, and the
/// sum of their squared motions.
struct Samples {
    at: Vec<[f64; 2]>,
    motion: Vec<[f64; 2]>,
    norm2: f64,
}

/// The least-squares fit at one centre and radius: `(residual^2, alpha,
/// beta)`.
fn solve(s: &Samples, profile: Profile, c: [f64; 2], a: f64) -> (f64, f64, [f64; 2]) {
    // Normal equations of the columns (grad S), (S, 0), (0, S).
    let (mut gg, mut gs_x, mut gs_y, mut ss) = (0.0, 0.0, 0.0, 0.0);
    let (mut gb, mut sbu, mut sbv) = (0.0, 0.0, 0.0);
    for (p, m) in s.at.iter().zip(&s.motion) {
        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
        let (v, k) = profile.value(dx * dx + dy * dy, a);
        if v == 0.0 {
            continue;
        }
        let (gx, gy) = (k * dx, k * dy);
        gg += gx * gx + gy * gy;
        gs_x += gx * v;
        gs_y += gy * v;
        ss += v * v;
        gb += gx * m[0] + gy * m[1];
        sbu += v * m[0];
        sbv += v * m[1];
    }
    // No dot under the profile (S is at most 1): nothing explained.
    if ss <= 1e-9 {
        return (s.norm2, 0.0, [0.0; 2]);
    }
    // Eliminate beta: beta = (sb - alpha gs) / ss. The gradient's column,
    // less its projection on the profile's, may vanish (dots only where
    // the gradient follows the profile): then no squeeze.
    let den = gg - (gs_x * gs_x + gs_y * gs_y) / ss;
    let alpha = if den > 1e-12 * gg {
        (gb - (gs_x * sbu + gs_y * sbv) / ss) / den
    } else {
        0.0
    };
    let beta = [(sbu - alpha * gs_x) / ss, (sbv - alpha * gs_y) / ss];
    let explained = alpha * gb + beta[0] * sbu + beta[1] * sbv;
    ((s.norm2 - explained).max(0.0), alpha, beta)
}

/// Fits a round load's field ([module docs](self)) to the followed dots
/// (`dots`, their reference centres, and `moved`, their motion) about
/// contact `k` of `points` (every contact's point, pixels): the dots with a
/// motion whose reference centre lies within [`WINDOW_OF_PITCH`] pitches
/// of `points[k]` and no nearer to another contact's point, so that each of
/// two contacts close together reads its own side. `None` when `k` is out
/// of range, fewer than [`MIN_DOTS`] dots remain or none moved. A fit is
/// returned however well it fits; [`RoundFit::holds`] says whether it
/// describes the contact.
pub fn fit_round_field(
    dots: &[[f64; 2]],
    moved: &[Option<[f64; 2]>],
    points: &[[f64; 2]],
    k: usize,
    pitch: f64,
) -> Option<RoundFit> {
    let start = *points.get(k)?;
    if !(pitch.is_finite() && pitch > 0.0 && start.iter().all(|v| v.is_finite())) {
        return None;
    }
    let reach2 = (WINDOW_OF_PITCH * pitch).powi(2);
    let mut s = Samples {
        at: Vec::new(),
        motion: Vec::new(),
        norm2: 0.0,
    };
    for (p, m) in dots.iter().zip(moved) {
        let Some(m) = m else { continue };
        let (dx, dy) = (p[0] - start[0], p[1] - start[1]);
        let d2 = dx * dx + dy * dy;
        let nearer = |(j, o): (usize, &[f64; 2])| {
            j != k && (p[0] - o[0]).powi(2) + (p[1] - o[1]).powi(2) < d2
        };
        if d2 > reach2 || points.iter().enumerate().any(nearer) {
            continue;
        }
        if !(m[0].is_finite() && m[1].is_finite()) {
            continue;
        }
        s.at.push(*p);
        s.motion.push(*m);
        s.norm2 += m[0] * m[0] + m[1] * m[1];
    }
    if s.at.len() < MIN_DOTS || s.norm2 <= 0.0 {
        return None;
    }
    let (a_lo, a_hi) = (RADIUS_RANGE.0 * pitch, RADIUS_RANGE.1 * pitch);
    let max_shift2 = (MAX_CENTRE_SHIFT * pitch).powi(2);
    let mut best: Option<(f64, Profile, [f64; 2], f64)> = None;
    for profile in Profile::ALL {
        let eval = |c: [f64; 2], a: f64| solve(&s, profile, c, a).0;
        // The best starting radius at the starting point.
        let (mut a, mut e) = START_RADII
            .iter()
            .map(|&r| (r * pitch, eval(start, r * pitch)))
            .min_by(|p, q| p.1.total_cmp(&q.1))
            .expect("radii to try");
        let mut c = start;
        let (mut step_c, mut step_a) = (0.25 * pitch, 0.15 * a);
        let mut evaluations = START_RADII.len();
        while step_c >= MIN_STEP_PX && evaluations < MAX_EVALUATIONS {
            let moves = [
                ([c[0] + step_c, c[1]], a),
                ([c[0] - step_c, c[1]], a),
                ([c[0], c[1] + step_c], a),
                ([c[0], c[1] - step_c], a),
                (c, a + step_a),
                (c, a - step_a),
            ];
            let mut improved = false;
            for (cc, aa) in moves {
                let shift2 = (cc[0] - start[0]).powi(2) + (cc[1] - start[1]).powi(2);
                if aa < a_lo || aa > a_hi || shift2 > max_shift2 {
                    continue;
                }
                evaluations += 1;
                let ee = eval(cc, aa);
                if ee < e {
                    (c, a, e) = (cc, aa, ee);
                    improved = true;
                }
            }
            if !improved {
                step_c *= 0.5;
                step_a *= 0.5;
            }
        }
        if best.is_none_or(|b| e < b.0) {
            best = Some((e, profile, c, a));
        }
    }
    let (e, profile, c, a) = best?;
    let residual = (e / s.norm2).sqrt();
    if !residual.is_finite() {
        return None;
    }
    let (_, alpha, beta) = solve(&s, profile, c, a);
    let integral = profile.integral(a);
    let cell = pitch * pitch;
    let (mut sum, mut moment, mut size, mut spread) = ([0.0; 2], 0.0, 0.0, 0.0);
    for (p, m) in s.at.iter().zip(&s.motion) {
        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
        sum[0] += m[0];
        sum[1] += m[1];
        moment += m[0] * dx + m[1] * dy;
        let norm = m[0].hypot(m[1]);
        size += norm;
        spread += norm * dx.hypot(dy);
    }
    let shear = [beta[0] * integral, beta[1] * integral];
    let normal = -alpha * integral;
    let bounded = shear[0].hypot(shear[1]) <= MAX_OF_SUMS * cell * size
        && normal.abs() <= MAX_OF_SUMS * 0.5 * cell * spread;
    Some(RoundFit {
        centre: c,
        radius_px: a,
        profile,
        squeeze: alpha,
        shear,
        normal,
        residual,
        at_bound: a <= a_lo * 1.001 || a >= a_hi * 0.999,
        sums: ([sum[0] * cell, sum[1] * cell], 0.5 * cell * moment),
        bounded,
        dots: s.at.len(),
    })
}

#[cfg(test)]
mod tests;
