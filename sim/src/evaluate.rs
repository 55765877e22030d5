//! Scoring predicted contacts against ground truth (docs/formats.md: contacts JSON
//! Lines against `truth.jsonl`).
//!
//! Frames are paired by their `frame` name. Within a frame, predicted and true
//! contacts are matched one to one by their distance in the sensor's x-y
//! plane (`x_mm`, `y_mm`; on the strip, whose contacts all have `y_mm` 0,
//! the distance along the chord), closest pairs first, within a gate; a true contact left unmatched is a
//! **miss**, a predicted one a **false contact**. Errors are averaged over the
//! matched pairs.
//!
//! ```
//! use optical_tactile_sim::evaluate::{Evaluation, score};
//! use optical_tactile::io::{ContactRecord, FrameRecord};
//! let c = |x, fz| ContactRecord { x_mm: x, fz_n: fz, ..Default::default() };
//! let frame = |cs| FrameRecord { frame: "0.png".into(), t_s: 0.0, contacts: cs, latency_ms: None };
//! let e: Evaluation = score(&[frame(vec![c(10.5, -1.0)])], &[frame(vec![c(10.0, -1.2), c(50.0, -1.0)])], 5.0);
//! assert_eq!((e.matched, e.misses, e.false_contacts), (1, 1, 0));
//! assert!((e.mae_x_mm - 0.5).abs() < 1e-12);
//! ```

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;

use serde::Serialize;

use optical_tactile::io::{ContactRecord, FrameRecord};

/// The scores of a prediction against the truth.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Evaluation {
    /// Frames present in both files.
    pub frames: usize,
    /// Frames of the prediction with no frame of that name in the truth.
    pub unmatched_frames: usize,
    /// Matched contact pairs.
    pub matched: usize,
    /// True contacts with no prediction.
    pub misses: usize,
    /// Predicted contacts with no true contact.
    pub false_contacts: usize,
    /// Predicted contacts the tracker held without a detection in their
    /// frame (`missed` of 1 or more in the contacts file): they repeat an
    /// earlier reading, and are scored like the others.
    pub held: usize,
    /// Of the false contacts, those held (a contact that ended, repeated
    /// for the tracker's hold; `track --hold 0` writes none).
    pub false_held: usize,
    /// Mean |x error|, mm.
    pub mae_x_mm: f64,
    /// Mean |y error|, mm.
    pub mae_y_mm: f64,
    /// Mean |z error|, mm.
    pub mae_z_mm: f64,
    /// Mean 3-D location error, mm.
    pub mean_location_error_mm: f64,
    /// Mean |Fx error|, N.
    pub mae_fx_n: f64,
    /// Mean |Fy error|, N.
    pub mae_fy_n: f64,
    /// Mean |Fz error|, N.
    pub mae_fz_n: f64,
    /// Mean 3-D force error (the length of the force's error vector), N.
    pub mean_force_error_n: f64,
    /// Median per-frame latency, ms (if the prediction recorded it).
    pub median_latency_ms: Option<f64>,
    /// 95th percentile per-frame latency, ms (if recorded).
    pub p95_latency_ms: Option<f64>,
    /// Matched predictions the sensor marked out of domain
    /// (`out_of_domain` in the contacts file).
    pub matched_out_of_domain: usize,
    /// The errors of the matched predictions not marked out of domain, when
    /// some are marked (`None` when none is, or when all are).
    pub in_domain: Option<DomainErrors>,
    /// Largest |error| of Fx, Fy and Fz over the matched contacts, N.
    pub max_force_error_n: [f64; 3],
    /// The bar of [`Evaluation::beyond`], N ([`ScoreOptions::beyond_n`]).
    pub beyond_n: f64,
    /// Matched contacts whose |Fx|, |Fy|, |Fz| error exceeds
    /// [`Evaluation::beyond_n`]: the tail a mean hides.
    pub beyond: [usize; 3],
    /// The matched contacts of largest 3-D force error, largest first, at
    /// most [`ScoreOptions::worst`] of them.
    pub worst: Vec<WorstContact>,
    /// How the matched predictions' force sigmas (`fx_sigma_n` ... in the
    /// contacts file) cover their errors, when some carry them.
    pub sigma_coverage: Option<SigmaCoverage>,
    /// The errors per band of the true position along x
    /// ([`ScoreOptions::band_mm`]), bands in increasing x; empty without.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub bands: Vec<BandErrors>,
}

