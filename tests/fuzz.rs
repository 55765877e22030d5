//! Fuzzing every reader: arbitrary bytes, and structured mutations of valid
//! files (the bundled calibration, `tests.csv`, `poses.csv`, `.flo`, `.npy`,
//! PNG headers, JSON Lines), must give `Ok` or an `Error`, never a panic, a
//! hang or an allocation beyond the formats' bounds. A calibration that
//! loads is also run through the sensor on the bundled press frames, and
//! every contact it reports must be finite.
//!
//! Each property runs [`CASES`] cases, the arbitrary bytes twice that (some
//! 15 s in all with `cargo
//! test` on two cores); the seed comes from `PROPTEST_RNG_SEED`, which CI
//! sets, so a run can be repeated. For longer runs outside CI, see `fuzz/`
//! (cargo-fuzz).

#[path = "common/png.rs"]
mod png;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ndarray::Array2;
use optical_tactile::calibration::Calibration;
use optical_tactile::io::{self, FrameRecord, JsonlWriter, RawContactRecord};
use optical_tactile::{Error, TactileSensor};
use proptest::prelude::*;
use proptest::test_runner::Config;
use serde_json::Value;

/// Cases per property.
const CASES: u32 = 512;

fn config(cases: u32) -> Config {
    Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    }
}

fn fixture(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// A scratch file of its own (its name ends in `name`), removed when the
/// returned path is dropped.
fn scratch(name: &str) -> tempfile::TempPath {
    tempfile::Builder::new()
        .prefix("optical-tactile-fuzz-")
        .suffix(&format!("-{name}"))
        .tempfile()
        .unwrap()
        .into_temp_path()
}

/// Every reader on the file at `path`; each must return.
fn read_everything(path: &Path) {
    let _ = io::read_gray(path);
    let _ = io::read_flo(path);
    let _ = io::read_npy_f64(path);
    let _ = io::read_jsonl::<FrameRecord>(path);
    let _ = io::read_jsonl::<FrameRecord<RawContactRecord>>(path);
    let _ = io::read_tests_csv(path);
    let _ = io::read_poses_csv(path);
    let _ = Calibration::load(path);
}

/// The first and the fifth bundled press frames (a reference and a press).
fn frames() -> &'static (Array2<f32>, Array2<f32>) {
    static FRAMES: OnceLock<(Array2<f32>, Array2<f32>)> = OnceLock::new();
    FRAMES.get_or_init(|| {
        let paths = io::list_frames(fixture("fixtures/press")).unwrap();
        (
            io::read_gray(&paths[0]).unwrap(),
            io::read_gray(&paths[4]).unwrap(),
        )
    })
}

/// A loaded calibration through the sensor: errors are fine, non-finite
/// contacts are not.
fn run_sensor(cal: Calibration) -> Result<(), Error> {
    let mut sensor = TactileSensor::from_calibration(cal)?;
    let (reference, press) = frames();
    sensor.set_reference(reference)?;
    for c in sensor.process(press, 0.1)? {
        assert!(
            c.location_mm
                .iter()
                .chain(&c.force_n)
                .all(|x| x.is_finite()),
            "{c:?}"
        );
    }
    Ok(())
}

/// Values that break numbers validated only for sign or finiteness.
fn nasty_value() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::from(0)),
        Just(Value::from(-1)),
        Just(Value::from(1)),
        Just(Value::from(u32::MAX)),
        Just(Value::from(u64::MAX)),
        Just(Value::from(1u64 << 63)),
        Just(Value::from(i64::MIN)),
        Just(Value::from(1e9)),
        Just(Value::from(5e7)),
        Just(Value::from(1e300)),
        Just(Value::from(-1e300)),
        Just(Value::from(1e-300)),
        Just(Value::from(0.5)),
        Just(Value::Null),
        Just(Value::Bool(true)),
        Just(Value::from("x")),
        Just(Value::Array(vec![])),
        Just(serde_json::json!({})),
        any::<i64>().prop_map(Value::from),
        any::<f64>()
            .prop_filter("JSON numbers are finite", |x| x.is_finite())
            .prop_map(Value::from),
    ]
}

