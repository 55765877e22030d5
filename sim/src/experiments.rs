//! Experiments on the simulator: false contacts on rest frames, the minimum
//! detectable force, the two-contact spacing sweep, and the touch-mapping
//! error. Shared by the developer tool `sweep` (exploring thresholds) and
//! `examples/experiments.rs` (the paper's sensor-performance section). The
//! library prints nothing: progress and debug lines go to callbacks.
//!
//! Frames are rendered with [`SyntheticSensor::render_indexed`] (no PNGs) and
//! go through the sensor's default DIS flow (`fine`) on the extractor's
//! analysis grid, as in [`ContactExtractor`]. Every frame index is fixed by the condition it
//! belongs to, so the results do not depend on the thread count: conditions
//! run in parallel, each worker with its own flow and segmenters.
//!
//! - [`rest_sweep`]: a reference against another unloaded frame with fresh
//!   noise and flicker; any patch is a false contact.
//! - [`mdf_sweep`]: single rods pressed with a force ladder at several arc
//!   positions and the characterization protocol's five tilts; detected = a
//!   patch whose box covers the rod's column.
//! - [`spacing_sweep`]: two straight rods of equal force at decreasing
//!   spacing; told apart = exactly two contacts, each within a tolerance of
//!   its rod ([`pair_told_apart`]).
//! - [`mapping_run`]: the touch-mapping demo end to end: the `mapping`
//!   scenario, a [`TactileSensor`] over its frames, contacts into the world
//!   frame and clusters ([`crate::mapping::map_touches`], as the
//!   `touch_mapping` example), and their error against the true rods.

use std::path::Path;

use rayon::prelude::*;
use serde::Serialize;

use super::scenario::{self, Common, Mapping, Scenario, tilted_force};
use super::sensor::{Press, SyntheticSensor};
pub use crate::mapping::ClusterSummary;
use crate::mapping::{
    Cluster, MapOptions, map_touches, match_rods, poses_by_frame, read_rods_json,
};
use optical_tactile::calibration::Calibration;
use optical_tactile::contact::{ContactLocator, ContactPointMethod};
use optical_tactile::error::{Error, Result};
use optical_tactile::flow::dis::Dis;
use optical_tactile::io::{self, FrameRecord};
use optical_tactile::segment::{ContactPatch, Segmenter, SegmenterConfig, Thresholds};
use optical_tactile::sensor::{
    AnalysisGrid, ContactExtractor, ExtractorConfig, QUIET_MIN_TEXTURE, QUIET_TILE_PX,
    SensorConfig, TactileSensor, textured_tiles_into,
};

/// The characterization protocol's indenters and tilts, which the sweeps
/// run through.
pub use super::scenario::{INDENTERS_MM, TILTS_DEG};

/// First frame index of the rest pairs: far from the other sweeps' so that
/// their noise is fresh.
const REST_BASE: u64 = 1_000_000;
/// First frame index of the spacing sweep.
const SPACING_BASE: u64 = 2_000_000;

/// A named set of segmentation thresholds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ThresholdSet {
    /// Name printed in the tables (`LOW`, `MID`, `HIGH`, or a candidate).
    pub name: String,
    /// The thresholds (full-resolution pixels).
    pub thresholds: Thresholds,
}

impl ThresholdSet {
    /// The three presets `LOW`, `MID`, `HIGH`, in that order.
    pub fn presets() -> Vec<ThresholdSet> {
        [
            ("LOW", Thresholds::LOW),
            ("MID", Thresholds::MID),
            ("HIGH", Thresholds::HIGH),
        ]
        .into_iter()
        .map(|(name, thresholds)| ThresholdSet {
            name: name.to_string(),
            thresholds,
        })
        .collect()
    }
}

/// Options shared by the sweeps.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepOptions {
    /// The threshold sets evaluated on the same flows.
    pub sets: Vec<ThresholdSet>,
    /// Patch margin, full-resolution px (as [`ExtractorConfig::margin_px`]).
    pub margin_px: usize,
    /// Where to send one line per missed press (from 0.8 N) and per
    /// spacing case, with its patches and contour boxes (`None`: nowhere).
    pub debug: Option<DebugLog>,
}

