//! The image-sequence source: order, time stamps, and a broken frame in the middle.

#[path = "common/scratch.rs"]
mod scratch;
use scratch::scratch;

use ndarray::Array2;
use optical_tactile::capture::{FrameSource, SequenceSource};
use optical_tactile::io::{self, PoseRow};

#[test]
fn a_broken_frame_is_named_and_the_sequence_goes_on() {
    let tmp = scratch("seq");
    let dir = tmp.path();
    for k in [0usize, 1, 3] {
        let img = Array2::from_elem((4, 6), k as f32 * 10.0);
        io::write_gray_png(dir.join(format!("{k:06}.png")), &img).unwrap();
    }
    std::fs::write(dir.join("000002.png"), b"truncated").unwrap();
    io::write_poses_csv(
        dir.join("poses.csv"),
        &[PoseRow {
            frame: "000001.png".into(),
            t_s: 7.5,
            x_m: 0.0,
            y_m: 0.0,
            z_m: 0.0,
            qw: 1.0,
            qx: 0.0,
            qy: 0.0,
            qz: 0.0,
        }],
    )
    .unwrap();

    let mut seq = SequenceSource::open(dir).unwrap().with_fps(10.0).unwrap();
    assert_eq!(seq.remaining(), Some(4));
    let f0 = seq.next_frame().unwrap().unwrap();
    assert_eq!((f0.name.as_str(), f0.index, f0.t_s), ("000000.png", 0, 0.0));
    let f1 = seq.next_frame().unwrap().unwrap();
    assert_eq!(f1.t_s, 7.5, "time stamp from poses.csv");
    assert_eq!(f1.image[[0, 0]], 10.0);
    let e = seq.next_frame().unwrap().unwrap_err().to_string();
    assert!(e.contains("000002.png"), "{e}");
    let f3 = seq.next_frame().unwrap().unwrap();
    assert_eq!((f3.index, f3.t_s), (3, 0.3));
    assert!(seq.next_frame().is_none());
    assert!(SequenceSource::open(dir).unwrap().with_fps(0.0).is_err());
}
