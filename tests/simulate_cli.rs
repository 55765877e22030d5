//! The `simulate` example's command line: every scenario's options reach the
//! simulator's `Scenario` and `Common`, bad input is a usage error (exit
//! status 2) and `--help` is not an error.

#[allow(dead_code)]
#[path = "../examples/simulate.rs"]
mod simulate;

use clap::{CommandFactory, Parser};
use optical_tactile_sim::scenario::{Common, Scenario, TipPresses};
use simulate::{Cli, Job};

fn parse(line: &str) -> Result<Job, clap::Error> {
    let args = std::iter::once("simulate").chain(line.split_whitespace());
    Cli::try_parse_from(args).map(|c| c.command.job().0)
}

fn run(line: &str) -> (Scenario, Common) {
    match parse(line).unwrap() {
        Job::Run(b) => *b,
        other => panic!("{other:?}"),
    }
}

fn usage_error(line: &str) -> String {
    let e = parse(line).unwrap_err();
    assert_eq!(e.exit_code(), 2, "{line}: {e}");
    e.to_string()
}

#[test]
fn definition_is_consistent() {
    Cli::command().debug_assert();
}

#[test]
fn options_reach_the_scenario() {
    let (sc, c) = run("single --out /tmp/x --force-n 3 --pitch-deg 15 --no-flow --seed 9");
    let Scenario::Single(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.force_n, o.pitch_deg, o.frames), (3.0, 15.0, 10));
    assert!(!c.flow && c.seed == 9);
    assert_eq!(c.out, std::path::PathBuf::from("/tmp/x"));

    let (sc, _) =
        run("presses --out /tmp/x --presses 5 --indenters-mm 2,5 --force-min-n 1 --max-tilt-deg 7");
    let Scenario::Presses(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.presses, o.force_min_n, o.max_tilt_deg), (5, 1.0, 7.0));
    assert_eq!(o.indenters_mm, vec![2.0, 5.0]);

    // Flow is off by default for the characterization only, and --flow turns it on.
    let (sc, c) = run("characterization --out d --subset 12");
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.subset == Some(12)));
    assert!(!c.flow);
    assert!(run("characterization --out d --flow").1.flow);
    assert!(run("pair --out d").1.flow);
    assert!(!run("pair --out d --flow --no-flow").1.flow);

    // Negative positions, lists, the sensor's options.
    let (sc, c) = run(
        "perches --out d --x1-mm -70 --x2-mm 40 --k2 3 --youngs-kpa 60 --markers 500 --full-frame",
    );
    let Scenario::Perches(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.x_mm, o.stiffness_n_per_mm), ([-70.0, 40.0], [1.0, 3.0]));
    assert_eq!(c.config.material.youngs_kpa, 60.0);
    assert_eq!(c.config.markers.count, Some(500));
    assert!(c.config.full_frame);
    let default_depths = run("single --out d").1.config.markers.depth_mm;
    assert!(default_depths.0 < default_depths.1, "{default_depths:?}");
    let depths = |line: &str| run(line).1.config.markers.depth_mm;
    assert_eq!(depths("single --out d --marker-depth-mm 2,2"), (2.0, 2.0));
    assert_eq!(
        depths("presses --out d --marker-depth-mm 0.5,1.5"),
        (0.5, 1.5)
    );
    for bad in ["0,1", "3,2", "2", "1,2,3", "-1,1", "a,b", "1,inf"] {
        let e = usage_error(&format!("single --out d --marker-depth-mm {bad}"));
        assert!(e.contains("marker-depth-mm"), "{bad}: {e}");
    }
    let (sc, _) = run("mapping --out d --rods 0.5,1.5 --touches 3");
    let Scenario::Mapping(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.rods_x_m, o.touches), (vec![0.5, 1.5], 3));

    // Defaults equal the library's.
    let (sc, c) = run("pair --out d");
    assert_eq!(sc, Scenario::Pair(Default::default()));
    assert_eq!(c, Common::new("d"));
}