/// A sink for the sweeps' debug lines (the library prints nothing): called
/// once per line, from worker threads, e.g. `DebugLog(|l| eprintln!("{l}"))`.
#[derive(Clone, Copy)]
pub struct DebugLog(pub fn(&str));

impl DebugLog {
    fn line(&self, line: &str) {
        (self.0)(line)
    }
}

impl std::fmt::Debug for DebugLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("DebugLog(..)")
    }
}

impl PartialEq for DebugLog {
    fn eq(&self, other: &Self) -> bool {
        std::ptr::fn_addr_eq(self.0, other.0)
    }
}

impl Default for SweepOptions {
    /// The presets, the extractor's default margin, no debug output.
    fn default() -> Self {
        SweepOptions {
            sets: ThresholdSet::presets(),
            margin_px: ExtractorConfig::default().margin_px,
            debug: None,
        }
    }
}

impl SweepOptions {
    fn check(&self) -> Result<()> {
        if self.sets.is_empty() {
            return Err(Error::param("sets", "need at least one threshold set"));
        }
        for s in &self.sets {
            s.thresholds.validate()?;
        }
        Ok(())
    }
}

/// Progress callback: `(stage, done, total)`, called from worker threads.
pub use super::scenario::{Progress, no_progress};

/// A worker thread's state, built on its first use (an error, not a panic,
/// if that fails).
fn worker<T>(slot: &mut Option<T>, make: impl FnOnce() -> Result<T>) -> Result<&mut T> {
    if slot.is_none() {
        *slot = Some(make()?);
    }
    Ok(slot.as_mut().expect("just filled"))
}

/// Image column (full-resolution strip pixels) of a rod at arc position `s` mm.
pub fn rod_px(sensor: &SyntheticSensor, s: f64) -> f64 {
    let c = sensor.config();
    c.camera.s_to_px(&c.skin, s)
}

/// Does a patch (native-resolution box) cover column `x_px` (full resolution)?
fn covers(p: &ContactPatch, scale: f64, x_px: f64) -> bool {
    let x0 = p.bbox.x as f64 * scale;
    let x1 = (p.bbox.x + p.bbox.width) as f64 * scale;
    (x0..=x1).contains(&x_px)
}

/// One DIS (the sensor's default preset) and one segmenter per threshold
/// set, run on the same flow on the extractor's analysis grid.
struct Bench {
    dis: Dis,
    grid: AnalysisGrid,
    segs: Vec<Segmenter>,
    patches: Vec<ContactPatch>,
}

