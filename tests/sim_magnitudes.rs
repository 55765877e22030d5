use optical_tactile::sim::{Contact, SimConfig, SyntheticSensor};

#[test]
fn print_magnitudes() {
    let s = SyntheticSensor::new(SimConfig::default(), 1).unwrap();
    let c = Contact::rod(0.0, [0.0, 0.0, -2.0], 5.0);
    for _ in 0..3 {
        let t = std::time::Instant::now();
        let d = s.marker_displacements(&[c]).unwrap();
        let t1 = t.elapsed();
        let r0 = s.render_indexed(0, &[], false).unwrap();
        let t2 = t.elapsed();
        let r1 = s.render_indexed(0, &[c], false).unwrap();
        let t3 = t.elapsed();
        let r2 = s.render_indexed(0, &[c], true).unwrap();
        let t4 = t.elapsed();
        println!(
            "disp {t1:?} render-empty {:?} render-contact {:?} with flow {:?} threads {}",
            t2 - t1,
            t3 - t2,
            t4 - t3,
            rayon::current_num_threads()
        );
        std::hint::black_box((d, r0, r1, r2));
    }
}
