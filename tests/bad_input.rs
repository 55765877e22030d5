//! Bad input is an `Error`, within seconds and in bounded memory: sizes from
//! files and parameters beyond their bounds (docs/formats.md, "Bounds"),
//! files that are not regular files, files larger than their format allows,
//! images declaring more pixels than a frame may have, non-finite numbers
//! on their way into JSON or in from CSV.

#[path = "common/png.rs"]
mod png;
#[path = "common/scratch.rs"]
mod scratch;
use scratch::scratch;

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use optical_tactile::calibration::Calibration;
use optical_tactile::contact::{ContactLocator, ContactPointMethod};
use optical_tactile::flow::dis::{Dis, DisParams, DisPreset};
use optical_tactile::flow::refine::RefineParams;
use optical_tactile::io::{self, ContactRecord, FrameRecord, JsonlWriter};
use optical_tactile::segment::{Segmenter, SegmenterConfig, Thresholds};
use optical_tactile::{Error, TactileSensor};
use serde_json::{Value, json};

fn fixture(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// Runs `f` on another thread and fails the test if it takes more than
/// `secs` seconds (a hang shows as a failure, not a stuck test run).
fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(secs))
        .unwrap_or_else(|_| panic!("no answer within {secs} s"))
}

fn calibration_json() -> Value {
    let text = std::fs::read_to_string(fixture("fixtures/calibration.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn load_err(v: &Value) -> String {
    let t0 = Instant::now();
    let e = Calibration::from_json_str(&v.to_string()).unwrap_err();
    assert!(t0.elapsed() < Duration::from_secs(2), "{e}");
    e.to_string()
}

#[test]
fn calibration_sizes_beyond_their_bounds_are_refused_at_load() {
    let mut v = calibration_json();
    v["thresholds"]["erode"] = json!(4294967295u64);
    assert!(load_err(&v).contains("thresholds.erode"));
    let mut v = calibration_json();
    v["thresholds"]["dilate"] = json!(50_000_000);
    assert!(load_err(&v).contains("1..=255"));

    for sigma in [1e9, 1e300, 257.0] {
        let mut v = calibration_json();
        v["pipeline"]["contact_point"] = json!({"method": "slope_peak", "sigma_px": sigma});
        assert!(load_err(&v).contains("sigma_px"));
    }
    let mut v = calibration_json();
    v["pipeline"]["contact_point"] = json!({"method": "energy_centroid", "half_window_px": 1e12});
    assert!(load_err(&v).contains("half_window_px"));
    let mut v = calibration_json();
    v["pipeline"]["margin_px"] = json!(u64::MAX);
    assert!(load_err(&v).contains("margin_px"));
    for r in [json!(0), json!(u64::MAX), json!(1u64 << 20)] {
        let mut v = calibration_json();
        v["pipeline"]["light_box_px"] = r;
        assert!(load_err(&v).contains("light_box_px"));
    }
    let mut v = calibration_json();
    v["crop"]["x"] = json!(u64::MAX);
    assert!(load_err(&v).contains("crop"));

    // The profile model's sizes: huge values wrap in unchecked arithmetic.
    for (key, value) in [
        ("degree", json!(u64::MAX)),
        ("degree", json!(7)),
        ("half_width", json!(1u64 << 63)),
        ("half_width", json!(u64::MAX)),
        ("half_width", json!(4097)),
        ("step_px", json!(1e300)),
    ] {
        let mut v = calibration_json();
        v["profile"][key] = value;
        let e = load_err(&v);
        assert!(e.contains("profile model") && e.contains(key), "{e}");
        assert_eq!(e.matches("calibration").count(), 1, "{e}");
    }
    let mut v = calibration_json();
    v["profile"]["anchor"]["coefficients"] = json!(vec![0.0; 100]);
    assert!(load_err(&v).contains("column map"));
}

#[test]
fn parameters_beyond_their_bounds_are_refused() {
    for m in [
        ContactPointMethod::SlopePeak { sigma_px: 1e300 },
        ContactPointMethod::SlopePeak { sigma_px: 1e9 },
        ContactPointMethod::SlopePeak { sigma_px: f64::NAN },
        ContactPointMethod::EnergyCentroid {
            half_window_px: f64::INFINITY,
        },
    ] {
        assert!(m.validate().is_err(), "{m:?}");
        let u = ndarray::Array2::<f32>::zeros((10, 40));
        let mut raws = [optical_tactile::contact::RawContact::default()];
        let e = ContactLocator::new().refine(m, &mut raws, u.view(), u.view(), 4.0);
        assert!(matches!(e, Err(Error::InvalidParameter { .. })), "{e:?}");
    }
    assert!(
        ContactPointMethod::SlopePeak { sigma_px: 256.0 }
            .validate()
            .is_ok()
    );

    let mut t = Thresholds::MID;
    t.erode = 50_000_000;
    assert!(t.validate().is_err());
    t.erode = 255;
    t.validate().unwrap();
    let config = SegmenterConfig {
        thresholds: Thresholds::MID,
        margin: usize::MAX,
        scale: 1.0,
    };
    assert!(Segmenter::new(config).is_err());

    let base = DisParams::preset(DisPreset::Fast);
    let bad: [fn(&mut DisParams); 6] = [
        |p| p.refinement.sor_iterations = 4_000_000_000,
        |p| p.refinement.outer_iterations = 101,
        |p| p.gradient_descent_iterations = usize::MAX,
        |p| p.coarsest_scale = Some(64),
        |p| p.stripes = 1 << 40,
        |p| p.min_stripe_rows = usize::MAX,
    ];
    for f in bad {
        let mut p = base.clone();
        f(&mut p);
        let e = Dis::new(p).unwrap_err();
        assert!(matches!(e, Error::InvalidParameter { .. }), "{e}");
    }
    let r = RefineParams {
        sor_iterations: 100,
        outer_iterations: 100,
        ..RefineParams::default()
    };
    r.validate().unwrap();
}

/// A reader of a file, as a function of its path.
type Reader = fn(&Path) -> Result<(), Error>;

/// Every reader of a file.
fn readers() -> Vec<(&'static str, Reader)> {
    vec![
        ("png", |p| io::read_gray(p).map(drop)),
        ("flo", |p| io::read_flo(p).map(drop)),
        ("npy", |p| io::read_npy_f64(p).map(drop)),
        ("jsonl", |p| io::read_jsonl::<FrameRecord>(p).map(drop)),
        ("tests.csv", |p| io::read_tests_csv(p).map(drop)),
        ("poses.csv", |p| io::read_poses_csv(p).map(drop)),
        ("calibration", |p| Calibration::load(p).map(drop)),
    ]
}

#[test]
fn devices_fifos_and_directories_are_refused_as_files() {
    let tmp = scratch("special");
    let d = tmp.path();
    let fifo = d.join("poses.csv");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success());
    std::fs::write(d.join("000000.png"), b"not read").unwrap();
    let dir = d.join("a-directory");
    std::fs::create_dir(&dir).unwrap();
    for (what, read) in readers() {
        for (path, says) in [
            (Path::new("/dev/zero").to_path_buf(), "not a regular file"),
            (dir.clone(), "is a directory"),
        ] {
            let e = within(5, move || read(&path).unwrap_err().to_string());
            assert!(e.contains(says), "{what}: {e}");
        }
        if made {
            let fifo = fifo.clone();
            let e = within(5, move || read(&fifo).unwrap_err().to_string());
            assert!(e.contains("not a regular file"), "{what}: {e}");
        }
    }
    // A sequence with a FIFO for `poses.csv` opens without waiting on it.
    let seq = d.to_path_buf();
    within(5, move || {
        let _ = optical_tactile::SequenceSource::open(&seq);
    });
}

/// A PNG whose header declares `w x h` gray pixels, with a tiny (invalid)
/// image data stream.
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = out.len();
        out.extend_from_slice(kind);
        out.extend_from_slice(data);
        let crc = png::crc32(&out[start..]);
        out.extend_from_slice(&crc.to_be_bytes());
    }
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    chunk(&mut out, b"IHDR", &ihdr);
    chunk(
        &mut out,
        b"IDAT",
        &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
    );
    chunk(&mut out, b"IEND", &[]);
    out
}