impl Bench {
    fn new(o: &SweepOptions) -> Result<Self> {
        let params = ExtractorConfig::default().flow;
        let grid = AnalysisGrid::new(params.finest_scale);
        let scale = grid.scale() as f64;
        let segs = o
            .sets
            .iter()
            .map(|s| {
                Segmenter::new(SegmenterConfig {
                    thresholds: s.thresholds,
                    margin: o.margin_px,
                    scale,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Bench {
            dis: Dis::new(params)?,
            grid,
            segs,
            patches: Vec::new(),
        })
    }

    /// Sets the reference, and each segmenter's observable region as the
    /// extractor does.
    fn set_reference(&mut self, reference: &ndarray::Array2<f32>) -> Result<()> {
        self.dis.set_reference(reference)?;
        let observable = self.grid.observable(&self.dis);
        for seg in &mut self.segs {
            seg.set_observable(observable.clone());
        }
        Ok(())
    }

    /// Full-resolution pixels per pixel of the analysis grid.
    fn scale(&self) -> f64 {
        self.grid.scale() as f64
    }

    /// Computes the flow of `frame` against the current reference, then calls
    /// `f(set index, patches, segmenter)` for every threshold set.
    fn each(
        &mut self,
        frame: &ndarray::Array2<f32>,
        mut f: impl FnMut(usize, &[ContactPatch], &Segmenter),
    ) -> Result<()> {
        self.dis.compute_native(frame)?;
        let (native, _) = self.dis.native_flow().ok_or(Error::NoReference)?;
        let flow = self.grid.update(native)?;
        for (k, seg) in self.segs.iter_mut().enumerate() {
            seg.segment_into(flow, &mut self.patches)?;
            f(k, &self.patches, seg);
        }
        Ok(())
    }

    /// Largest `|flow|` of the last frame, full-resolution pixels, over the
    /// skin's interior: the cells whose `tile_px` tile of the reference and
    /// its 8 neighbours are all textured (`textured` from
    /// [`textured_tiles_into`], `tiles_x` tiles per row). On the black strip
    /// ends the flow is not measurable and DIS fills in what its coarse
    /// levels guessed; a tile on the skin's edge holds both, and the
    /// full-resolution `fine` flow put up to 1.3 px there at rest.
    fn peak(&self, textured: &[bool], tiles_x: usize, tile_px: usize) -> f64 {
        let (flow, scale) = self.grid.flow();
        let tiles_y = textured.len().div_ceil(tiles_x.max(1));
        let inside = |ty: usize, tx: usize| {
            (ty.saturating_sub(1)..=(ty + 1).min(tiles_y - 1)).all(|y| {
                (tx.saturating_sub(1)..=(tx + 1).min(tiles_x - 1))
                    .all(|x| textured.get(y * tiles_x + x).copied().unwrap_or(true))
            })
        };
        let mut best = 0.0f64;
        for ((r, c), u) in flow.u.indexed_iter() {
            if tiles_x == 0 || inside(r * scale / tile_px, c * scale / tile_px) {
                best = best.max(f64::from(u.hypot(flow.v[[r, c]])));
            }
        }
        best
    }
}

/// False contacts on rest pairs, per threshold set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RestResult {
    /// The threshold sets, in the order of the per-set vectors.
    pub sets: Vec<ThresholdSet>,
    /// Number of rest pairs.
    pub pairs: usize,
    /// Per set: rest pairs with at least one patch.
    pub false_frames: Vec<usize>,
    /// Per set: patches found in all rest pairs.
    pub false_patches: Vec<usize>,
    /// Per set: the largest contour sum (full-resolution px^3) seen at rest,
    /// how far below the sum threshold the noise stays.
    pub max_contour_sum: Vec<f64>,
    /// Peak `|flow|` of every rest pair over the textured skin
    /// (full-resolution px), ascending.
    pub peaks_px: Vec<f64>,
}

impl RestResult {
    /// The `p`-quantile (0..=1) of the per-pair peak `|flow|`, px.
    pub fn peak_quantile(&self, p: f64) -> f64 {
        let n = self.peaks_px.len();
        if n == 0 {
            return f64::NAN;
        }
        self.peaks_px[((p.clamp(0.0, 1.0) * n as f64) as usize).min(n - 1)]
    }
}

/// Runs `pairs` rest pairs (frame indices from 1 000 000 on).
pub fn rest_sweep(
    sensor: &SyntheticSensor,
    o: &SweepOptions,
    pairs: usize,
    progress: Progress<'_>,
) -> Result<RestResult> {
    o.check()?;
    if pairs == 0 {
        return Err(Error::param("pairs", "need at least one rest pair"));
    }
    let n = o.sets.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    // Per pair: (false patches per set, max contour sum per set, peak).
    let per: Vec<(Vec<usize>, Vec<f64>, f64)> = (0..pairs as u64)
        .into_par_iter()
        .map_init(
            || (None, Vec::new()),
            |(slot, textured): &mut (Option<Bench>, Vec<bool>), k| {
                let bench = worker(slot, || Bench::new(o))?;
                let r = sensor.render_indexed(REST_BASE + 2 * k, &[], false)?;
                let f = sensor.render_indexed(REST_BASE + 2 * k + 1, &[], false)?;
                bench.set_reference(&r.frame)?;
                let tiles_x =
                    textured_tiles_into(&r.frame, QUIET_TILE_PX, QUIET_MIN_TEXTURE, textured);
                let mut patches = vec![0usize; n];
                let mut sums = vec![0.0f64; n];
                let s3 = bench.scale().powi(3);
                bench.each(&f.frame, |i, p, seg| {
                    patches[i] = p.len();
                    sums[i] = seg.contour_sums().iter().copied().fold(0.0, f64::max) * s3;
                })?;
                let peak = bench.peak(textured, tiles_x, QUIET_TILE_PX);
                progress(
                    "rest",
                    done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
                    pairs,
                );
                Ok((patches, sums, peak))
            },
        )
        .collect::<Result<_>>()?;
    let mut out = RestResult {
        sets: o.sets.clone(),
        pairs,
        false_frames: vec![0; n],
        false_patches: vec![0; n],
        max_contour_sum: vec![0.0; n],
        peaks_px: per.iter().map(|p| p.2).collect(),
    };
    for (patches, sums, _) in &per {
        for i in 0..n {
            out.false_frames[i] += usize::from(patches[i] > 0);
            out.false_patches[i] += patches[i];
            out.max_contour_sum[i] = out.max_contour_sum[i].max(sums[i]);
        }
    }
    out.peaks_px.sort_by(f64::total_cmp);
    Ok(out)
}

/// The presses of the minimum-detectable-force sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MdfPlan {
    /// Arc positions of the presses, mm from the centre.
    pub positions_mm: Vec<f64>,
    /// The force ladder, N, ascending.
    pub forces_n: Vec<f64>,
}

impl Default for MdfPlan {
    /// 7 positions from -120 to 120 mm, forces 0.1..=2.0 N by 0.1 N.
    fn default() -> Self {
        MdfPlan {
            positions_mm: vec![-120.0, -80.0, -40.0, 0.0, 40.0, 80.0, 120.0],
            forces_n: (1..=20).map(|k| k as f64 / 10.0).collect(),
        }
    }
}

/// Detections of the minimum-detectable-force sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MdfResult {
    /// The threshold sets.
    pub sets: Vec<ThresholdSet>,
    /// The presses.
    pub plan: MdfPlan,
    /// Presses per (indenter, force): positions x tilts.
    pub per: usize,
    /// `hits[set][indenter][force]`: presses detected (a patch covering the rod).
    pub hits: Vec<Vec<Vec<usize>>>,
    /// Per set: patches in loaded frames that do not cover the rod.
    pub stray: Vec<usize>,
}

