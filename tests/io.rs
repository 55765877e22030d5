//! File formats round-trip exactly, and malformed files give errors that name them.

#[path = "common/scratch.rs"]
mod scratch;
use scratch::scratch;

use ndarray::Array2;
use optical_tactile::io::{self, ContactRecord, FrameRecord, PoseRow, Split, TestRow};
use optical_tactile::{Error, FlowField};

fn sample_flow() -> FlowField {
    let u = Array2::from_shape_fn((3, 5), |(y, x)| x as f32 * 0.5 - y as f32);
    let v = Array2::from_shape_fn((3, 5), |(y, x)| (x * y) as f32 * -0.25 + 1e-7);
    FlowField::from_planes(u, v).unwrap()
}

#[test]
fn flo_round_trip_and_layout() {
    let dir = scratch("flo");
    let p = dir.path().join("f.flo");
    let f = sample_flow();
    io::write_flo(&p, &f).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    assert_eq!(&bytes[..4], b"PIEH");
    assert_eq!(i32::from_le_bytes(bytes[4..8].try_into().unwrap()), 5);
    assert_eq!(i32::from_le_bytes(bytes[8..12].try_into().unwrap()), 3);
    // Interleaved u, v, row-major: the second pixel's u is at byte 20.
    assert_eq!(f32::from_le_bytes(bytes[20..24].try_into().unwrap()), 0.5);
    assert_eq!(io::read_flo(&p).unwrap(), f);
}

#[test]
fn malformed_flo_is_an_error() {
    let dir = scratch("badflo");
    let p = dir.path().join("bad.flo");
    std::fs::write(&p, b"PIEH").unwrap();
    assert!(matches!(io::read_flo(&p), Err(Error::Format { .. })));
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&1.0f32.to_le_bytes());
    bytes.extend_from_slice(&[0; 8]);
    std::fs::write(&p, &bytes).unwrap();
    let e = io::read_flo(&p).unwrap_err().to_string();
    assert!(e.contains("bad magic") && e.contains("bad.flo"), "{e}");
    // Truncated data.
    io::write_flo(&p, &sample_flow()).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    bytes.pop();
    std::fs::write(&p, &bytes).unwrap();
    assert!(io::read_flo(&p).is_err());
    // Absurd header size.
    bytes[4..8].copy_from_slice(&i32::MAX.to_le_bytes());
    std::fs::write(&p, &bytes).unwrap();
    assert!(io::read_flo(&p).is_err());
    assert!(matches!(
        io::read_flo(dir.path().join("missing.flo")),
        Err(Error::Io { .. })
    ));
}

#[test]
fn npy_round_trip_f32_and_f64() {
    let dir = scratch("npy");
    let a = Array2::from_shape_fn((4, 7), |(y, x)| (y * 7 + x) as f32 / 3.0);
    io::write_npy_f32(dir.path().join("a.npy"), &a).unwrap();
    assert_eq!(io::read_npy_f32(dir.path().join("a.npy")).unwrap(), a);
    let bytes = std::fs::read(dir.path().join("a.npy")).unwrap();
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    assert_eq!(
        (10 + hlen) % 64,
        0,
        "header padded to 64 bytes as numpy does"
    );
    let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
    assert!(header.contains("'descr': '<f4'") && header.contains("(4, 7)"));
    let b = a.mapv(|x| x as f64 * std::f64::consts::PI);
    io::write_npy_f64(dir.path().join("b.npy"), &b).unwrap();
    assert_eq!(io::read_npy_f64(dir.path().join("b.npy")).unwrap(), b);
}

