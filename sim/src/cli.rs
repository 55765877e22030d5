//! Command-line parsing for the `simulate` example (hand-written, no clap), kept
//! in the library so that its errors are tested like everything else.

use std::path::PathBuf;

use super::scenario::{
    Characterization, Common, Mapping, Pair, Perches, Presses, Scenario, Single,
};
use optical_tactile::error::{Error, Result};

/// The `--help` text: every scenario and option.
pub const HELP: &str = "\
simulate: synthetic optical tactile sensor frames with ground truth

USAGE:
    cargo run --release --example simulate -- <SCENARIO> --out DIR [OPTIONS]
    cargo run --release --example simulate -- fixtures [--out fixtures] [--docs docs/img]

SCENARIOS:
    single            one indenter, force ramp (frame 0 unloaded), optional tilt
    pair              two indenters at a given spacing, force ramps
    presses           independent presses at random places, forces, tilts and
                      rods, each frame against frame 0 (accuracy between the
                      protocol's points)
    characterization  the characterization protocol (tests.csv + frames/), SPEC.md
    perches           two rods of different stiffness under a descending body
    mapping           touch, move, touch over rods at known world positions (poses.csv, rods.json)
    fixtures          the repository's fixtures (a two-contact press and a
                      characterization subset) and, with --docs, the README pictures