impl MdfResult {
    /// The smallest ladder force from which every larger one is detected in
    /// at least `rate` of the presses, for one indenter (index into
    /// [`INDENTERS_MM`]) or, with `None`, the largest over the indenters.
    /// `None` if even the top of the ladder misses.
    pub fn min_force(&self, set: usize, indenter: Option<usize>, rate: f64) -> Option<f64> {
        match indenter {
            Some(i) => {
                let h = &self.hits[set][i];
                let mut best = None;
                for fi in (0..self.plan.forces_n.len()).rev() {
                    if h[fi] as f64 >= rate * self.per as f64 - 1e-9 {
                        best = Some(self.plan.forces_n[fi]);
                    } else {
                        break;
                    }
                }
                best
            }
            None => (0..INDENTERS_MM.len())
                .map(|i| self.min_force(set, Some(i), rate))
                .try_fold(0.0f64, |m, v| v.map(|v| m.max(v))),
        }
    }

    /// Fraction of all presses (every indenter) detected at force index `fi`.
    pub fn rate(&self, set: usize, fi: usize) -> f64 {
        let h: usize = self.hits[set].iter().map(|h| h[fi]).sum();
        h as f64 / (self.hits[set].len() * self.per) as f64
    }
}

/// Runs the minimum-detectable-force sweep: per indenter, position and tilt
/// one fresh reference (frame index `c * (1 + forces)` for condition `c`)
/// and a fresh frame per force.
pub fn mdf_sweep(
    sensor: &SyntheticSensor,
    o: &SweepOptions,
    plan: &MdfPlan,
    progress: Progress<'_>,
) -> Result<MdfResult> {
    o.check()?;
    let nf = plan.forces_n.len();
    if nf == 0 || plan.positions_mm.is_empty() {
        return Err(Error::param("plan", "need at least one force and position"));
    }
    if plan.forces_n.iter().any(|f| !(f.is_finite() && *f >= 0.0))
        || plan.forces_n.windows(2).any(|w| w[1] <= w[0])
    {
        return Err(Error::param(
            "forces_n",
            "forces must be finite, >= 0 and strictly ascending",
        ));
    }
    let skin = &sensor.config().skin;
    for &s in &plan.positions_mm {
        if !(s.is_finite() && s.abs() <= skin.half_length()) {
            return Err(Error::param(
                "positions_mm",
                format!("arc position {s} mm is off the skin"),
            ));
        }
    }
    let n = o.sets.len();
    let np = plan.positions_mm.len();
    let conds = INDENTERS_MM.len() * np * TILTS_DEG.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    // Per condition: hits[set][force] and stray patches per set.
    type Cond = (Vec<Vec<bool>>, Vec<usize>);
    let per: Vec<Cond> = (0..conds)
        .into_par_iter()
        .map_init(
            || None,
            |slot: &mut Option<Bench>, c| -> Result<Cond> {
                let bench = worker(slot, || Bench::new(o))?;
                let (ii, rest) = (c / (np * TILTS_DEG.len()), c % (np * TILTS_DEG.len()));
                let (pi, ti) = (rest / TILTS_DEG.len(), rest % TILTS_DEG.len());
                let (d, s, (yaw, pitch)) = (INDENTERS_MM[ii], plan.positions_mm[pi], TILTS_DEG[ti]);
                let x = skin.arc_to_chord(s);
                let xp = rod_px(sensor, s);
                let mut idx = (c * (1 + nf)) as u64;
                let r = sensor.render_indexed(idx, &[], false)?;
                idx += 1;
                bench.set_reference(&r.frame)?;
                let mut hit = vec![vec![false; nf]; n];
                let mut stray = vec![0usize; n];
                let scale = bench.scale();
                for (fi, &f) in plan.forces_n.iter().enumerate() {
                    let rod = Press::rod(x, tilted_force(f, yaw, pitch), d);
                    let fr = sensor.render_indexed(idx, &[rod], false)?;
                    idx += 1;
                    bench.each(&fr.frame, |k, p, _| {
                        hit[k][fi] = p.iter().any(|p| covers(p, scale, xp));
                        let away = p.iter().filter(|p| !covers(p, scale, xp)).count();
                        stray[k] += away;
                        if let Some(log) = o.debug.filter(|_| f >= 0.8 && away > 0) {
                            let boxes: Vec<_> = p
                                .iter()
                                .map(|p| (p.bbox.x as f64 * scale, p.bbox.x_end() as f64 * scale))
                                .collect();
                            log.line(&format!(
                                "miss set {k} d {d} s {s} tilt ({yaw},{pitch}) f {f}: rod {xp:.0} boxes {boxes:?}"
                            ));
                        }
                    })?;
                }
                progress(
                    "mdf",
                    done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
                    conds,
                );
                Ok((hit, stray))
            },
        )
        .collect::<Result<_>>()?;
    let mut hits = vec![vec![vec![0usize; nf]; INDENTERS_MM.len()]; n];
    let mut stray = vec![0usize; n];
    for (c, (hit, st)) in per.iter().enumerate() {
        let ii = c / (np * TILTS_DEG.len());
        for k in 0..n {
            for fi in 0..nf {
                hits[k][ii][fi] += usize::from(hit[k][fi]);
            }
            stray[k] += st[k];
        }
    }
    Ok(MdfResult {
        sets: o.sets.clone(),
        plan: plan.clone(),
        per: np * TILTS_DEG.len(),
        hits,
        stray,
    })
}