/// JSON pointers to every value in `v`.
fn pointers(v: &Value, at: String, out: &mut Vec<String>) {
    out.push(at.clone());
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                pointers(x, format!("{at}/{k}"), out);
            }
        }
        // Long arrays (kernels, coefficients): a few of their elements.
        Value::Array(a) => {
            for i in [0, 1, a.len() / 2, a.len().saturating_sub(1)] {
                if let Some(x) = a.get(i) {
                    pointers(x, format!("{at}/{i}"), out);
                }
            }
        }
        _ => {}
    }
}

fn calibration_value() -> &'static (Value, Vec<String>) {
    static CAL: OnceLock<(Value, Vec<String>)> = OnceLock::new();
    CAL.get_or_init(|| {
        let text = std::fs::read_to_string(fixture("fixtures/calibration.json")).unwrap();
        let v: Value = serde_json::from_str(&text).unwrap();
        let mut ptrs = Vec::new();
        pointers(&v, String::new(), &mut ptrs);
        ptrs.retain(|p| !p.is_empty());
        (v, ptrs)
    })
}

/// Replaces (or, with `remove`, deletes) the value at `ptr`.
fn mutate(v: &mut Value, ptr: &str, new: Value, remove: bool) {
    if remove {
        let (parent, key) = ptr.rsplit_once('/').unwrap();
        match v.pointer_mut(parent) {
            Some(Value::Object(m)) => {
                m.remove(key);
            }
            Some(Value::Array(a)) => {
                if let Ok(i) = key.parse::<usize>()
                    && i < a.len()
                {
                    a.remove(i);
                }
            }
            _ => {}
        }
    } else if let Some(x) = v.pointer_mut(ptr) {
        *x = new;
    }
}

/// Arbitrary short byte strings, biased to start like the formats do.
fn bytes() -> impl Strategy<Value = Vec<u8>> {
    let prefix = prop_oneof![
        Just(Vec::new()),
        Just(b"\x89PNG\r\n\x1a\n".to_vec()),
        Just(b"\x93NUMPY\x01\x00".to_vec()),
        Just(b"\x93NUMPY\x02\x00".to_vec()),
        Just(io::FLO_MAGIC.to_le_bytes().to_vec()),
        Just(b"{\"version\": 1, ".to_vec()),
        Just(b"frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz\n".to_vec()),
    ];
    (prefix, prop::collection::vec(any::<u8>(), 0..600)).prop_map(|(mut p, rest)| {
        p.extend(rest);
        p
    })
}

proptest! {
    #![proptest_config(config(CASES * 2))]

    /// Arbitrary bytes, to every reader.
    #[test]
    fn arbitrary_bytes_to_every_reader(data in bytes()) {
        let p = scratch("bytes");
        std::fs::write(&p, &data).unwrap();
        read_everything(&p);
    }
}