#[test]
fn images_and_fields_larger_than_a_frame_are_refused_from_their_headers() {
    let tmp = scratch("large");
    let d = tmp.path();
    for (w, h) in [(20000, 20000), (16384, 16384), (1, 100_000), (u32::MAX, 1)] {
        let p = d.join("big.png");
        std::fs::write(&p, png_header_only(w, h)).unwrap();
        let t0 = Instant::now();
        let e = io::read_gray(&p).unwrap_err().to_string();
        assert!(t0.elapsed() < Duration::from_secs(2));
        assert!(e.contains(&format!("{w}x{h} is larger")), "{e}");
    }
    // Within the bounds, the bad data stream is what fails.
    let p = d.join("small.png");
    std::fs::write(&p, png_header_only(64, 32)).unwrap();
    assert!(io::read_gray(&p).is_err());

    let p = d.join("big.flo");
    let mut flo = io::FLO_MAGIC.to_le_bytes().to_vec();
    flo.extend_from_slice(&16384i32.to_le_bytes());
    flo.extend_from_slice(&16384i32.to_le_bytes());
    std::fs::write(&p, &flo).unwrap();
    let e = io::read_flo(&p).unwrap_err().to_string();
    assert!(e.contains("16384x16384 is larger"), "{e}");

    let p = d.join("big.npy");
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }\n";
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    std::fs::write(&p, &npy).unwrap();
    let e = io::read_npy_f64(&p).unwrap_err().to_string();
    assert!(e.contains("is larger"), "{e}");
    let mut npy = b"\x93NUMPY\x02\x00".to_vec();
    npy.extend_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&p, &npy).unwrap();
    let e = io::read_npy_f64(&p).unwrap_err().to_string();
    assert!(e.contains("header"), "{e}");
}