/// The cases of the two-rod spacing sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpacingPlan {
    /// Spacings along the arc, mm, descending.
    pub spacings_mm: Vec<f64>,
    /// The force of the first (left) rod, N.
    pub forces_n: Vec<f64>,
    /// The second (right) rod's force as a fraction of the first's (1:
    /// equal presses).
    pub second_force_ratio: f64,
    /// Arc positions of the pair's midpoint, mm.
    pub centres_mm: Vec<f64>,
    /// A contact counts for a rod within this distance along the arc, mm.
    pub tol_mm: f64,
}

impl Default for SpacingPlan {
    /// Spacings 40 down to 5 mm, equal forces of 1.5 and 3 N, midpoints -60,
    /// 0, 60 mm, tolerance 3 mm.
    fn default() -> Self {
        SpacingPlan {
            spacings_mm: vec![
                40.0, 35.0, 30.0, 25.0, 20.0, 17.5, 15.0, 12.5, 10.0, 7.5, 5.0,
            ],
            forces_n: vec![1.5, 3.0],
            second_force_ratio: 1.0,
            centres_mm: vec![-60.0, 0.0, 60.0],
            tol_mm: 3.0,
        }
    }
}

/// Results of the spacing sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpacingResult {
    /// The threshold sets.
    pub sets: Vec<ThresholdSet>,
    /// The cases.
    pub plan: SpacingPlan,
    /// `apart[set][indenter][force][spacing][centre]`: told apart?
    pub apart: Vec<Vec<Vec<Vec<Vec<bool>>>>>,
}