proptest! {
    #![proptest_config(config(CASES))]

    /// The bundled calibration with up to three values replaced by nasty
    /// ones or removed; what loads runs through the sensor.
    #[test]
    fn mutated_calibrations_load_or_fail_and_run(
        edits in prop::collection::vec((any::<prop::sample::Index>(), nasty_value(), prop::bool::weighted(0.15)), 1..4),
    ) {
        let (base, ptrs) = calibration_value();
        let mut v = base.clone();
        for (i, new, remove) in edits {
            mutate(&mut v, i.get(ptrs).as_str(), new, remove);
        }
        let text = v.to_string();
        if let Ok(cal) = Calibration::from_json_str(&text) {
            let _ = run_sensor(cal);
        }
    }

    /// The bundled calibration's text cut or with a byte changed.
    #[test]
    fn damaged_calibration_text(cut in any::<prop::sample::Index>(), at in any::<prop::sample::Index>(), byte in any::<u8>()) {
        let text = std::fs::read(fixture("fixtures/calibration.json")).unwrap();
        let mut t = text[..cut.index(text.len() + 1)].to_vec();
        if !t.is_empty() {
            let k = at.index(t.len());
            t[k] = byte;
        }
        let p = scratch("calibration.json");
        std::fs::write(&p, &t).unwrap();
        if let Ok(cal) = Calibration::load(&p) {
            let _ = run_sensor(cal);
        }
    }

    /// `tests.csv` and `poses.csv` with fields replaced, lines repeated or
    /// cut.
    #[test]
    fn mutated_csv(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<prop::sample::Index>(), prop_oneof![
            Just("NaN".to_string()), Just("inf".to_string()), Just("-1".to_string()), Just("1e400".to_string()),
            Just(String::new()), Just("/dev/zero".to_string()), Just("18446744073709551616".to_string()),
            Just("a,b".to_string()), Just("\u{feff}".to_string()), "[ -~]{0,12}",
        ]), 1..4),
        cut in any::<prop::sample::Index>(),
    ) {
        let tests = std::fs::read_to_string(fixture("fixtures/characterization/tests.csv")).unwrap();
        let poses = "frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz\n000000.png,0,0,0,0,1,0,0,0\n000001.png,0.02,0,0,0.001,1,0,0,0\n";
        for (name, src) in [("tests.csv", tests.as_str()), ("poses.csv", poses)] {
            let mut lines: Vec<Vec<String>> = src
                .lines()
                .map(|l| l.split(',').map(String::from).collect())
                .collect();
            for (line, field, value) in &edits {
                let l = line.index(lines.len());
                let f = field.index(lines[l].len());
                lines[l][f] = value.clone();
            }
            let mut text: String = lines.iter().map(|l| l.join(",") + "\n").collect();
            let mut end = cut.index(text.len() + 1);
            while !text.is_char_boundary(end) {
                end -= 1;
            }
            text.truncate(end);
            let p = scratch(name);
            std::fs::write(&p, &text).unwrap();
            if let Ok(rows) = io::read_tests_csv(&p) {
                for r in rows {
                    prop_assert!(r.fz_n.is_finite() && r.x_mm.is_finite());
                }
            }
            if let Ok(rows) = io::read_poses_csv(&p) {
                for r in rows {
                    prop_assert!(r.t_s.is_finite());
                }
            }
        }
    }

    /// `.flo` headers of any size and files of any length.
    #[test]
    fn flo_headers(w in prop_oneof![any::<i32>(), 0i32..40], h in prop_oneof![any::<i32>(), 0i32..40], extra in -20i64..20) {
        let mut b = io::FLO_MAGIC.to_le_bytes().to_vec();
        b.extend_from_slice(&w.to_le_bytes());
        b.extend_from_slice(&h.to_le_bytes());
        // Data for the header's size (when small), give or take a little.
        let want = if (0..40).contains(&w) && (0..40).contains(&h) { 8 * (w * h) as i64 } else { 64 };
        b.resize((12 + want + extra).max(0) as usize, 0x3f);
        let p = scratch("f.flo");
        std::fs::write(&p, &b).unwrap();
        if let Ok(f) = io::read_flo(&p) {
            prop_assert_eq!(f.size(), (w as usize, h as usize));
            prop_assert_eq!(extra, 0);
        }
    }

    /// `.npy` headers: any version, header length, dtype and shape.
    #[test]
    fn npy_headers(
        version in 0u8..5,
        descr in prop_oneof![Just("<f4"), Just("<f8"), Just(">f8"), Just("<i4"), Just("")],
        fortran in any::<bool>(),
        shape in prop_oneof![
            (0usize..6, 0usize..6).prop_map(|(a, b)| format!("({a}, {b})")),
            Just("(4294967296, 4294967296)".to_string()),
            Just("(18446744073709551615, 2)".to_string()),
            Just("(3,)".to_string()),
            Just("(2, 2, 2)".to_string()),
            "[ -~]{0,16}",
        ],
        hlen_delta in -4i64..4,
        data in prop::collection::vec(any::<u8>(), 0..300),
    ) {
        let dict = format!("{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}\n", if fortran { "True" } else { "False" });
        let mut b = b"\x93NUMPY".to_vec();
        b.push(version);
        b.push(0);
        let hlen = (dict.len() as i64 + hlen_delta).max(0) as u64;
        if version == 1 {
            b.extend_from_slice(&(hlen as u16).to_le_bytes());
        } else {
            b.extend_from_slice(&(hlen as u32).to_le_bytes());
        }
        b.extend_from_slice(dict.as_bytes());
        b.extend_from_slice(&data);
        let p = scratch("a.npy");
        std::fs::write(&p, &b).unwrap();
        let _ = io::read_npy_f64(&p);
    }

    /// A small valid PNG with its header's size fields (and CRC) replaced,
    /// or a byte anywhere changed.
    #[test]
    fn png_headers(w in prop_oneof![any::<u32>(), 0u32..64], h in prop_oneof![any::<u32>(), 0u32..64], fix_crc in any::<bool>(), at in any::<prop::sample::Index>(), byte in any::<u8>(), poke in any::<bool>()) {
        let p = scratch("i.png");
        io::write_gray_png(&p, &Array2::from_shape_fn((24, 40), |(y, x)| ((x * 7 + y * 13) % 256) as f32)).unwrap();
        let mut b = std::fs::read(&p).unwrap();
        b[16..20].copy_from_slice(&w.to_be_bytes());
        b[20..24].copy_from_slice(&h.to_be_bytes());
        if fix_crc {
            let crc = png::crc32(&b[12..29]);
            b[29..33].copy_from_slice(&crc.to_be_bytes());
        }
        if poke {
            let k = at.index(b.len());
            b[k] = byte;
        }
        std::fs::write(&p, &b).unwrap();
        if let Ok(img) = io::read_gray(&p) {
            let (rows, cols) = img.dim();
            prop_assert!(rows * cols <= optical_tactile::frame::MAX_FRAME_PIXELS);
        }
    }

    /// JSON Lines of contacts with values replaced; what reads writes again
    /// (nothing non-finite) and reads back.
    #[test]
    fn mutated_json_lines(
        edits in prop::collection::vec((any::<prop::sample::Index>(), nasty_value()), 0..4),
        raw in any::<bool>(),
        junk in prop_oneof![Just(String::new()), Just("[[[[[[[[".repeat(40)), Just("null".to_string()), Just("{\"frame\":".to_string()), "[ -~]{0,20}"],
    ) {
        let line = if raw {
            serde_json::json!({"frame": "000003.png", "t_s": 0.06, "contacts": [
                {"x_px": 412.5, "y_px": 100.0, "box_px": [380, 40, 64, 120], "strength": 5000.0,
                 "ds1": 10.0, "ds2": -2.0, "dn": 400.0, "d_pf": 3.5, "area_px": 2000}]})
        } else {
            serde_json::json!({"frame": "000003.png", "t_s": 0.06, "latency_ms": 4.5, "contacts": [
                {"id": 1, "x_mm": -20.0, "y_mm": 0.0, "z_mm": 150.0, "fx_n": 0.1, "fy_n": 0.0, "fz_n": -2.0,
                 "x_px": 412.5, "y_px": 100.0, "fallback": false, "missed": 1}]})
        };
        let mut v = line;
        let mut ptrs = Vec::new();
        pointers(&v, String::new(), &mut ptrs);
        ptrs.retain(|p| !p.is_empty());
        for (i, new) in edits {
            mutate(&mut v, i.get(&ptrs).as_str(), new, false);
        }
        let text = format!("{v}\n\n{junk}\n");
        let p = scratch("c.jsonl");
        std::fs::write(&p, &text).unwrap();
        let roundtrip = |records: &[FrameRecord<RawContactRecord>]| -> Result<(), TestCaseError> {
            let q = scratch("again.jsonl");
            let mut w = JsonlWriter::create(&q).unwrap();
            for r in records {
                w.write(r).unwrap();
            }
            drop(w);
            // serde_json's default parser may round a long decimal one ulp
            // away: the count, not the bits, is compared.
            prop_assert_eq!(io::read_jsonl::<FrameRecord<RawContactRecord>>(&q).unwrap().len(), records.len());
            Ok(())
        };
        if let Ok(records) = io::read_jsonl::<FrameRecord<RawContactRecord>>(&p) {
            roundtrip(&records)?;
        }
        if let Ok(records) = io::read_jsonl::<FrameRecord>(&p) {
            let q = scratch("again2.jsonl");
            let mut w = JsonlWriter::create(&q).unwrap();
            for r in &records {
                w.write(r).unwrap();
            }
            drop(w);
            prop_assert_eq!(io::read_jsonl::<FrameRecord>(&q).unwrap().len(), records.len());
        }
    }
}