COMMON OPTIONS:
    --out DIR            output folder (created; required except for `fixtures`)
    --seed N             seed for markers, noise and random choices [1]
    --flow / --no-flow   write the true dense motion as flow/*.flo
                         [on, except for characterization]
    --fps F              frame rate for time stamps [50]
    --full-frame         render the full 1920x1080 camera frame with the strip
                         inside it (crop printed) instead of the 1600x200 strip
    --youngs-kpa E       gel Young's modulus, kPa [40]
    --poisson NU         gel Poisson's ratio [0.47]
    --layer-mm T         gel layer thickness over the rigid plate, mm [8]
    --coverage C         fraction of the image covered by markers [0.3]
    --markers N          exact number of markers (overrides --coverage)
    --noise-read S       read-noise standard deviation, grey levels [1.0]
    --flicker S          relative per-frame brightness flicker [0.01]
    -h, --help           this text

single:
    --x-mm X             chord position, mm [0]
    --force-n F          peak force magnitude, N [2]
    --frames N           frames including the reference [10]
    --indenter-mm D      rod diameter, mm [5]
    --pitch-deg P        force tilt in the x-z plane, deg [0]
    --yaw-deg Y          force tilt in the y-z plane, deg [0]
pair:
    --x-mm X             chord position of the midpoint, mm [0]
    --spacing-mm S       distance between the rods along the arc, mm [40]
    --force-n F          peak force of the left rod, N [2]
    --force2-n F         peak force of the right rod, N [1.5]
    --frames N           [10]     --indenter-mm D   [5]
presses (independent presses anywhere, each against frame 0; presses.json):
    --presses N          loaded frames [150]
    --x-max-mm X         chord positions uniform in [-X, X], mm [110]
    --force-min-n F --force-max-n F   force magnitude range, N [0.5, 3]
    --max-tilt-deg T     pitch or yaw (even odds) uniform in [-T, T] [15]
    --indenters-mm D,D   rod diameters drawn from, mm [2,5,10]
characterization:
    --subset N           a random subset of N tests [all: 7200]
    --repeats R          repetitions [5]
    --load-cell-noise F  load-cell noise per axis, N [0.003]
perches:
    --x1-mm X --x2-mm X  rod positions, mm [-60, 50]
    --k1 K --k2 K        rod stiffness, N/mm [1, 2]
    --penetration-mm P   deepest penetration, mm [1.5]
    --frames N           [12]     --indenter-mm D   [10]
mapping:
    --rods X,X,...       world x of the rods, m [0.4,0.9,1.35,1.9,2.5]
    --rods-top-m Z       height of the rods' tops, m [1.0]
    --touches N          touches per rod [2]
    --force-n F          peak touch force, N [1.5]
    --indenter-mm D      rod diameter, mm [10]
fixtures:
    --docs DIR           also write reference_frame.png and press_motion.png there
";

/// What the command line asks for.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Print [`HELP`].
    Help,
    /// Run one scenario (boxed: the options are large).
    Run(Box<(Scenario, Common)>),
    /// Regenerate the fixtures under `out` (and the pictures under `docs`).
    Fixtures {
        /// Fixtures folder.
        out: PathBuf,
        /// Pictures folder, if wanted.
        docs: Option<PathBuf>,
        /// Seed.
        seed: u64,
    },
}

fn value<T: std::str::FromStr>(name: &str, v: Option<&String>) -> Result<T> {
    let v = v.ok_or_else(|| Error::param(name, "needs a value"))?;
    v.parse()
        .map_err(|_| Error::param(name, format!("cannot parse `{v}`")))
}

/// A comma-separated list of numbers.
fn parse_list(name: &str, s: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| Error::param(name, format!("cannot parse `{t}`")))
        })
        .collect()
}

/// Parses `args` (without the program name).
pub fn parse(args: &[String]) -> Result<Command> {
    if args.is_empty() {
        return Err(Error::param("scenario", "missing; try --help"));
    }
    if args.iter().any(|a| a == "-h" || a == "--help") {
        return Ok(Command::Help);
    }
    let name = args[0].as_str();
    let mut scenario = match name {
        "single" => Scenario::Single(Single::default()),
        "pair" => Scenario::Pair(Pair::default()),
        "presses" => Scenario::Presses(Presses::default()),
        "characterization" => Scenario::Characterization(Characterization::default()),
        "perches" => Scenario::Perches(Perches::default()),
        "mapping" => Scenario::Mapping(Mapping::default()),
        "fixtures" => Scenario::Single(Single::default()),
        other => {
            return Err(Error::param(
                "scenario",
                format!(
                    "unknown scenario `{other}` (single, pair, presses, characterization, perches, mapping, fixtures)"
                ),
            ));
        }
    };
    let mut out: Option<PathBuf> = None;
    let mut docs: Option<PathBuf> = None;
    let mut common = Common::new("");
    common.flow = !matches!(scenario, Scenario::Characterization(_));
    let mut i = 1;
    while i < args.len() {
        let key = args[i].as_str();
        let v = args.get(i + 1);
        let mut took = true;
        let cfg = &mut common.config;
        match (key, &mut scenario) {
            ("--out", _) => out = Some(PathBuf::from(value::<String>(key, v)?)),
            ("--docs", _) if name == "fixtures" => {
                docs = Some(PathBuf::from(value::<String>(key, v)?))
            }
            ("--seed", _) => common.seed = value(key, v)?,
            ("--fps", _) => common.fps = value(key, v)?,
            ("--flow", _) => (common.flow, took) = (true, false),
            ("--no-flow", _) => (common.flow, took) = (false, false),
            ("--full-frame", _) => (cfg.full_frame, took) = (true, false),
            ("--youngs-kpa", _) => cfg.material.youngs_kpa = value(key, v)?,
            ("--poisson", _) => cfg.material.poisson = value(key, v)?,
            ("--layer-mm", _) => cfg.material.layer_mm = value(key, v)?,
            ("--coverage", _) => cfg.markers.coverage = value(key, v)?,
            ("--markers", _) => cfg.markers.count = Some(value(key, v)?),
            ("--noise-read", _) => cfg.noise.read = value(key, v)?,
            ("--flicker", _) => cfg.noise.flicker = value(key, v)?,
            ("--x-mm", Scenario::Single(o)) => o.x_mm = value(key, v)?,
            ("--force-n", Scenario::Single(o)) => o.force_n = value(key, v)?,
            ("--frames", Scenario::Single(o)) => o.frames = value(key, v)?,
            ("--indenter-mm", Scenario::Single(o)) => o.indenter_mm = value(key, v)?,
            ("--pitch-deg", Scenario::Single(o)) => o.pitch_deg = value(key, v)?,
            ("--yaw-deg", Scenario::Single(o)) => o.yaw_deg = value(key, v)?,
            ("--x-mm", Scenario::Pair(o)) => o.x_mm = value(key, v)?,
            ("--spacing-mm", Scenario::Pair(o)) => o.spacing_mm = value(key, v)?,
            ("--force-n", Scenario::Pair(o)) => o.force_n = value(key, v)?,
            ("--force2-n", Scenario::Pair(o)) => o.force2_n = value(key, v)?,
            ("--frames", Scenario::Pair(o)) => o.frames = value(key, v)?,
            ("--indenter-mm", Scenario::Pair(o)) => o.indenter_mm = value(key, v)?,
            ("--presses", Scenario::Presses(o)) => o.presses = value(key, v)?,
            ("--x-max-mm", Scenario::Presses(o)) => o.x_max_mm = value(key, v)?,
            ("--force-min-n", Scenario::Presses(o)) => o.force_min_n = value(key, v)?,
            ("--force-max-n", Scenario::Presses(o)) => o.force_max_n = value(key, v)?,
            ("--max-tilt-deg", Scenario::Presses(o)) => o.max_tilt_deg = value(key, v)?,
            ("--indenters-mm", Scenario::Presses(o)) => {
                let s: String = value(key, v)?;
                o.indenters_mm = parse_list(key, &s)?;
            }
            ("--subset", Scenario::Characterization(o)) => o.subset = Some(value(key, v)?),
            ("--repeats", Scenario::Characterization(o)) => o.repeats = value(key, v)?,
            ("--load-cell-noise", Scenario::Characterization(o)) => {
                o.load_cell_noise_n = value(key, v)?
            }
            ("--x1-mm", Scenario::Perches(o)) => o.x_mm[0] = value(key, v)?,
            ("--x2-mm", Scenario::Perches(o)) => o.x_mm[1] = value(key, v)?,
            ("--k1", Scenario::Perches(o)) => o.stiffness_n_per_mm[0] = value(key, v)?,
            ("--k2", Scenario::Perches(o)) => o.stiffness_n_per_mm[1] = value(key, v)?,
            ("--penetration-mm", Scenario::Perches(o)) => o.max_penetration_mm = value(key, v)?,
            ("--frames", Scenario::Perches(o)) => o.frames = value(key, v)?,
            ("--indenter-mm", Scenario::Perches(o)) => o.indenter_mm = value(key, v)?,
            ("--rods", Scenario::Mapping(o)) => {
                let s: String = value(key, v)?;
                o.rods_x_m = parse_list(key, &s)?;
            }
            ("--rods-top-m", Scenario::Mapping(o)) => o.rods_top_m = value(key, v)?,
            ("--touches", Scenario::Mapping(o)) => o.touches = value(key, v)?,
            ("--force-n", Scenario::Mapping(o)) => o.force_n = value(key, v)?,
            ("--indenter-mm", Scenario::Mapping(o)) => o.indenter_mm = value(key, v)?,
            _ => {
                return Err(Error::param(
                    key,
                    format!("unknown option for `{name}`; try --help"),
                ));
            }
        }
        i += if took { 2 } else { 1 };
    }
    if name == "fixtures" {
        return Ok(Command::Fixtures {
            out: out.unwrap_or_else(|| PathBuf::from("fixtures")),
            docs,
            seed: common.seed,
        });
    }
    common.out = out.ok_or_else(|| Error::param("out", "required: --out DIR"))?;
    Ok(Command::Run(Box::new((scenario, common))))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn parses_options_and_rejects_nonsense() {
        match parse(&args(
            "single --out /tmp/x --force-n 3 --pitch-deg 15 --no-flow --seed 9",
        ))
        .unwrap()
        {
            Command::Run(b) if matches!(b.0, Scenario::Single(_)) => {
                let (Scenario::Single(o), c) = *b else {
                    unreachable!()
                };
                assert_eq!((o.force_n, o.pitch_deg), (3.0, 15.0));
                assert!(!c.flow && c.seed == 9);
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(parse(&args("pair --help")).unwrap(), Command::Help);
        assert!(parse(&args("bogus --out x")).is_err());
        assert!(parse(&args("single")).is_err()); // no --out
        assert!(parse(&args("single --out x --spacing-mm 3")).is_err()); // pair-only
        assert!(parse(&args("single --out x --force-n")).is_err()); // no value
        assert!(parse(&args("single --out x --force-n abc")).is_err());
        assert!(parse(&[]).is_err());
        match parse(&args(
            "presses --out /tmp/x --presses 5 --indenters-mm 2,5 --force-min-n 1 --max-tilt-deg 7",
        ))
        .unwrap()
        {
            Command::Run(b) => {
                let (Scenario::Presses(o), _) = *b else {
                    panic!("not presses")
                };
                assert_eq!((o.presses, o.force_min_n, o.max_tilt_deg), (5, 1.0, 7.0));
                assert_eq!(o.indenters_mm, vec![2.0, 5.0]);
            }
            other => panic!("{other:?}"),
        }
        assert!(parse(&args("presses --out x --indenters-mm 2,x")).is_err());
        assert!(parse(&args("presses --out x --x-mm 3")).is_err()); // single-only
        match parse(&args("characterization --out d --subset 12")).unwrap() {
            Command::Run(b) => match *b {
                (Scenario::Characterization(o), c) => assert!(o.subset == Some(12) && !c.flow),
                other => panic!("{other:?}"),
            },
            other => panic!("{other:?}"),
        }
    }
}