#[test]
fn npy_reads_fortran_order_and_rejects_others() {
    let dir = scratch("npyf");
    // A hand-made Fortran-order 2x3 array [[0,1,2],[3,4,5]] stored column by column.
    let dict = "{'descr': '<f8', 'fortran_order': True, 'shape': (2, 3), }";
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(dict.len() as u16 + 1).to_le_bytes());
    bytes.extend_from_slice(dict.as_bytes());
    bytes.push(b'\n');
    for v in [0.0f64, 3.0, 1.0, 4.0, 2.0, 5.0] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(dir.path().join("f.npy"), &bytes).unwrap();
    let a = io::read_npy_f64(dir.path().join("f.npy")).unwrap();
    assert_eq!(a, ndarray::arr2(&[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]));
    let bad = bytes.clone();
    let s = String::from_utf8_lossy(&bad).replace("<f8", "<i8");
    std::fs::write(dir.path().join("i.npy"), s.as_bytes()).unwrap();
    assert!(io::read_npy_f64(dir.path().join("i.npy")).is_err());
    std::fs::write(dir.path().join("t.npy"), &bytes[..bytes.len() - 3]).unwrap();
    assert!(io::read_npy_f64(dir.path().join("t.npy")).is_err());
    std::fs::write(dir.path().join("n.npy"), b"hello").unwrap();
    assert!(io::read_npy_f64(dir.path().join("n.npy")).is_err());
}

#[test]
fn png_gray_and_colour_and_sixteen_bit() {
    let dir = scratch("png");
    let a = Array2::from_shape_fn((6, 9), |(y, x)| (y * 30 + x * 3) as f32);
    io::write_gray_png(dir.path().join("g.png"), &a).unwrap();
    assert_eq!(io::read_gray(dir.path().join("g.png")).unwrap(), a);
    // RGB: the green channel is used.
    let rgb: Vec<u8> = (0..6 * 9).flat_map(|k| [200, (k % 256) as u8, 7]).collect();
    io::write_rgb_png(dir.path().join("c.png"), &rgb, 9, 6).unwrap();
    let g = io::read_gray(dir.path().join("c.png")).unwrap();
    assert_eq!(g[[1, 2]], 11.0);
    // 16-bit gray maps to the 8-bit scale.
    let img =
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(2, 1, vec![65535u16, 257]).unwrap();
    img.save(dir.path().join("s.png")).unwrap();
    let s = io::read_gray(dir.path().join("s.png")).unwrap();
    assert_eq!(s.into_raw_vec_and_offset().0, vec![255.0, 1.0]);
    // Not a PNG.
    std::fs::write(dir.path().join("x.png"), b"not an image").unwrap();
    let e = io::read_gray(dir.path().join("x.png")).unwrap_err();
    assert!(matches!(e, Error::Image { .. }) && e.to_string().contains("x.png"));
}

#[test]
fn sequences_are_sorted_pngs_only() {
    let dir = scratch("seq");
    let a = Array2::<f32>::zeros((2, 2));
    for n in ["000002.png", "000000.png", "000001.PNG"] {
        io::write_gray_png(dir.path().join(n), &a).unwrap();
    }
    std::fs::write(dir.path().join("truth.jsonl"), "").unwrap();
    std::fs::write(dir.path().join("poses.csv"), "").unwrap();
    let names: Vec<String> = io::list_frames(dir.path())
        .unwrap()
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["000000.png", "000001.PNG", "000002.png"]);
    let empty = scratch("seq-empty");
    assert!(io::list_frames(empty.path()).is_err());
    assert!(io::list_frames(empty.path().join("nope")).is_err());
}