#[test]
fn over_long_lines_are_refused() {
    let tmp = scratch("long");
    let d = tmp.path();
    let p = d.join("c.jsonl");
    let mut text = String::from("{\"frame\":\"a\",\"t_s\":0,\"contacts\":[]}\n");
    text.push_str(&" ".repeat(io::MAX_LINE_BYTES + 10));
    std::fs::write(&p, text).unwrap();
    let e = io::read_jsonl::<FrameRecord>(&p).unwrap_err().to_string();
    assert!(e.contains("c.jsonl:2:") && e.contains("longer than"), "{e}");
}

#[test]
fn non_finite_numbers_are_not_written_as_json() {
    let tmp = scratch("nonfinite");
    let d = tmp.path();
    let p = d.join("c.jsonl");
    let mut w = JsonlWriter::create(&p).unwrap();
    let mut rec = FrameRecord {
        frame: "a.png".into(),
        t_s: 0.0,
        contacts: vec![ContactRecord::default()],
        latency_ms: None,
    };
    w.write(&rec).unwrap();
    rec.contacts[0].fx_n = f64::INFINITY;
    let e = w.write(&rec).unwrap_err().to_string();
    assert!(e.contains("contacts[0].fx_n"), "{e}");
    rec.contacts[0].fx_n = 0.0;
    rec.t_s = f64::NAN;
    assert!(w.write(&rec).is_err());
    drop(w);
    // Only the good record was written, and it reads back.
    assert_eq!(io::read_jsonl::<FrameRecord>(&p).unwrap().len(), 1);
}

#[test]
fn non_finite_numbers_in_csv_are_errors() {
    let tmp = scratch("csv");
    let d = tmp.path();
    let p = d.join("poses.csv");
    std::fs::write(
        &p,
        "frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz\na.png,0,0,0,0,1,0,0,0\nb.png,NaN,0,0,0,1,0,0,0\n",
    )
    .unwrap();
    let e = io::read_poses_csv(&p).unwrap_err().to_string();
    assert!(e.contains("poses.csv:3") && e.contains("`t_s`"), "{e}");

    let src = std::fs::read_to_string(fixture("fixtures/characterization/tests.csv")).unwrap();
    let mut lines: Vec<String> = src.lines().map(String::from).collect();
    let header: Vec<&str> = lines[0].split(',').collect();
    let k = header.iter().position(|h| *h == "fz_n").unwrap();
    let mut row: Vec<String> = lines[1].split(',').map(String::from).collect();
    row[k] = "inf".into();
    lines[1] = row.join(",");
    let p = d.join("tests.csv");
    std::fs::write(&p, lines.join("\n")).unwrap();
    let e = io::read_tests_csv(&p).unwrap_err().to_string();
    assert!(e.contains("tests.csv:2") && e.contains("`fz_n`"), "{e}");
}

#[test]
fn overflowing_calibrations_report_no_non_finite_contact() {
    // Coefficients that overflow the force maps: the sensor drops and
    // counts such contacts, never reports them.
    let mut v = calibration_json();
    for g in ["gx", "gy", "gz"] {
        let n = v[g]["coefficients"].as_array().unwrap().len();
        v[g]["coefficients"] = json!(vec![1e300; n]);
    }
    let cal = Calibration::from_json_str(&v.to_string()).unwrap();
    let mut sensor = TactileSensor::from_calibration(cal).unwrap();
    let frames = io::list_frames(fixture("fixtures/press")).unwrap();
    sensor
        .set_reference(&io::read_gray(&frames[0]).unwrap())
        .unwrap();
    let frame = io::read_gray(&frames[4]).unwrap();
    let contacts = sensor.process(&frame, 0.1).unwrap();
    for c in contacts {
        assert!(
            c.location_mm
                .iter()
                .chain(&c.force_n)
                .all(|x| x.is_finite())
        );
    }
}
