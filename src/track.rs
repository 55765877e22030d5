//! Contacts over time: identity across frames, smoothing, hysteresis, and the
//! policy that decides when it is safe to take a fresh reference frame.
//!
//! - **Identity** ([`Tracker`]): each frame's contacts are matched to the live
//!   tracks by gated nearest neighbour on the location (mm), closest pairs first;
//!   a matched contact keeps its track's id, an unmatched one starts a new id.
//! - **Hysteresis**: a new track needs a detection strength of at least
//!   `start_strength`; a live track continues with anything above
//!   `keep_strength` (lower), and survives up to `max_missed` frames with no
//!   detection at all, holding its last estimate. So a contact near the
//!   detection threshold does not flicker on and off (the paper's readings
//!   dropped to zero for single frames near the threshold).
//! - **Smoothing** (optional): a constant-velocity Kalman filter per tracked
//!   quantity (location and force components).
//! - **Re-referencing** ([`ReferencePolicy`]): after `quiet_s` seconds with no
//!   contact (not even a held one) and a small global flow, take a new reference
//!   so that slow lighting or temperature drift does not pile up; never while
//!   anything touches.

use serde::{Deserialize, Serialize};

use crate::contact::Contact;
use crate::error::{Error, Result};

/// Noise levels of the constant-velocity Kalman filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct FilterConfig {
    /// Standard deviation of a location measurement, mm.
    pub location_sigma_mm: f64,
    /// Standard deviation of a force measurement, N.
    pub force_sigma_n: f64,
    /// Acceleration noise of the location (how fast a contact may change its
    /// speed), mm/s^2.
    pub location_accel: f64,
    /// Rate-of-change noise of the force, N/s^2.
    pub force_accel: f64,
}

impl Default for FilterConfig {
    fn default() -> Self {
        FilterConfig {
            location_sigma_mm: 0.5,
            force_sigma_n: 0.03,
            location_accel: 500.0,
            force_accel: 20.0,
        }
    }
}

/// How contacts are followed over time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct TrackerConfig {
    /// Largest jump (mm) between frames for a contact to keep its identity.
    pub gate_mm: f64,
    /// Detection strength a new contact needs (the segmentation's summed |flow|,
    /// in the same units). 0 accepts every detection.
    pub start_strength: f64,
    /// Detection strength that keeps a live contact alive (<= `start_strength`).
    pub keep_strength: f64,
    /// Frames a contact is held without a detection before it ends.
    pub max_missed: u32,
    /// Smoothing filter, if any.
    pub filter: Option<FilterConfig>,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            gate_mm: 10.0,
            start_strength: 0.0,
            keep_strength: 0.0,
            max_missed: 2,
            filter: None,
        }
    }
}

impl TrackerConfig {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<()> {
        if !(self.gate_mm.is_finite() && self.gate_mm > 0.0) {
            return Err(Error::param(
                "gate_mm",
                format!("must be > 0, got {}", self.gate_mm),
            ));
        }
        if !(self.keep_strength >= 0.0 && self.keep_strength <= self.start_strength) {
            return Err(Error::param(
                "keep_strength",
                format!(
                    "must lie in 0..=start_strength ({}), got {}",
                    self.start_strength, self.keep_strength
                ),
            ));
        }
        if let Some(f) = &self.filter {
            let all = [
                f.location_sigma_mm,
                f.force_sigma_n,
                f.location_accel,
                f.force_accel,
            ];
            if all.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(Error::param(
                    "filter",
                    "every noise level must be finite and > 0",
                ));
            }
        }
        Ok(())
    }
}

/// A 1-D constant-velocity Kalman filter: state (value, rate).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Cv1 {
    x: f64,
    v: f64,
    p: [[f64; 2]; 2],
}

impl Cv1 {
    fn new(x: f64, sigma: f64) -> Self {
        Cv1 {
            x,
            v: 0.0,
            p: [[sigma * sigma, 0.0], [0.0, 1e6 * sigma * sigma]],
        }
    }

    fn predict(&mut self, dt: f64, accel: f64) {
        self.x += self.v * dt;
        let p = self.p;
        // P = F P F^T + Q, F = [[1, dt], [0, 1]], Q from white acceleration noise.
        let (dt2, q) = (dt * dt, accel * accel);
        self.p = [
            [
                p[0][0] + dt * (p[1][0] + p[0][1]) + dt2 * p[1][1] + q * dt2 * dt2 / 4.0,
                p[0][1] + dt * p[1][1] + q * dt2 * dt / 2.0,
            ],
            [
                p[1][0] + dt * p[1][1] + q * dt2 * dt / 2.0,
                p[1][1] + q * dt2,
            ],
        ];
    }

