//! The `evaluate` example end to end: the tail counts, the worst list and
//! the position bands reach its JSON, and bad options are clear usage
//! errors.

#[allow(dead_code)]
#[path = "../examples/evaluate.rs"]
mod evaluate;
#[path = "common/scratch.rs"]
mod scratch;

use std::path::Path;

use optical_tactile::io::{ContactRecord, FrameRecord};
use scratch::scratch;
use serde_json::Value;

fn args(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// One frame per press, one contact each at `x` mm with force `fz` N.
fn write_frames(path: &Path, presses: &[(f64, f64)]) {
    let mut text = String::new();
    for (i, &(x_mm, fz_n)) in presses.iter().enumerate() {
        let frame = FrameRecord {
            frame: format!("{i:06}.png"),
            t_s: 0.0,
            contacts: vec![ContactRecord {
                x_mm,
                fz_n,
                ..Default::default()
            }],
            latency_ms: None,
        };
        text += &serde_json::to_string(&frame).unwrap();
        text.push('\n');
    }
    std::fs::write(path, text).unwrap();
}

#[test]
fn the_tail_and_the_worst_contacts_reach_the_json() {
    let guard = scratch("evaluate");
    let d = guard.path();
    let (pred, truth, json) = (d.join("p.jsonl"), d.join("t.jsonl"), d.join("e.json"));
    // Fz errors 0.05, 0.4, 0.2 and 0.35.
    write_frames(
        &truth,
        &[(0.0, -1.0), (10.0, -2.0), (20.0, -1.0), (30.0, -3.0)],
    );
    write_frames(
        &pred,
        &[(0.1, -1.05), (10.0, -1.6), (20.0, -1.2), (30.5, -2.65)],
    );
    let run = |extra: &[&str]| {
        let mut a = vec![p(&pred), p(&truth), "--json", p(&json)];
        a.extend_from_slice(extra);
        evaluate::run_with(&args(&a)).unwrap();
        serde_json::from_str::<Value>(&std::fs::read_to_string(&json).unwrap()).unwrap()
    };
    let e = run(&[]);
    assert_eq!(e["beyond_n"], 0.3);
    assert_eq!(e["beyond"], serde_json::json!([0, 0, 2]));
    let frames: Vec<&str> = e["worst"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w["frame"].as_str().unwrap())
        .collect();
    assert_eq!(
        frames,
        ["000001.png", "000003.png", "000002.png", "000000.png"]
    );
    assert_eq!(e["worst"][1]["location_error_mm"][0], 0.5);

    let e = run(&["--beyond", "0.1", "--worst", "1"]);
    assert_eq!(e["beyond"], serde_json::json!([0, 0, 3]));
    assert_eq!(e["worst"].as_array().unwrap().len(), 1);
    let e = run(&["--worst", "0"]);
    assert!(e["worst"].as_array().unwrap().is_empty());
    assert!(e.get("bands").is_none(), "no bands unless asked: {e}");

    // Bands of 15 mm: [0, 15) holds the presses at 0 and 10 mm (Fz off by
    // 0.05 and 0.4 N), [15, 30) the one at 20, [30, 45) the one at 30.
    let e = run(&["--bands", "15"]);
    let bands = e["bands"].as_array().unwrap();
    let got: Vec<(f64, u64, f64)> = bands
        .iter()
        .map(|b| {
            (
                b["from_mm"].as_f64().unwrap(),
                b["matched"].as_u64().unwrap(),
                b["mae_force_n"][2].as_f64().unwrap(),
            )
        })
        .collect();
    let want = [(0.0, 2, 0.225), (15.0, 1, 0.2), (30.0, 1, 0.35)];
    assert_eq!(got.len(), want.len(), "{got:?}");
    for (g, w) in got.iter().zip(want) {
        assert!(
            g.0 == w.0 && g.1 == w.1 && (g.2 - w.2).abs() < 1e-9,
            "{got:?}"
        );
    }
    assert_eq!(bands[0]["beyond"], 1);
}

#[test]
fn bad_bars_and_list_lengths_are_usage_errors() {
    let guard = scratch("evaluate-bad");
    let t = guard.path().join("t.jsonl");
    write_frames(&t, &[(0.0, -1.0)]);
    for (flag, value, says) in [
        ("--beyond", "0", "expected a positive number"),
        ("--beyond", "-0.3", "expected a positive number"),
        ("--beyond", "NaN", "expected a positive number"),
        ("--worst", "1001", "1001 is not in 0..=1000"),
        ("--worst", "-1", "--worst"),
        ("--bands", "0", "expected a positive number"),
        ("--bands", "inf", "expected a positive number"),
        ("--bands", "ten", "expected a positive number"),
    ] {
        // `--flag=value`: a value of `-1` alone would read as a flag.
        let option = format!("{flag}={value}");
        let e = evaluate::run_with(&args(&[p(&t), p(&t), &option]))
            .unwrap_err()
            .to_string();
        assert!(e.contains(says), "{flag} {value}: {e}");
    }
}