#[test]
fn the_fingertip_sensor_and_its_scenarios() {
    use optical_tactile::geometry::SensorGeometry;
    use optical_tactile_sim::{MarkerLayout, SimConfig};

    // The flat sensor's preset, its protocol's repetitions, presses of
    // round tips, and a round tip for the shear.
    let (sc, c) = run("characterization --sensor fingertip --out d");
    assert_eq!(c.config, SimConfig::fingertip());
    assert!(matches!(c.config.skin.geometry, SensorGeometry::Flat(_)));
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.repeats == 2));
    assert!(!c.flow);
    let (sc, _) = run("characterization --sensor fingertip --out d --repeats 3");
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.repeats == 3));
    let (sc, _) = run("characterization --sensor strip --out d");
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.repeats == 5));
    // Two spheres 8 mm apart on the fingertip's gel, rods 40 mm apart on
    // the strip, unless told.
    let spacing = |line: &str| match run(line).0 {
        Scenario::Pair(o) => o.spacing_mm,
        other => panic!("{other:?}"),
    };
    assert_eq!(spacing("pair --sensor fingertip --out d"), 8.0);
    assert_eq!(spacing("pair --out d"), 40.0);
    assert_eq!(
        spacing("pair --sensor fingertip --spacing-mm 7 --out d"),
        7.0
    );
    // Spot checks: the scenario's default unless asked.
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.spot_checks.is_none()));
    let (sc, _) = run("characterization --sensor fingertip --out d --spot-checks 40");
    assert!(matches!(sc, Scenario::Characterization(ref o) if o.spot_checks == Some(40)));
    usage_error("characterization --out d --spot-checks -1");

    let (sc, _) = run("presses --sensor fingertip --out d --presses 7 --max-shear-ratio 0.5");
    let Scenario::TipPresses(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!(
        o,
        TipPresses {
            presses: 7,
            max_shear_ratio: 0.5,
            ..TipPresses::default()
        }
    );
    let (sc, _) = run("presses --sensor fingertip --out d --punch-mm 3,12 --sphere-mm 4,4");
    let Scenario::TipPresses(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.punch_mm, o.sphere_mm), ((3.0, 12.0), (4.0, 4.0)));
    let (sc, _) = run("presses --sensor fingertip --out d --press-seed 4");
    assert!(matches!(sc, Scenario::TipPresses(ref o) if o.press_seed == Some(4)));
    usage_error("presses --sensor fingertip --out d --punch-mm 12,3");
    usage_error("presses --sensor fingertip --out d --fingertip-mm 15");
    let (sc, _) = run("presses --out d");
    assert!(matches!(sc, Scenario::Presses(ref o) if o.max_tilt_deg == 15.0));

    let (sc, _) = run("shear --sensor fingertip --out d --indenter-mm 18");
    let Scenario::Shear(o) = sc else {
        panic!("{sc:?}")
    };
    assert_eq!((o.fingertip_y_mm, o.indenter_mm), (Some(0.0), 18.0));
    let (sc, _) = run("shear --out d");
    assert!(matches!(sc, Scenario::Shear(ref o) if o.fingertip_y_mm.is_none()));

    // The material and marker options vary it.
    let (_, c) = run(
        "single --sensor fingertip --out d --youngs-kpa 300 --layer-mm 3 --pitch-px 25 --dot-px 6",
    );
    assert_eq!(
        (c.config.material.youngs_kpa, c.config.material.layer_mm),
        (300.0, 3.0)
    );
    let MarkerLayout::Grid(g) = c.config.markers.layout else {
        panic!("{:?}", c.config.markers.layout)
    };
    assert_eq!((g.pitch_px, g.diameter_px), (25.0, 6.0));
    let (_, c) = run("single --sensor fingertip --out d --random-markers --markers 900");
    assert_eq!(c.config.markers.layout, MarkerLayout::Random);
    assert_eq!(c.config.markers.count, Some(900));
    // The dot-grid strip keeps its own defaults.
    let (_, c) = run("shear --dot-grid --out d");
    assert_eq!(c.config, SimConfig::dot_grid(Default::default()));

    usage_error("single --out d --sensor round");
    usage_error("single --out d --sensor fingertip --dot-grid");
    usage_error("single --out d --dot-grid --random-markers");
}

#[test]
fn fixtures_default_to_this_crate() {
    match parse("fixtures --docs pics --seed 3").unwrap() {
        Job::Fixtures { out, docs, seed } => {
            assert_eq!(
                out,
                std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
            );
            assert_eq!(docs.as_deref(), Some(std::path::Path::new("pics")));
            assert_eq!(seed, 3);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn nonsense_is_a_usage_error() {
    assert!(usage_error("warp --out x").contains("warp"));
    assert!(usage_error("single").contains("--out"));
    usage_error("");
    usage_error("single --out x --spacing-mm 3"); // pair only
    usage_error("single --out x --force-n"); // no value
    assert!(usage_error("single --out x --force-n abc").contains("abc"));
    assert!(usage_error("presses --out x --indenters-mm 2,x").contains("2,x"));
    usage_error("presses --out x --x-mm 3"); // single only
    usage_error("fixtures --force-n 2");
    // Help is not an error.
    let e = parse("pair --help").unwrap_err();
    assert_eq!(e.exit_code(), 0);
    assert!(e.to_string().contains("--spacing-mm"));
}