    fn update(&mut self, z: f64, sigma: f64) {
        let s = self.p[0][0] + sigma * sigma;
        let k = [self.p[0][0] / s, self.p[1][0] / s];
        let y = z - self.x;
        self.x += k[0] * y;
        self.v += k[1] * y;
        let p = self.p;
        self.p = [
            [(1.0 - k[0]) * p[0][0], (1.0 - k[0]) * p[0][1]],
            [p[1][0] - k[1] * p[0][0], p[1][1] - k[1] * p[0][1]],
        ];
    }
}

#[derive(Debug, Clone)]
struct Track {
    contact: Contact,
    /// Filters for x, y, z, fx, fy, fz (when smoothing is on).
    filters: Option<[Cv1; 6]>,
}

/// Follows contacts from frame to frame (see the module docs).
#[derive(Debug, Clone)]
pub struct Tracker {
    config: TrackerConfig,
    tracks: Vec<Track>,
    next_id: u64,
    out: Vec<Contact>,
    pairs: Vec<(f64, usize, usize)>,
    used_track: Vec<bool>,
    used_det: Vec<bool>,
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

impl Tracker {
    /// A tracker with no live contact.
    pub fn new(config: TrackerConfig) -> Result<Self> {
        config.validate()?;
        Ok(Tracker {
            config,
            tracks: Vec::new(),
            next_id: 1,
            out: Vec::new(),
            pairs: Vec::new(),
            used_track: Vec::new(),
            used_det: Vec::new(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// Forgets every live contact (ids keep counting up).
    pub fn reset(&mut self) {
        self.tracks.clear();
        self.out.clear();
    }

    /// The contacts returned by the last [`update`](Self::update).
    pub fn last(&self) -> &[Contact] {
        &self.out
    }

    /// Number of live contacts, including held ones.
    pub fn live(&self) -> usize {
        self.tracks.len()
    }

    /// Takes one frame's detections (`dt_s` seconds after the previous frame)
    /// and returns the tracked contacts, each with its id, smoothed if
    /// smoothing is on. Held contacts (no detection this frame) have `missed > 0`.
    pub fn update(&mut self, detections: &[Contact], dt_s: f64) -> &[Contact] {
        let dt = if dt_s.is_finite() && dt_s > 0.0 {
            dt_s
        } else {
            0.0
        };
        let cfg = self.config;
        // Candidate pairs inside the gate, closest first (ties by index: deterministic).
        self.pairs.clear();
        for (t, tr) in self.tracks.iter().enumerate() {
            for (d, det) in detections.iter().enumerate() {
                let dd = dist(&tr.contact.location_mm, &det.location_mm);
                if dd <= cfg.gate_mm && det.raw.strength >= cfg.keep_strength {
                    self.pairs.push((dd, t, d));
                }
            }
        }
        self.pairs
            .sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        self.used_track.clear();
        self.used_track.resize(self.tracks.len(), false);
        self.used_det.clear();
        self.used_det.resize(detections.len(), false);
        for &(_, t, d) in &self.pairs {
            if self.used_track[t] || self.used_det[d] {
                continue;
            }
            self.used_track[t] = true;
            self.used_det[d] = true;
            let tr = &mut self.tracks[t];
            let id = tr.contact.id;
            tr.contact = detections[d];
            tr.contact.id = id;
            tr.contact.missed = 0;
            if let (Some(f), Some(filters)) = (cfg.filter, tr.filters.as_mut()) {
                apply_filter(filters, &mut tr.contact, dt, &f, true);
            }
        }
        // Unmatched tracks are held (predicted, when filtering) or end.
        let mut k = 0;
        while k < self.tracks.len() {
            if self.used_track[k] {
                k += 1;
                continue;
            }
            let tr = &mut self.tracks[k];
            tr.contact.missed += 1;
            if tr.contact.missed > cfg.max_missed {
                self.tracks.swap_remove(k);
                self.used_track.swap_remove(k);
                continue;
            }
            if let (Some(f), Some(filters)) = (cfg.filter, tr.filters.as_mut()) {
                apply_filter(filters, &mut tr.contact, dt, &f, false);
            }
            k += 1;
        }
        // Unmatched detections strong enough start new tracks.
        for (d, det) in detections.iter().enumerate() {
            if self.used_det[d] || det.raw.strength < cfg.start_strength {
                continue;
            }
            let mut contact = *det;
            contact.id = self.next_id;
            contact.missed = 0;
            self.next_id += 1;
            let filters = cfg.filter.map(|f| {
                let l = f.location_sigma_mm;
                let n = f.force_sigma_n;
                let [x, y, z] = contact.location_mm;
                let [fx, fy, fz] = contact.force_n;
                [
                    Cv1::new(x, l),
                    Cv1::new(y, l),
                    Cv1::new(z, l),
                    Cv1::new(fx, n),
                    Cv1::new(fy, n),
                    Cv1::new(fz, n),
                ]
            });
            self.tracks.push(Track { contact, filters });
        }
        self.tracks.sort_by_key(|t| t.contact.id);
        self.out.clear();
        self.out.extend(self.tracks.iter().map(|t| t.contact));
        &self.out
    }
}

fn apply_filter(
    filters: &mut [Cv1; 6],
    c: &mut Contact,
    dt: f64,
    f: &FilterConfig,
    measured: bool,
) {
    for k in 0..6 {
        let (sigma, accel) = if k < 3 {
            (f.location_sigma_mm, f.location_accel)
        } else {
            (f.force_sigma_n, f.force_accel)
        };
        let flt = &mut filters[k];
        flt.predict(dt, accel);
        if measured {
            let z = if k < 3 {
                c.location_mm[k]
            } else {
                c.force_n[k - 3]
            };
            flt.update(z, sigma);
        }
        if k < 3 {
            c.location_mm[k] = flt.x;
        } else {
            c.force_n[k - 3] = flt.x;
        }
    }
}

/// When to take a fresh reference frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct ReferencePolicy {
    /// Whether re-referencing happens at all.
    pub enabled: bool,
    /// Seconds of continuous quiet (no contact, small flow) before re-referencing.
    pub quiet_s: f64,
    /// Largest flow magnitude (full-resolution px) that still counts as quiet:
    /// drift is slow and small, a touch is not. The sensor compares it with
    /// the largest mean `|flow|` over 16x16-pixel tiles
    /// ([`max_tile_mean`](crate::sensor::max_tile_mean)), not with the single
    /// largest pixel, which at rest is border noise.
    ///
    /// The default, 1.25 px, sits above the default (`fine`) flow's rest
    /// noise: on the simulator, over seeds 1-3 and read noise 1, 1.5 and 2
    /// grey levels (100 rest frames each), that statistic reached 0.97 px at
    /// most (99th percentiles 0.33-0.85 px; `camera_check` in
    /// docs/results.md). A real camera's rest noise of 0.4-1.0 px fits under
    /// it; a noisier one needs its own limit. The statistic cannot tell a
    /// light press from that noise (a 1 N press reaches 0.3-0.8 px): a
    /// detected contact, not the flow, is what keeps the sensor from
    /// re-referencing under a touch.
    pub max_flow_px: f64,
}

impl Default for ReferencePolicy {
    fn default() -> Self {
        ReferencePolicy {
            enabled: true,
            quiet_s: 2.0,
            max_flow_px: 1.25,
        }
    }
}

impl ReferencePolicy {
    /// This configuration with `enabled` set (whether re-referencing happens at all).
    pub fn with_enabled(mut self, enabled: bool) -> Self {
        self.enabled = enabled;
        self
    }

    /// This configuration with `quiet_s` set (seconds of quiet before re-referencing).
    pub fn with_quiet_s(mut self, quiet_s: f64) -> Self {
        self.quiet_s = quiet_s;
        self
    }

    /// This configuration with `max_flow_px` set (the largest flow that counts as quiet).
    pub fn with_max_flow_px(mut self, max_flow_px: f64) -> Self {
        self.max_flow_px = max_flow_px;
        self
    }
}

/// Applies a [`ReferencePolicy`] frame by frame.
#[derive(Debug, Clone)]
pub struct ReferenceMonitor {
    policy: ReferencePolicy,
    quiet_since: Option<f64>,
}

impl ReferenceMonitor {
    /// A monitor that has seen nothing yet.
    pub fn new(policy: ReferencePolicy) -> Result<Self> {
        if !(policy.quiet_s.is_finite() && policy.quiet_s >= 0.0) {
            return Err(Error::param(
                "quiet_s",
                format!("must be >= 0, got {}", policy.quiet_s),
            ));
        }
        if !(policy.max_flow_px.is_finite() && policy.max_flow_px >= 0.0) {
            return Err(Error::param(
                "max_flow_px",
                format!("must be >= 0, got {}", policy.max_flow_px),
            ));
        }
        Ok(ReferenceMonitor {
            policy,
            quiet_since: None,
        })
    }

    /// The policy.
    pub fn policy(&self) -> &ReferencePolicy {
        &self.policy
    }

    /// Whether [`observe`](Self::observe) reads its flow magnitude for a
    /// frame with `live_contacts` live contacts: only when the policy is on
    /// and nothing touches (otherwise the frame is not quiet, or not
    /// watched, whatever the flow). A caller may then skip measuring it and
    /// pass any value, such as NaN.
    pub fn reads_flow(&self, live_contacts: usize) -> bool {
        self.policy.enabled && live_contacts == 0
    }

    /// Feeds one frame: its time, the number of live contacts (held ones
    /// included) and its largest flow magnitude. Returns `true` when this frame
    /// should become the new reference; the quiet clock then starts again.
    pub fn observe(&mut self, t_s: f64, live_contacts: usize, max_flow_px: f64) -> bool {
        if !self.policy.enabled {
            return false;
        }
        let quiet =
            live_contacts == 0 && max_flow_px.is_finite() && max_flow_px <= self.policy.max_flow_px;
        if !quiet {
            self.quiet_since = None;
            return false;
        }
        let since = *self.quiet_since.get_or_insert(t_s);
        if t_s - since >= self.policy.quiet_s {
            self.quiet_since = Some(t_s);
            true
        } else {
            false
        }
    }

    /// Forgets the quiet time so far (e.g. after an explicit new reference).
    pub fn reset(&mut self) {
        self.quiet_since = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flow_the_monitor_does_not_read_changes_nothing() {
        // Wherever `reads_flow` is false, NaN in place of the flow gives the
        // same answers and leaves the same state, frame after frame.
        for enabled in [false, true] {
            let policy = ReferencePolicy {
                enabled,
                quiet_s: 0.05,
                max_flow_px: 0.1,
                ..Default::default()
            };
            let (mut a, mut b) = (
                ReferenceMonitor::new(policy).unwrap(),
                ReferenceMonitor::new(policy).unwrap(),
            );
            for k in 0..40 {
                let t = 0.02 * k as f64;
                let live = [0, 0, 0, 1, 0, 0, 0, 0, 2, 0][k % 10];
                let flow = [0.01, 0.5, 0.02, 0.03, 0.0][k % 5];
                let skipped = if a.reads_flow(live) { flow } else { f64::NAN };
                assert_eq!(
                    a.observe(t, live, skipped),
                    b.observe(t, live, flow),
                    "frame {k}"
                );
                assert_eq!(a.quiet_since, b.quiet_since);
            }
        }
    }

    fn det(x: f64, fz: f64, strength: f64) -> Contact {
        let mut c = Contact {
            location_mm: [x, 0.0, 150.0],
            force_n: [0.0, 0.0, fz],
            ..Default::default()
        };
        c.raw.strength = strength;
        c
    }

    #[test]
    fn identities_follow_contacts_and_new_ones_get_new_ids() {
        let mut t = Tracker::new(TrackerConfig::default()).unwrap();
        let a = t
            .update(&[det(-50.0, -1.0, 1.0), det(40.0, -1.0, 1.0)], 0.02)
            .to_vec();
        assert_eq!(a.iter().map(|c| c.id).collect::<Vec<_>>(), [1, 2]);
        // They move a little and come in the other order; a third appears.
        let b = t
            .update(
                &[
                    det(43.0, -1.0, 1.0),
                    det(-48.0, -1.0, 1.0),
                    det(0.0, -1.0, 1.0),
                ],
                0.02,
            )
            .to_vec();
        let by_id = |id: u64| b.iter().find(|c| c.id == id).unwrap().location_mm[0];
        assert_eq!((by_id(1), by_id(2), by_id(3)), (-48.0, 43.0, 0.0));
    }

    #[test]
    fn a_jump_beyond_the_gate_is_a_new_contact() {
        let mut t = Tracker::new(TrackerConfig {
            max_missed: 0,
            ..Default::default()
        })
        .unwrap();
        t.update(&[det(0.0, -1.0, 1.0)], 0.02);
        let b = t.update(&[det(30.0, -1.0, 1.0)], 0.02);
        assert_eq!(b.len(), 1);
        assert_eq!(b[0].id, 2);
    }

    #[test]
    fn hysteresis_holds_a_contact_through_a_dropout() {
        let cfg = TrackerConfig {
            start_strength: 10.0,
            keep_strength: 4.0,
            max_missed: 2,
            ..Default::default()
        };
        let mut t = Tracker::new(cfg).unwrap();
        // Too weak to start.
        assert!(t.update(&[det(0.0, -0.3, 5.0)], 0.02).is_empty());
        assert_eq!(t.update(&[det(0.0, -1.0, 12.0)], 0.02).len(), 1);
        // Weaker but above keep: continues with the same id.
        let c = t.update(&[det(0.5, -0.6, 5.0)], 0.02)[0];
        assert_eq!((c.id, c.missed), (1, 0));
        // Missing for two frames: held with its last value.
        for k in 1..=2 {
            let c = t.update(&[], 0.02)[0];
            assert_eq!((c.id, c.missed, c.force_n[2]), (1, k, -0.6));
        }
        // Back: same id.
        assert_eq!(t.update(&[det(0.2, -0.7, 6.0)], 0.02)[0].id, 1);
        // Gone for three frames: ends.
        t.update(&[], 0.02);
        t.update(&[], 0.02);
        assert!(t.update(&[], 0.02).is_empty());
        assert_eq!(t.live(), 0);
    }

    #[test]
    fn the_filter_smooths_noise_and_follows_a_ramp() {
        let cfg = TrackerConfig {
            filter: Some(FilterConfig::default()),
            ..Default::default()
        };
        let mut t = Tracker::new(cfg).unwrap();
        let mut rng = 12345u64;
        let mut noise = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % 2001) as f64 / 1000.0 - 1.0
        };
        let (mut raw_err, mut flt_err) = (0.0, 0.0);
        for k in 0..200 {
            let truth = -0.5 - 0.01 * k as f64; // a force ramp, N
            let z = truth + 0.05 * noise();
            let out = t.update(&[det(10.0 + 0.3 * noise(), z, 1.0)], 0.02)[0];
            if k >= 50 {
                raw_err += (z - truth).abs();
                flt_err += (out.force_n[2] - truth).abs();
            }
        }
        assert!(
            flt_err < 0.7 * raw_err,
            "filtered {flt_err} vs raw {raw_err}"
        );
    }

    #[test]
    fn bad_configs_are_errors() {
        let bad = TrackerConfig {
            gate_mm: 0.0,
            ..Default::default()
        };
        assert!(Tracker::new(bad).is_err());
        let bad = TrackerConfig {
            start_strength: 1.0,
            keep_strength: 2.0,
            ..Default::default()
        };
        assert!(Tracker::new(bad).is_err());
        let bad = TrackerConfig {
            filter: Some(FilterConfig {
                force_sigma_n: f64::NAN,
                ..Default::default()
            }),
            ..Default::default()
        };
        assert!(Tracker::new(bad).is_err());
        assert!(
            ReferenceMonitor::new(ReferencePolicy {
                quiet_s: -1.0,
                ..Default::default()
            })
            .is_err()
        );
    }

    #[test]
    fn re_reference_only_after_quiet_time_and_never_while_touched() {
        let mut m = ReferenceMonitor::new(ReferencePolicy {
            enabled: true,
            quiet_s: 1.0,
            max_flow_px: 0.5,
        })
        .unwrap();
        let mut fired = Vec::new();
        for k in 0..400 {
            let t = k as f64 * 0.02;
            // Touched from 1 s to 3 s; large flow at 5 s.
            let touching = (1.0..3.0).contains(&t);
            let flow = if (5.0..5.1).contains(&t) { 2.0 } else { 0.1 };
            if m.observe(t, touching as usize, flow) {
                assert!(!touching);
                fired.push(t);
            }
        }
        // Quiet from 0, then 3-5, then 5.1-8: fires at 1.0? No: touched at 1.0.
        // First quiet stretch [0, 1) never reaches 1 s. Then at 4.0, then 6.1, 7.1.
        let want = [4.0, 6.1, 7.1];
        assert_eq!(fired.len(), want.len(), "{fired:?}");
        for (a, b) in fired.iter().zip(want) {
            assert!((a - b).abs() < 1e-9, "{fired:?}");
        }
        let mut off = ReferenceMonitor::new(ReferencePolicy {
            enabled: false,
            ..Default::default()
        })
        .unwrap();
        assert!((0..1000).all(|k| !off.observe(k as f64, 0, 0.0)));
    }
}