/// The errors of the matched contacts whose true x lies in one band
/// `[from_mm, from_mm + width)`: where on the sensor the errors are.
///
/// Why: a calibration is fitted and scored at the protocol's points, and
/// one mean over presses anywhere hides where between them it reads worse
/// (on the simulated strip, towards its ends).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct BandErrors {
    /// The band's lower edge, mm (true x).
    pub from_mm: f64,
    /// Its upper edge (excluded), mm.
    pub to_mm: f64,
    /// Matched contacts in the band.
    pub matched: usize,
    /// Mean 3-D location error, mm.
    pub mean_location_error_mm: f64,
    /// Mean |Fx|, |Fy|, |Fz| error, N.
    pub mae_force_n: [f64; 3],
    /// Largest |Fz| error, N.
    pub max_fz_error_n: f64,
    /// Contacts whose error on some axis exceeds [`Evaluation::beyond_n`].
    pub beyond: usize,
    /// Fraction of the band's contacts carrying sigmas whose |Fz| error
    /// lies within one `fz_sigma_n`; `None` when none carries them.
    pub fz_within_one_sigma: Option<f64>,
}

/// Running sums of one [`BandErrors`].
#[derive(Default)]
struct BandSums {
    matched: usize,
    location: f64,
    force: [f64; 3],
    max_fz: f64,
    beyond: usize,
    with_sigma: usize,
    fz_within: usize,
}

/// How well the predicted force sigmas describe the errors: the fractions
/// of errors within one and two sigmas, per axis (a Gaussian error with the
/// right sigma gives 68% and 95%).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct SigmaCoverage {
    /// Matched contacts that carry all three sigmas.
    pub contacts: usize,
    /// Fraction of |Fx|, |Fy|, |Fz| errors within one sigma.
    pub within_one: [f64; 3],
    /// Fraction within two sigmas.
    pub within_two: [f64; 3],
}

/// Most contacts [`ScoreOptions::worst`] may list, for a caller that takes
/// the count from a user (a longer list is no longer a summary).
pub const MAX_WORST: usize = 1000;

/// What [`score_with`] reports besides the means.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoreOptions {
    /// A prediction matches a true contact within this distance, mm.
    pub gate_mm: f64,
    /// Count the matched contacts whose error on an axis exceeds this, N
    /// ([`Evaluation::beyond`]).
    pub beyond_n: f64,
    /// List this many matched contacts of largest 3-D force error
    /// ([`Evaluation::worst`]; 0: none).
    pub worst: usize,
    /// Score the matched contacts apart per band of this width along the
    /// true x, mm ([`Evaluation::bands`]); `None`: no bands. A width that
    /// is not finite and > 0 gives no bands.
    pub band_mm: Option<f64>,
}

impl Default for ScoreOptions {
    /// A 10 mm gate, errors beyond 0.3 N counted, the five worst listed.
    fn default() -> Self {
        ScoreOptions {
            gate_mm: 10.0,
            beyond_n: 0.3,
            worst: 5,
            band_mm: None,
        }
    }
}

/// One matched contact of [`Evaluation::worst`]: where it was and how far
/// off its prediction was.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WorstContact {
    /// The frame's name.
    pub frame: String,
    /// The true contact's x and y, mm.
    pub true_mm: [f64; 2],
    /// The true force, N.
    pub true_force_n: [f64; 3],
    /// Predicted minus true x, y and z, mm.
    pub location_error_mm: [f64; 3],
    /// Predicted minus true Fx, Fy and Fz, N.
    pub force_error_n: [f64; 3],
    /// Length of the force error, N.
    pub force_error_3d_n: f64,
    /// Whether the sensor marked the prediction out of domain.
    pub out_of_domain: bool,
}

/// Location and force errors of a subset of the matched contacts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DomainErrors {
    /// Matched pairs in the subset.
    pub matched: usize,
    /// Mean |x error|, mm.
    pub mae_x_mm: f64,
    /// Mean |y error|, mm.
    pub mae_y_mm: f64,
    /// Mean |Fx error|, N.
    pub mae_fx_n: f64,
    /// Mean |Fy error|, N.
    pub mae_fy_n: f64,
    /// Mean |Fz error|, N.
    pub mae_fz_n: f64,
}