impl SpacingResult {
    /// The smallest spacing of the list from which every larger one is told
    /// apart, for one force (or every force with `None`) and one midpoint
    /// (or every midpoint with `None`); `None` if the largest spacing already
    /// fails.
    pub fn min_spacing(
        &self,
        set: usize,
        indenter: usize,
        force: Option<usize>,
        centre: Option<usize>,
    ) -> Option<f64> {
        let forces: Vec<usize> =
            force.map_or_else(|| (0..self.plan.forces_n.len()).collect(), |f| vec![f]);
        let centres: Vec<usize> =
            centre.map_or_else(|| (0..self.plan.centres_mm.len()).collect(), |c| vec![c]);
        let mut best = None;
        for (si, &sp) in self.plan.spacings_mm.iter().enumerate() {
            let ok = forces
                .iter()
                .all(|&f| centres.iter().all(|&c| self.apart[set][indenter][f][si][c]));
            if ok {
                best = Some(sp);
            } else {
                break;
            }
        }
        best
    }

    /// Pairs told apart at spacing index `si` (out of the midpoints).
    pub fn count(&self, set: usize, indenter: usize, force: usize, si: usize) -> usize {
        self.apart[set][indenter][force][si]
            .iter()
            .filter(|&&b| b)
            .count()
    }
}

/// Presses two straight rods of diameter `indenter_mm` with forces
/// `forces_n` (left, right), `spacing_mm` apart along the arc around midpoint `centre_mm`, and
/// tells whether `extractor` finds exactly two contacts, each within
/// `tol_mm` (along the arc) of its rod, its column measured as the shipped
/// calibration does ([`ContactPointMethod::DEFAULT`]). Frames `frame_index` (reference) and
/// `frame_index + 1` (loaded). With `debug`, sends the case to it as one line.
#[allow(clippy::too_many_arguments)]
pub fn pair_told_apart(
    sensor: &SyntheticSensor,
    extractor: &mut ContactExtractor,
    indenter_mm: f64,
    forces_n: [f64; 2],
    spacing_mm: f64,
    centre_mm: f64,
    tol_mm: f64,
    frame_index: u64,
    debug: Option<DebugLog>,
) -> Result<bool> {
    let skin = &sensor.config().skin;
    let (s1, s2) = (centre_mm - 0.5 * spacing_mm, centre_mm + 0.5 * spacing_mm);
    let on_skin = s1.abs().max(s2.abs()) <= skin.half_length();
    if !(spacing_mm.is_finite() && spacing_mm >= 0.0 && centre_mm.is_finite() && on_skin) {
        return Err(Error::param(
            "spacing_mm",
            format!("rods at arc {s1} and {s2} mm: not both on the skin"),
        ));
    }
    if !(tol_mm.is_finite() && tol_mm > 0.0) {
        return Err(Error::param("tol_mm", format!("must be > 0, got {tol_mm}")));
    }
    let rods = [
        Press::rod(skin.arc_to_chord(s1), [0.0, 0.0, -forces_n[0]], indenter_mm),
        Press::rod(skin.arc_to_chord(s2), [0.0, 0.0, -forces_n[1]], indenter_mm),
    ];
    let (p1, p2) = (rod_px(sensor, s1), rod_px(sensor, s2));
    let tol = tol_mm * sensor.config().camera.px_per_mm_s;
    let r = sensor.render_indexed(frame_index, &[], false)?;
    let o = sensor.render_indexed(frame_index + 1, &rods, false)?;
    extractor.set_reference(&r.frame)?;
    extractor.extract(&o.frame)?;
    let raws = extractor.raws();
    if let Some(log) = debug {
        let got: Vec<_> = raws
            .iter()
            .map(|r| (r.x_px.round(), r.bbox.x, r.bbox.x + r.bbox.w))
            .collect();
        let s = extractor.scale();
        let cores: Vec<_> = extractor
            .segmenter()
            .contour_boxes()
            .iter()
            .map(|b| (b.x * s, b.x_end() * s))
            .collect();
        log.line(&format!(
            "d {indenter_mm} f {forces_n:?} sp {spacing_mm} c {centre_mm}: rods {p1:.0} {p2:.0} got {got:?} contours {cores:?}"
        ));
    }
    if raws.len() != 2 {
        return Ok(false);
    }
    // Each contact's column as the shipped calibration measures it (the
    // slope peak), not the patch's potential minimum: that is where the
    // sensor reports the contact.
    let mut raws = [raws[0], raws[1]];
    let (flow, s) = extractor.finest_flow();
    ContactLocator::new().refine(
        ContactPointMethod::DEFAULT,
        &mut raws,
        flow.u.view(),
        flow.v.view(),
        s as f64,
    )?;
    let mut xs = [raws[0].x_px, raws[1].x_px];
    xs.sort_by(f64::total_cmp);
    Ok((xs[0] - p1).abs() <= tol && (xs[1] - p2).abs() <= tol)
}