#[test]
fn jsonl_matches_the_dataset_example() {
    let dir = scratch("jsonl");
    let example = r#"{"frame":"000012.png","t_s":0.24,"contacts":[{"id":3,"x_mm":-60.2,"y_mm":0.0,"z_mm":151.6,"fx_n":0.11,"fy_n":-0.02,"fz_n":-1.93,"x_px":512.4,"y_px":101.0,"d_pf":3.1,"dx":10.2,"dy":-1.0,"dz":-250.3,"area_px":2311}]}"#;
    let rec: FrameRecord = serde_json::from_str(example).unwrap();
    assert_eq!(serde_json::to_string(&rec).unwrap(), example);
    let empty = FrameRecord {
        frame: "000000.png".into(),
        t_s: 0.0,
        contacts: vec![],
        latency_ms: Some(3.5),
    };
    let truth = FrameRecord {
        frame: "000001.png".into(),
        t_s: 0.02,
        contacts: vec![ContactRecord {
            x_mm: 1.0,
            fz_n: -2.0,
            ..Default::default()
        }],
        latency_ms: None,
    };
    assert_eq!(
        serde_json::to_string(&truth.contacts[0]).unwrap(),
        r#"{"x_mm":1.0,"y_mm":0.0,"z_mm":0.0,"fx_n":0.0,"fy_n":0.0,"fz_n":-2.0}"#
    );
    let p = dir.path().join("c.jsonl");
    let mut w = io::JsonlWriter::create(&p).unwrap();
    for r in [&empty, &rec, &truth] {
        w.write(r).unwrap();
    }
    // Flushed per line: readable before the writer is dropped.
    let back: Vec<FrameRecord> = io::read_jsonl(&p).unwrap();
    assert_eq!(back, vec![empty, rec, truth]);
    assert!(
        std::fs::read_to_string(&p)
            .unwrap()
            .starts_with(r#"{"frame":"000000.png","t_s":0.0,"contacts":[],"latency_ms":3.5}"#)
    );
    drop(w);
    std::fs::write(
        &p,
        "{\"frame\":\"a\",\"t_s\":0,\"contacts\":[]}\n\n{oops}\n",
    )
    .unwrap();
    let e = io::read_jsonl::<FrameRecord>(&p).unwrap_err().to_string();
    assert!(e.contains("c.jsonl:3:"), "{e}");
}

fn row(test: usize, split: Split) -> TestRow {
    TestRow {
        test,
        frame: format!("frames/t{test:04}.png"),
        reference: format!("frames/t{test:04}_ref.png"),
        point: 2,
        indenter_mm: 10.0,
        yaw_deg: 0.0,
        pitch_deg: 15.0,
        repeat: 1,
        force_n: 1.5,
        split,
        x_mm: -114.1,
        y_mm: 0.0,
        fx_n: 0.39,
        fy_n: 0.02,
        fz_n: -1.45,
    }
}

#[test]
fn tests_csv_round_trip_and_the_dataset_example() {
    let dir = scratch("csv");
    let p = dir.path().join("tests.csv");
    let rows = vec![
        row(0, Split::Train),
        row(1, Split::Val),
        row(2, Split::Test),
        TestRow {
            point: 0,
            ..row(3, Split::Spot)
        },
    ];
    io::write_tests_csv(&p, &rows).unwrap();
    assert_eq!(io::read_tests_csv(&p).unwrap(), rows);
    let text = "test,frame,reference,point,indenter_mm,yaw_deg,pitch_deg,repeat,force_n,split,x_mm,y_mm,fx_n,fy_n,fz_n\n\
                0,frames/t0000.png,frames/t0000_ref.png,2,10,0,15,1,1.5,train,-114.1,0.0,0.39,0.02,-1.45\n";
    std::fs::write(&p, text).unwrap();
    assert_eq!(io::read_tests_csv(&p).unwrap(), vec![row(0, Split::Train)]);
    // Columns in another order plus an extra column are fine.
    let text = "split,extra,test,frame,reference,point,indenter_mm,yaw_deg,pitch_deg,repeat,force_n,x_mm,y_mm,fx_n,fy_n,fz_n\n\
                test,zz,2,frames/t0002.png,frames/t0002_ref.png,2,10,0,15,1,1.5,-114.1,0.0,0.39,0.02,-1.45\n";
    std::fs::write(&p, text).unwrap();
    assert_eq!(io::read_tests_csv(&p).unwrap(), vec![row(2, Split::Test)]);
}

#[test]
fn malformed_tests_csv_names_file_and_line() {
    let dir = scratch("badcsv");
    let p = dir.path().join("tests.csv");
    let head = "test,frame,reference,point,indenter_mm,yaw_deg,pitch_deg,repeat,force_n,split,x_mm,y_mm,fx_n,fy_n,fz_n\n";
    let good = "0,a.png,b.png,2,10,0,15,1,1.5,train,-114.1,0.0,0.39,0.02,-1.45\n";
    let cases = [
        (
            format!(
                "{head}{good}0,a.png,b.png,2,10,0,15,1,1.5,holdout,-114.1,0.0,0.39,0.02,-1.45\n"
            ),
            "tests.csv:3: unknown split `holdout` (expected train, val, test or spot)",
        ),
        (
            format!("{head}{good}0,a.png,b.png,2,10,0,15,1,x,train,-114.1,0.0,0.39,0.02,-1.45\n"),
            "tests.csv:3: column `force_n`",
        ),
        (format!("{head}0,a.png\n"), "tests.csv:2: 2 fields"),
        (head.replace(",fz_n", ",fz"), "missing column `fz_n`"),
        (String::new(), "empty file"),
    ];
    for (text, want) in cases {
        std::fs::write(&p, &text).unwrap();
        let e = io::read_tests_csv(&p).unwrap_err().to_string();
        assert!(e.contains(want), "`{e}` should contain `{want}`");
    }
}

#[test]
fn poses_csv_round_trip() {
    let dir = scratch("poses");
    let p = dir.path().join("poses.csv");
    let rows = vec![PoseRow {
        frame: "000000.png".into(),
        t_s: 0.0,
        x_m: 0.0,
        y_m: 0.0,
        z_m: 1.2,
        qw: 1.0,
        qx: 0.0,
        qy: 0.0,
        qz: 0.0,
    }];
    io::write_poses_csv(&p, &rows).unwrap();
    assert_eq!(io::read_poses_csv(&p).unwrap(), rows);
    std::fs::write(&p, "frame,t_s,x_m,y_m,z_m,qw,qx,qy\n").unwrap();
    assert!(
        io::read_poses_csv(&p)
            .unwrap_err()
            .to_string()
            .contains("qz")
    );
}

#[test]
fn sweeps_csv_round_trip_and_its_errors() {
    let dir = scratch("sweeps");
    let p = dir.path().join("sweeps.csv");
    let rows: Vec<io::SweepRow> = (0..3)
        .map(|i| io::SweepRow {
            sweep: i / 2,
            frame: format!("sweeps/s0_{i:05}.png"),
            reference: "sweeps/s0_ref.png".into(),
            indenter_mm: 10.0,
            force_n: 2.0,
            x_mm: -114.1 + 0.5 * i as f64,
            y_mm: 0.0,
            fx_n: 0.001,
            fy_n: -0.002,
            fz_n: -2.003,
        })
        .collect();
    io::write_sweeps_csv(&p, &rows).unwrap();
    assert_eq!(io::read_sweeps_csv(&p).unwrap(), rows);
    // As a test of the pipeline: point 0, no tilt, the sweep as `repeat`.
    let t = rows[2].as_test(7);
    assert_eq!(
        (t.test, t.point, t.repeat, t.yaw_deg, t.pitch_deg),
        (7, 0, 1, 0.0, 0.0)
    );
    assert_eq!(
        (t.x_mm, t.fz_n, &t.frame),
        (rows[2].x_mm, rows[2].fz_n, &rows[2].frame)
    );
    let head = "sweep,frame,reference,indenter_mm,force_n,x_mm,y_mm,fx_n,fy_n,fz_n\n";
    let good = "0,a.png,r.png,10,2,-114.1,0,0,0,-2\n";
    let cases = [
        (
            format!("{head}{good}0,a.png,r.png,10,0,-114.1,0,0,0,-2\n"),
            "sweeps.csv:3: column `force_n`: must be > 0",
        ),
        (
            format!("{head}{good}0,a.png,r.png,10,2,NaN,0,0,0,-2\n"),
            "sweeps.csv:3: column `x_mm`",
        ),
        (
            format!("{head}-1,a.png,r.png,10,2,0,0,0,0,-2\n"),
            "sweeps.csv:2: column `sweep`",
        ),
        (format!("{head}0,a.png\n"), "sweeps.csv:2: 2 fields"),
        (head.replace(",fz_n", ""), "missing column `fz_n`"),
        (String::new(), "empty file"),
    ];
    for (text, want) in cases {
        std::fs::write(&p, &text).unwrap();
        let e = io::read_sweeps_csv(&p).unwrap_err().to_string();
        assert!(e.contains(want), "`{e}` should contain `{want}`");
    }
}