/// Matches contacts one to one by their distance in the x-y plane within
/// `gate_mm`, closest first. Returns the index pairs `(predicted, true)`.
pub fn match_contacts(
    pred: &[ContactRecord],
    truth: &[ContactRecord],
    gate_mm: f64,
) -> Vec<(usize, usize)> {
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (i, p) in pred.iter().enumerate() {
        for (j, t) in truth.iter().enumerate() {
            let d = (p.x_mm - t.x_mm).hypot(p.y_mm - t.y_mm);
            if d <= gate_mm {
                pairs.push((d, i, j));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let (mut up, mut ut) = (vec![false; pred.len()], vec![false; truth.len()]);
    let mut out = Vec::new();
    for (_, i, j) in pairs {
        if !up[i] && !ut[j] {
            up[i] = true;
            ut[j] = true;
            out.push((i, j));
        }
    }
    out
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    let k = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[k]
}

/// Scores `pred` against `truth` (frames paired by name), with a gate of
/// `gate_mm` and the other [`ScoreOptions`] at their defaults.
pub fn score(pred: &[FrameRecord], truth: &[FrameRecord], gate_mm: f64) -> Evaluation {
    score_with(
        pred,
        truth,
        &ScoreOptions {
            gate_mm,
            ..ScoreOptions::default()
        },
    )
}

/// Scores `pred` against `truth` (frames paired by name) as `options` say.
pub fn score_with(
    pred: &[FrameRecord],
    truth: &[FrameRecord],
    options: &ScoreOptions,
) -> Evaluation {
    let gate_mm = options.gate_mm;
    let by_name: HashMap<&str, &FrameRecord> =
        truth.iter().map(|f| (f.frame.as_str(), f)).collect();
    let mut e = Evaluation {
        beyond_n: options.beyond_n,
        ..Evaluation::default()
    };
    let mut sums = [0.0f64; 8];
    // Over the pairs whose prediction is not out of domain: x, y, Fx, Fy, Fz.
    let mut inside = [0.0f64; 5];
    let mut latencies = Vec::new();
    // Contacts with sigmas; per axis, errors within one and two sigmas.
    let (mut with_sigma, mut one, mut two) = (0usize, [0usize; 3], [0usize; 3]);
    let band_mm = options.band_mm.filter(|w| *w > 0.0 && w.is_finite());
    let mut bands: BTreeMap<i64, BandSums> = BTreeMap::new();
    for p in pred {
        if let Some(l) = p.latency_ms {
            latencies.push(l);
        }
        let Some(t) = by_name.get(p.frame.as_str()) else {
            e.unmatched_frames += 1;
            continue;
        };
        e.frames += 1;
        let m = match_contacts(&p.contacts, &t.contacts, gate_mm);
        e.matched += m.len();
        e.misses += t.contacts.len() - m.len();
        e.false_contacts += p.contacts.len() - m.len();
        let held = |c: &ContactRecord| c.missed.is_some_and(|k| k > 0);
        e.held += p.contacts.iter().filter(|c| held(c)).count();
        e.false_held += p
            .contacts
            .iter()
            .enumerate()
            .filter(|&(i, c)| held(c) && !m.iter().any(|&(k, _)| k == i))
            .count();
        for (i, j) in m {
            let (a, b) = (&p.contacts[i], &t.contacts[j]);
            let out_of_domain = a.out_of_domain == Some(true);
            let d = [a.x_mm - b.x_mm, a.y_mm - b.y_mm, a.z_mm - b.z_mm];
            sums[0] += d[0].abs();
            sums[1] += d[1].abs();
            sums[2] += d[2].abs();
            let location_3d = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            sums[3] += location_3d;
            let errors = [a.fx_n - b.fx_n, a.fy_n - b.fy_n, a.fz_n - b.fz_n];
            for (k, err) in errors.iter().enumerate() {
                sums[4 + k] += err.abs();
                e.max_force_error_n[k] = e.max_force_error_n[k].max(err.abs());
                e.beyond[k] += usize::from(err.abs() > options.beyond_n);
            }
            let error_3d = errors.iter().map(|x| x * x).sum::<f64>().sqrt();
            sums[7] += error_3d;
            // The three sigmas, when the prediction carries them all.
            let sigmas = match (a.fx_sigma_n, a.fy_sigma_n, a.fz_sigma_n) {
                (Some(x), Some(y), Some(z)) => Some([x, y, z]),
                _ => None,
            };
            if let Some(w) = band_mm {
                // Saturating: a far position lands in the outermost band
                // an i64 can name, not in a wrong one.
                let band = bands.entry((b.x_mm / w).floor() as i64).or_default();
                band.matched += 1;
                band.location += location_3d;
                for (acc, err) in band.force.iter_mut().zip(&errors) {
                    *acc += err.abs();
                }
                band.max_fz = band.max_fz.max(errors[2].abs());
                band.beyond += usize::from(errors.iter().any(|e| e.abs() > options.beyond_n));
                if let Some(sigma) = sigmas {
                    band.with_sigma += 1;
                    band.fz_within += usize::from(errors[2].abs() <= sigma[2]);
                }
            }
            if options.worst > 0 {
                e.worst.push(WorstContact {
                    frame: p.frame.clone(),
                    true_mm: [b.x_mm, b.y_mm],
                    true_force_n: [b.fx_n, b.fy_n, b.fz_n],
                    location_error_mm: d,
                    force_error_n: errors,
                    force_error_3d_n: error_3d,
                    out_of_domain,
                });
                // Kept short as it goes: sorted, largest first, cut at
                // twice the count before it is sorted again.
                if e.worst.len() >= 2 * options.worst {
                    keep_worst(&mut e.worst, options.worst);
                }
            }
            if let Some(sigmas) = sigmas {
                with_sigma += 1;
                for (k, (err, sigma)) in errors.iter().zip(sigmas).enumerate() {
                    one[k] += usize::from(err.abs() <= sigma);
                    two[k] += usize::from(err.abs() <= 2.0 * sigma);
                }
            }
            if out_of_domain {
                e.matched_out_of_domain += 1;
            } else {
                for (acc, err) in inside.iter_mut().zip([d[0], d[1]].iter().chain(&errors)) {
                    *acc += err.abs();
                }
            }
        }
    }
    keep_worst(&mut e.worst, options.worst);
    if let Some(w) = band_mm {
        e.bands = bands
            .into_iter()
            .map(|(i, b)| {
                let k = b.matched as f64;
                BandErrors {
                    from_mm: i as f64 * w,
                    to_mm: (i as f64 + 1.0) * w,
                    matched: b.matched,
                    mean_location_error_mm: b.location / k,
                    mae_force_n: b.force.map(|f| f / k),
                    max_fz_error_n: b.max_fz,
                    beyond: b.beyond,
                    fz_within_one_sigma: (b.with_sigma > 0)
                        .then(|| b.fz_within as f64 / b.with_sigma as f64),
                }
            })
            .collect();
    }
    if with_sigma > 0 {
        let k = with_sigma as f64;
        e.sigma_coverage = Some(SigmaCoverage {
            contacts: with_sigma,
            within_one: one.map(|c| c as f64 / k),
            within_two: two.map(|c| c as f64 / k),
        });
    }
    let kept = e.matched - e.matched_out_of_domain;
    if e.matched_out_of_domain > 0 && kept > 0 {
        let k = kept as f64;
        e.in_domain = Some(DomainErrors {
            matched: kept,
            mae_x_mm: inside[0] / k,
            mae_y_mm: inside[1] / k,
            mae_fx_n: inside[2] / k,
            mae_fy_n: inside[3] / k,
            mae_fz_n: inside[4] / k,
        });
    }
    let n = e.matched.max(1) as f64;
    [
        e.mae_x_mm,
        e.mae_y_mm,
        e.mae_z_mm,
        e.mean_location_error_mm,
        e.mae_fx_n,
        e.mae_fy_n,
        e.mae_fz_n,
        e.mean_force_error_n,
    ] = sums.map(|s| s / n);
    if !latencies.is_empty() {
        latencies.sort_by(f64::total_cmp);
        e.median_latency_ms = Some(quantile(&latencies, 0.5));
        e.p95_latency_ms = Some(quantile(&latencies, 0.95));
    }
    e
}

/// Sorts `worst` by 3-D force error, largest first (ties in frame order),
/// and keeps the first `n`.
fn keep_worst(worst: &mut Vec<WorstContact>, n: usize) {
    worst.sort_by(|a, b| b.force_error_3d_n.total_cmp(&a.force_error_3d_n));
    worst.truncate(n);
}

impl Evaluation {
    /// A markdown table of the scores.
    pub fn to_markdown(&self) -> String {
        let mut s = String::from("| quantity | value |\n|---|---|\n");
        let mut row = |k: &str, v: String| {
            let _ = writeln!(s, "| {k} | {v} |");
        };
        row("frames scored", self.frames.to_string());
        if self.unmatched_frames > 0 {
            row(
                "frames missing from the truth",
                self.unmatched_frames.to_string(),
            );
        }
        row("matched contacts", self.matched.to_string());
        row("misses", self.misses.to_string());
        row("false contacts", self.false_contacts.to_string());
        if self.held > 0 {
            row(
                "contacts held by the tracker (missed > 0)",
                format!("{} ({} of them false contacts)", self.held, self.false_held),
            );
        }
        // Errors over no pair are not zero errors: say there is none.
        let scored = self.matched > 0;
        let mut err = |k: &str, v: f64, digits: usize| {
            row(
                k,
                if scored {
                    format!("{v:.digits$}")
                } else {
                    "n/a (no matched contact)".to_string()
                },
            )
        };
        err("MAE x (mm)", self.mae_x_mm, 3);
        err("MAE y (mm)", self.mae_y_mm, 3);
        err("MAE z (mm)", self.mae_z_mm, 3);
        err(
            "mean 3-D location error (mm)",
            self.mean_location_error_mm,
            3,
        );
        err("MAE Fx (N)", self.mae_fx_n, 4);
        err("MAE Fy (N)", self.mae_fy_n, 4);
        err("MAE Fz (N)", self.mae_fz_n, 4);
        err("mean 3-D force error (N)", self.mean_force_error_n, 4);
        if scored {
            let [x, y, z] = self.max_force_error_n;
            row(
                "largest error Fx / Fy / Fz (N)",
                format!("{x:.3} / {y:.3} / {z:.3}"),
            );
            let [x, y, z] = self.beyond;
            row(
                &format!(
                    "contacts off by more than {} N, Fx / Fy / Fz",
                    self.beyond_n
                ),
                format!("{x} / {y} / {z}"),
            );
        }
        if let Some(c) = &self.sigma_coverage {
            let pct = |v: [f64; 3]| {
                format!(
                    "{:.0}% / {:.0}% / {:.0}%",
                    100.0 * v[0],
                    100.0 * v[1],
                    100.0 * v[2]
                )
            };
            row(
                "force errors within 1 sigma, Fx / Fy / Fz (aim 68%)",
                format!("{} ({} contacts)", pct(c.within_one), c.contacts),
            );
            row("force errors within 2 sigma (aim 95%)", pct(c.within_two));
        }
        if self.matched_out_of_domain > 0 {
            row(
                "matched contacts marked out of domain",
                self.matched_out_of_domain.to_string(),
            );
        }
        if let Some(d) = &self.in_domain {
            row(
                "the others: MAE x / y (mm), Fx / Fy / Fz (N)",
                format!(
                    "{:.3} / {:.3}, {:.4} / {:.4} / {:.4} ({} contacts)",
                    d.mae_x_mm, d.mae_y_mm, d.mae_fx_n, d.mae_fy_n, d.mae_fz_n, d.matched
                ),
            );
        }
        if let (Some(m), Some(p)) = (self.median_latency_ms, self.p95_latency_ms) {
            row("latency median / p95 (ms)", format!("{m:.2} / {p:.2}"));
        }
        if !self.worst.is_empty() {
            s.push_str(
                "\n| worst contacts (3-D force error) | true x, y (mm) | true Fx / Fy / Fz (N) \
                 | location error x / y / z (mm) | force error Fx / Fy / Fz (N) | 3-D (N) |\n\
                 |---|---|---|---|---|---|\n",
            );
            for w in &self.worst {
                let [x, y] = w.true_mm;
                let [fx, fy, fz] = w.true_force_n;
                let [ex, ey, ez] = w.location_error_mm;
                let [gx, gy, gz] = w.force_error_n;
                let mark = if w.out_of_domain {
                    " (out of domain)"
                } else {
                    ""
                };
                let _ = writeln!(
                    s,
                    "| {}{mark} | {x:.1}, {y:.1} | {fx:.2} / {fy:.2} / {fz:.2} | {ex:+.2} / {ey:+.2} / {ez:+.2} \
                     | {gx:+.3} / {gy:+.3} / {gz:+.3} | {:.3} |",
                    w.frame, w.force_error_3d_n
                );
            }
        }
        if !self.bands.is_empty() {
            let _ = write!(
                s,
                "\n| true x (mm) | contacts | 3-D location error (mm) | MAE Fx / Fy / Fz (N) \
                 | largest Fz error (N) | beyond {} N | Fz within 1 sigma |\n\
                 |---|---|---|---|---|---|---|\n",
                self.beyond_n
            );
            for b in &self.bands {
                let [fx, fy, fz] = b.mae_force_n;
                let within = b
                    .fz_within_one_sigma
                    .map_or("n/a".to_string(), |v| format!("{:.0}%", 100.0 * v));
                let _ = writeln!(
                    s,
                    "| {:.0} to {:.0} | {} | {:.3} | {fx:.4} / {fy:.4} / {fz:.4} | {:.3} | {} | {within} |",
                    b.from_mm,
                    b.to_mm,
                    b.matched,
                    b.mean_location_error_mm,
                    b.max_fz_error_n,
                    b.beyond
                );
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(x: f64, fz: f64) -> ContactRecord {
        ContactRecord {
            x_mm: x,
            fz_n: fz,
            ..Default::default()
        }
    }

    fn f(name: &str, cs: Vec<ContactRecord>, lat: Option<f64>) -> FrameRecord {
        FrameRecord {
            frame: name.into(),
            t_s: 0.0,
            contacts: cs,
            latency_ms: lat,
        }
    }

    #[test]
    fn closest_pairs_win_and_each_contact_is_used_once() {
        let p = [c(0.0, 0.0), c(9.0, 0.0)];
        let t = [c(8.0, 0.0), c(1.0, 0.0)];
        assert_eq!(match_contacts(&p, &t, 5.0), vec![(0, 1), (1, 0)]);
        // Both predictions near the same truth: one match, one false contact.
        let p = [c(0.0, 0.0), c(0.5, 0.0)];
        assert_eq!(match_contacts(&p, &[c(0.4, 0.0)], 5.0), vec![(1, 0)]);
    }

    #[test]
    fn contacts_out_of_domain_are_counted_and_the_others_scored_apart() {
        let mut far = c(10.0, -2.0);
        far.out_of_domain = Some(true);
        let mut near = c(0.5, -1.5);
        near.out_of_domain = Some(false);
        let pred = vec![f("a", vec![near, far], None)];
        let truth = vec![f("a", vec![c(0.0, -1.0), c(10.0, -1.0)], None)];
        let e = score(&pred, &truth, 5.0);
        assert_eq!((e.matched, e.matched_out_of_domain), (2, 1));
        let d = e.in_domain.expect("one contact in domain");
        assert_eq!(d.matched, 1);
        assert!((d.mae_x_mm - 0.5).abs() < 1e-12 && (d.mae_fz_n - 0.5).abs() < 1e-12);
        // Over both: x (0.5 + 0) / 2, Fz (0.5 + 1) / 2.
        assert!((e.mae_x_mm - 0.25).abs() < 1e-12 && (e.mae_fz_n - 0.75).abs() < 1e-12);
        let md = e.to_markdown();
        assert!(
            md.contains("| matched contacts marked out of domain | 1 |"),
            "{md}"
        );
        // Nothing marked: no separate scores.
        let plain = score(&[f("a", vec![c(0.5, -1.5)], None)], &truth, 5.0);
        assert_eq!((plain.matched_out_of_domain, plain.in_domain), (0, None));
    }

    #[test]
    fn sigmas_are_scored_by_how_many_errors_they_cover() {
        let with = |x: f64, fz: f64, sigma: f64| ContactRecord {
            fx_sigma_n: Some(sigma),
            fy_sigma_n: Some(sigma),
            fz_sigma_n: Some(sigma),
            ..c(x, fz)
        };
        // Fz errors 0.05, 0.15, 0.25, 0.5 against sigmas of 0.1: one within
        // one sigma, two within two; Fx and Fy errors are 0. A contact
        // without sigmas is scored but not counted.
        let truth = vec![f(
            "a",
            vec![
                c(0.0, -1.0),
                c(20.0, -1.0),
                c(40.0, -1.0),
                c(60.0, -1.0),
                c(80.0, -1.0),
            ],
            None,
        )];
        let pred = vec![f(
            "a",
            vec![
                with(0.0, -1.05, 0.1),
                with(20.0, -1.15, 0.1),
                with(40.0, -0.75, 0.1),
                with(60.0, -1.5, 0.1),
                c(80.0, -2.0),
            ],
            None,
        )];
        let e = score(&pred, &truth, 5.0);
        let cov = e.sigma_coverage.expect("four contacts carry sigmas");
        assert_eq!(cov.contacts, 4);
        assert_eq!(cov.within_one, [1.0, 1.0, 0.25]);
        assert_eq!(cov.within_two, [1.0, 1.0, 0.5]);
        assert_eq!(e.max_force_error_n, [0.0, 0.0, 1.0]);
        let md = e.to_markdown();
        assert!(md.contains("100% / 100% / 25% (4 contacts)"), "{md}");
        assert!(
            md.contains("| largest error Fx / Fy / Fz (N) | 0.000 / 0.000 / 1.000 |"),
            "{md}"
        );
        // Without sigmas there is nothing to score.
        assert_eq!(score(&truth, &truth, 5.0).sigma_coverage, None);
    }

    #[test]
    fn the_3d_force_error_is_the_length_of_the_error_vector() {
        // Errors (0.3, 0, -0.4) and (0, 0.12, 0.05): lengths 0.5 and 0.13.
        let force = |x: f64, fx: f64, fy: f64, fz: f64| ContactRecord {
            fx_n: fx,
            fy_n: fy,
            ..c(x, fz)
        };
        let truth = vec![f(
            "a",
            vec![force(0.0, 0.0, 0.0, -1.0), force(50.0, 0.1, 0.0, -2.0)],
            None,
        )];
        let pred = vec![f(
            "a",
            vec![force(0.0, 0.3, 0.0, -1.4), force(50.0, 0.1, 0.12, -1.95)],
            None,
        )];
        let e = score(&pred, &truth, 5.0);
        assert!((e.mean_force_error_n - 0.315).abs() < 1e-12, "{e:?}");
        assert!(
            e.to_markdown()
                .contains("| mean 3-D force error (N) | 0.3150 |")
        );
    }

    #[test]
    fn the_tail_is_counted_per_axis_and_the_worst_are_listed_largest_first() {
        // Fz errors 0.1, 0.5, 0.31, 0.25 and one Fx error of 0.4, over two
        // frames.
        let force = |x: f64, fx: f64, fz: f64| ContactRecord {
            fx_n: fx,
            ..c(x, fz)
        };
        let truth = vec![
            f("a", vec![c(0.0, -1.0), c(50.0, -1.0)], None),
            f("b", vec![c(0.0, -2.0), c(50.0, -2.0)], None),
        ];
        let pred = vec![
            f("a", vec![c(0.0, -1.1), force(50.0, 0.4, -1.5)], None),
            f("b", vec![c(0.2, -2.31), c(50.0, -1.75)], None),
        ];
        let e = score(&pred, &truth, 5.0);
        assert_eq!(e.beyond_n, 0.3);
        assert_eq!(e.beyond, [1, 0, 2]);
        let listed: Vec<(&str, f64)> = e
            .worst
            .iter()
            .map(|w| (w.frame.as_str(), w.true_mm[0]))
            .collect();
        assert_eq!(
            listed,
            [("a", 50.0), ("b", 0.0), ("b", 50.0), ("a", 0.0)],
            "{:?}",
            e.worst
        );
        let w = &e.worst[0];
        assert!((w.force_error_3d_n - 0.41f64.sqrt()).abs() < 1e-12);
        assert!(
            (w.force_error_n[0] - 0.4).abs() < 1e-12 && (w.force_error_n[2] + 0.5).abs() < 1e-12
        );
        assert!((e.worst[1].location_error_mm[0] - 0.2).abs() < 1e-12);
        let md = e.to_markdown();
        assert!(
            md.contains("| contacts off by more than 0.3 N, Fx / Fy / Fz | 1 / 0 / 2 |"),
            "{md}"
        );
        assert!(md.contains("| worst contacts (3-D force error) |"), "{md}");

        // Another bar, a shorter list, and none.
        let opts = |beyond_n, worst| ScoreOptions {
            gate_mm: 5.0,
            beyond_n,
            worst,
            band_mm: None,
        };
        // The bar is strict: the Fz error of exactly 0.25 is not beyond it.
        assert_eq!(score_with(&pred, &truth, &opts(0.25, 5)).beyond, [1, 0, 2]);
        let e = score_with(&pred, &truth, &opts(0.05, 2));
        assert_eq!(e.beyond, [1, 0, 4]);
        assert_eq!(e.worst.len(), 2);
        assert_eq!(
            (e.worst[0].frame.as_str(), e.worst[1].frame.as_str()),
            ("a", "b")
        );
        let e = score_with(&pred, &truth, &opts(0.3, 0));
        assert!(e.worst.is_empty() && !e.to_markdown().contains("worst contacts"));
    }

    #[test]
    fn bands_score_the_contacts_by_where_they_are_and_add_up_to_the_whole() {
        // True contacts at -15, -5, 5, 12 and 25 mm; the predictions read
        // Fz off by 0.1, 0.2, 0.4, 0.0 and 0.5 N, x off by 1 mm at 12 mm.
        let at = [
            (-15.0, 0.1),
            (-5.0, 0.2),
            (5.0, 0.4),
            (12.0, 0.0),
            (25.0, 0.5),
        ];
        let truth: Vec<FrameRecord> = at
            .iter()
            .enumerate()
            .map(|(i, &(x, _))| f(&i.to_string(), vec![c(x, -1.0)], None))
            .collect();
        let pred: Vec<FrameRecord> = at
            .iter()
            .enumerate()
            .map(|(i, &(x, err))| {
                let mut p = c(if x == 12.0 { 13.0 } else { x }, -1.0 - err);
                // Sigmas on all but the last: 0.25 N covers 0.1 and 0.2.
                if i < 4 {
                    (p.fx_sigma_n, p.fy_sigma_n, p.fz_sigma_n) = (Some(1.0), Some(1.0), Some(0.25));
                }
                f(&i.to_string(), vec![p], None)
            })
            .collect();
        let options = |band_mm| ScoreOptions {
            band_mm,
            ..ScoreOptions::default()
        };
        let e = score_with(&pred, &truth, &options(Some(10.0)));
        let edges: Vec<(f64, f64, usize)> = e
            .bands
            .iter()
            .map(|b| (b.from_mm, b.to_mm, b.matched))
            .collect();
        assert_eq!(
            edges,
            vec![
                (-20.0, -10.0, 1),
                (-10.0, 0.0, 1),
                (0.0, 10.0, 1),
                (10.0, 20.0, 1),
                (20.0, 30.0, 1)
            ]
        );
        let fz: Vec<f64> = e.bands.iter().map(|b| b.mae_force_n[2]).collect();
        for (got, want) in fz.iter().zip([0.1, 0.2, 0.4, 0.0, 0.5]) {
            assert!((got - want).abs() < 1e-12, "{fz:?}");
        }
        assert!((e.bands[3].mean_location_error_mm - 1.0).abs() < 1e-12);
        let beyond: Vec<usize> = e.bands.iter().map(|b| b.beyond).collect();
        assert_eq!(beyond, vec![0, 0, 1, 0, 1]);
        let within: Vec<Option<f64>> = e.bands.iter().map(|b| b.fz_within_one_sigma).collect();
        assert_eq!(
            within,
            vec![Some(1.0), Some(1.0), Some(0.0), Some(1.0), None]
        );
        let md = e.to_markdown();
        assert!(md.contains("| true x (mm) | contacts |"), "{md}");
        assert!(md.contains("| -20 to -10 | 1 |"), "{md}");
        assert!(
            md.contains("| 20 to 30 | 1 | 0.000 | 0.0000 / 0.0000 / 0.5000 | 0.500 | 1 | n/a |"),
            "{md}"
        );

        // Wider bands: the contacts pool, and the bands' sums are the whole's.
        let e = score_with(&pred, &truth, &options(Some(20.0)));
        assert_eq!(
            e.bands.iter().map(|b| b.matched).collect::<Vec<_>>(),
            vec![2, 2, 1]
        );
        let pooled: f64 = e
            .bands
            .iter()
            .map(|b| b.matched as f64 * b.mae_force_n[2])
            .sum();
        assert!((pooled / e.matched as f64 - e.mae_fz_n).abs() < 1e-12);
        let located: f64 = e
            .bands
            .iter()
            .map(|b| b.matched as f64 * b.mean_location_error_mm)
            .sum();
        assert!((located / e.matched as f64 - e.mean_location_error_mm).abs() < 1e-12);

        // No bands asked, or a width that names none: no table.
        for w in [
            None,
            Some(0.0),
            Some(-5.0),
            Some(f64::NAN),
            Some(f64::INFINITY),
        ] {
            let e = score_with(&pred, &truth, &options(w));
            assert!(e.bands.is_empty(), "{w:?}");
            assert!(!e.to_markdown().contains("true x (mm)"));
        }
        // A width far below the positions' scale: every contact its own
        // band, none lost.
        let e = score_with(&pred, &truth, &options(Some(1e-300)));
        assert_eq!(e.bands.iter().map(|b| b.matched).sum::<usize>(), 5);
    }

    #[test]
    fn the_worst_list_is_the_same_however_long_the_sequence() {
        // Many frames, errors in no order: the list kept short as it goes
        // must be the list a full sort gives.
        let n = 200;
        let err = |i: usize| ((i * 37) % n) as f64 / n as f64;
        let truth: Vec<FrameRecord> = (0..n)
            .map(|i| f(&format!("{i:03}"), vec![c(0.0, -1.0)], None))
            .collect();
        let pred: Vec<FrameRecord> = (0..n)
            .map(|i| f(&format!("{i:03}"), vec![c(0.0, -1.0 - err(i))], None))
            .collect();
        let e = score_with(
            &pred,
            &truth,
            &ScoreOptions {
                worst: 7,
                ..ScoreOptions::default()
            },
        );
        let mut all: Vec<f64> = (0..n).map(err).collect();
        all.sort_by(|a, b| b.total_cmp(a));
        let got: Vec<f64> = e.worst.iter().map(|w| w.force_error_3d_n).collect();
        assert_eq!(got.len(), 7);
        for (g, want) in got.iter().zip(&all) {
            assert!((g - want).abs() < 1e-12, "{got:?} against {:?}", &all[..7]);
        }
    }

    #[test]
    fn scores_count_misses_false_contacts_and_errors() {
        let truth = vec![
            f("a", vec![c(0.0, -1.0), c(40.0, -2.0)], None),
            f("b", vec![], None),
        ];
        let pred = vec![
            f("a", vec![c(1.0, -1.5), c(100.0, -1.0)], Some(2.0)),
            f("b", vec![c(3.0, -0.1)], Some(4.0)),
            f("zzz", vec![], Some(3.0)),
        ];
        let e = score(&pred, &truth, 10.0);
        assert_eq!((e.frames, e.unmatched_frames), (2, 1));
        assert_eq!((e.matched, e.misses, e.false_contacts), (1, 1, 2));
        assert_eq!((e.mae_x_mm, e.mae_fz_n), (1.0, 0.5));
        assert_eq!(e.median_latency_ms, Some(3.0));
        assert!(e.to_markdown().contains("| misses | 1 |"));
        // No record says it was held: no row for it.
        assert_eq!((e.held, e.false_held), (0, 0));
        assert!(!e.to_markdown().contains("held"));
    }

    #[test]
    fn held_contacts_are_counted_matched_or_false() {
        let held = |x: f64, fz: f64, missed: u32| ContactRecord {
            missed: Some(missed),
            ..c(x, fz)
        };
        let truth = vec![
            f("a", vec![c(0.0, -1.0)], None),
            f("b", vec![c(0.0, -1.2)], None),
        ];
        // Frame a: fresh at 0, a held one where nothing is; frame b: the
        // one at 0 held (matched), a fresh false one, a record with
        // `missed: 0`.
        let pred = vec![
            f("a", vec![c(0.5, -1.0), held(60.0, -2.0, 1)], None),
            f(
                "b",
                vec![held(0.5, -1.0, 2), c(90.0, -0.5), held(-90.0, -0.5, 0)],
                None,
            ),
        ];
        let e = score(&pred, &truth, 5.0);
        assert_eq!((e.matched, e.false_contacts), (2, 3));
        assert_eq!((e.held, e.false_held), (2, 1));
        assert!(
            e.to_markdown().contains(
                "| contacts held by the tracker (missed > 0) | 2 (1 of them false contacts) |"
            ),
            "{}",
            e.to_markdown()
        );
    }
}