/// Runs the spacing sweep: every indenter x force x spacing x midpoint, each
/// case with its own frames (indices from 2 000 000 on), every threshold set
/// on the same frames, cases in parallel.
pub fn spacing_sweep(
    sensor: &SyntheticSensor,
    o: &SweepOptions,
    plan: &SpacingPlan,
    progress: Progress<'_>,
) -> Result<SpacingResult> {
    o.check()?;
    let (nf, ns, nc) = (
        plan.forces_n.len(),
        plan.spacings_mm.len(),
        plan.centres_mm.len(),
    );
    if nf == 0 || ns == 0 || nc == 0 {
        return Err(Error::param(
            "plan",
            "need at least one force, spacing and midpoint",
        ));
    }
    let r = plan.second_force_ratio;
    if !(r > 0.0 && r.is_finite()) {
        return Err(Error::param(
            "second_force_ratio",
            format!("must be finite and > 0, got {r}"),
        ));
    }
    let configs: Vec<ExtractorConfig> = o
        .sets
        .iter()
        .map(|s| {
            ExtractorConfig::default()
                .with_thresholds(s.thresholds)
                .with_margin_px(o.margin_px)
        })
        .collect();
    let cases = INDENTERS_MM.len() * nf * ns * nc;
    let done = std::sync::atomic::AtomicUsize::new(0);
    let per: Vec<Vec<bool>> = (0..cases)
        .into_par_iter()
        .map_init(
            || None,
            |slot: &mut Option<Vec<ContactExtractor>>, case| -> Result<Vec<bool>> {
                let exs = worker(slot, || {
                    configs
                        .iter()
                        .map(|c| ContactExtractor::new(c.clone()))
                        .collect::<Result<Vec<_>>>()
                })?;
                let ci = case % nc;
                let si = (case / nc) % ns;
                let fi = (case / (nc * ns)) % nf;
                let ii = case / (nc * ns * nf);
                let mut out = Vec::with_capacity(exs.len());
                for ex in exs.iter_mut() {
                    out.push(pair_told_apart(
                        sensor,
                        ex,
                        INDENTERS_MM[ii],
                        [
                            plan.forces_n[fi],
                            plan.forces_n[fi] * plan.second_force_ratio,
                        ],
                        plan.spacings_mm[si],
                        plan.centres_mm[ci],
                        plan.tol_mm,
                        SPACING_BASE + 2 * case as u64,
                        o.debug,
                    )?);
                }
                progress(
                    "spacing",
                    done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1,
                    cases,
                );
                Ok(out)
            },
        )
        .collect::<Result<_>>()?;
    let n = o.sets.len();
    let mut apart = vec![vec![vec![vec![vec![false; nc]; ns]; nf]; INDENTERS_MM.len()]; n];
    for (case, told) in per.iter().enumerate() {
        let ci = case % nc;
        let si = (case / nc) % ns;
        let fi = (case / (nc * ns)) % nf;
        let ii = case / (nc * ns * nf);
        for k in 0..n {
            apart[k][ii][fi][si][ci] = told[k];
        }
    }
    Ok(SpacingResult {
        sets: o.sets.clone(),
        plan: plan.clone(),
        apart,
    })
}

/// Options of the touch-mapping experiment ([`mapping_run`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MappingOptions {
    /// The simulated sequence (rods, touches, force).
    pub scenario: Mapping,
    /// Contacts into the world frame and clusters ([`map_touches`]).
    pub map: MapOptions,
    /// A cluster farther than this from every rod is a false obstacle, m.
    pub gate_m: f64,
}

impl Default for MappingOptions {
    /// The scenario's defaults (5 rods 0.45-0.6 m apart, 2 touches each, 1.5
    /// N), the `touch_mapping` example's [`MapOptions`] (contacts from 0.5 N,
    /// clustering radius 0.05 m), gate 0.2 m.
    fn default() -> Self {
        MappingOptions {
            scenario: Mapping::default(),
            map: MapOptions::default(),
            gate_m: 0.2,
        }
    }
}

/// The result of one touch-mapping run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MappingRun {
    /// The simulator seed.
    pub seed: u64,
    /// World contacts that entered the clustering.
    pub contacts: usize,
    /// The obstacle estimates.
    pub clusters: Vec<ClusterSummary>,
    /// Per true rod, the distance of its matched cluster from the rod's line,
    /// m (`None`: no cluster within the gate).
    pub errors_m: Vec<Option<f64>>,
    /// Clusters matched to no rod.
    pub false_clusters: usize,
}

impl MappingRun {
    /// The largest error over the rods, `None` if a rod was missed.
    pub fn worst_m(&self) -> Option<f64> {
        self.errors_m
            .iter()
            .try_fold(0.0f64, |m, e| e.map(|e| m.max(e)))
    }

    /// The mean error over the rods that were found (`NaN` if none).
    pub fn mean_m(&self) -> f64 {
        let found: Vec<f64> = self.errors_m.iter().flatten().copied().collect();
        found.iter().sum::<f64>() / found.len() as f64
    }
}

/// Simulates the `mapping` scenario with `seed` into `dir` (PNGs, `poses.csv`,
/// `rods.json`, `truth.jsonl`), runs a [`TactileSensor`] with `calibration` over the frames
/// (frame 0 is the reference; its crop, thresholds and flow preset come from
/// the calibration; the contacts detected in each frame are written to
/// `dir/contacts.jsonl`), puts every contact into the world frame with the pose
/// of its frame, clusters them, and matches the clusters with the true rods.
pub fn mapping_run(
    calibration: &Calibration,
    seed: u64,
    dir: &Path,
    o: &MappingOptions,
) -> Result<MappingRun> {
    let mut common = Common::new(dir);
    common.seed = seed;
    common.flow = false;
    scenario::run(&Scenario::Mapping(o.scenario.clone()), &common)?;
    let poses_path = dir.join("poses.csv");
    let poses = poses_by_frame(&io::read_poses_csv(&poses_path)?, &poses_path)?;
    let truth = read_rods_json(dir.join("rods.json"))?;
    let mut config = SensorConfig::default();
    config.extractor = ExtractorConfig::from_setup(&calibration.setup)?;
    let mut sensor = TactileSensor::new(config, calibration.clone())?;
    let mut records = Vec::new();
    for (k, path) in io::list_frames(dir)?.iter().enumerate() {
        let img = io::read_gray(path)?;
        if k == 0 {
            sensor.set_reference(&img)?;
            continue;
        }
        let t_s = k as f64 / common.fps;
        let contacts = sensor.process(&img, t_s)?;
        records.push(FrameRecord {
            frame: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            t_s,
            // Only contacts detected in this frame: a held one (`missed > 0`,
            // the tracker's hysteresis) repeats an earlier frame's estimate,
            // and this frame's pose (the body already lifted or moved on)
            // would put it in the wrong place.
            contacts: contacts
                .iter()
                .filter(|c| c.missed == 0)
                .map(|c| c.to_record())
                .collect(),
            latency_ms: None,
        });
    }
    // What the sensor saw, for inspection beside the scenario's truth.jsonl.
    let mut w = io::JsonlWriter::create(dir.join("contacts.jsonl"))?;
    for r in &records {
        w.write(r)?;
    }
    drop(w);
    let map = map_touches(&records, &poses, &truth.mounting, &o.map, &poses_path)?;
    let clusters = map.clusters;
    let matches = match_rods(&clusters, &truth.rods, o.gate_m)?;
    let matched = matches.iter().filter(|m| m.cluster.is_some()).count();
    Ok(MappingRun {
        seed,
        contacts: map.touches.len(),
        clusters: clusters.iter().map(Cluster::summary).collect(),
        errors_m: matches.iter().map(|m| m.error_m).collect(),
        false_clusters: clusters.len() - matched,
    })
}
