//! Synthetic sensor frames with ground truth, written in the DATASET.md formats.
//!
//! ```text
//! cargo run --release --example simulate -- <scenario> --out DIR [--seed N] [...]
//! cargo run --release --example simulate -- --help
//! ```

use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use ndarray::{Array2, s};
use optical_tactile::Result;
use optical_tactile::viz::{Canvas, Rgb, colormap};
use optical_tactile_sim::cli::{self, Command};
use optical_tactile_sim::scenario;
use optical_tactile_sim::{Press, SimConfig, SyntheticSensor};

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("simulate: error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: &[String]) -> Result<()> {
    let t0 = Instant::now();
    match cli::parse(args)? {
        Command::Help => print!("{}", cli::HELP),
        Command::Run(run) => {
            let (sc, common) = *run;
            if common.config.full_frame {
                let (x, y, w, h) = common.config.camera.crop();
                println!("full frame; the sensing strip is the crop x={x} y={y} w={w} h={h}");
            }
            let sum = scenario::run(&sc, &common)?;
            println!(
                "wrote {} frames to {} in {:.1} s",
                sum.frames,
                sum.out.display(),
                t0.elapsed().as_secs_f64()
            );
        }
        Command::Fixtures { out, docs, seed } => {
            scenario::fixtures(&out, seed)?;
            if let Some(d) = docs {
                pictures(&d, seed)?;
            }
            println!(
                "fixtures written to {} in {:.1} s",
                out.display(),
                t0.elapsed().as_secs_f64()
            );
        }
    }
    Ok(())
}

/// README pictures: an enlarged crop of a reference frame, and the true motion
/// field of a two-rod press (magnitude in colour, arrows exaggerated).
fn pictures(dir: &Path, seed: u64) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| optical_tactile::Error::io(dir, e))?;
    let mut sensor = SyntheticSensor::new(SimConfig::default(), seed)?;
    let (reference, _) = sensor.render(&[])?;
    let crop = reference.slice(s![.., 640..960]).to_owned();
    let scale = 3;
    let mut c = Canvas::new(crop.ncols() * scale, crop.nrows() * scale, Rgb(0, 0, 0));
    c.gray(&crop, 0, 0, scale);
    c.save_png(dir.join("reference_frame.png"))?;

    let contacts = [
        Press::rod(-20.0, [0.0, 0.0, -2.0], 5.0),
        Press::rod(20.0, [0.0, 0.0, -1.5], 5.0),
    ];
    let (_, flow) = sensor.render(&contacts)?;
    let (x0, x1) = (560usize, 1040usize);
    let mag: Array2<f64> = flow.magnitude().slice(s![.., x0..x1]).mapv(|v| v as f64);
    let scale = 2;
    let mut c = Canvas::new(mag.ncols() * scale, mag.nrows() * scale, Rgb(0, 0, 0));
    c.scalar(&mag, 0, 0, scale);
    let exaggerate = 20.0;
    let step = 12;
    for y in (step / 2..flow.height()).step_by(step) {
        for x in (x0 + step / 2..x1).step_by(step) {
            let (u, v) = (flow.u[[y, x]] as f64, flow.v[[y, x]] as f64);
            let (px, py) = (((x - x0) * scale) as f64, (y * scale) as f64);
            c.arrow(
                px,
                py,
                px + exaggerate * u * scale as f64,
                py + exaggerate * v * scale as f64,
                Rgb(255, 255, 255),
            );
        }
    }
    // Contact positions as dots (true x_px).
    for ct in &contacts {
        let r = scenario::truth_record(&sensor, ct);
        let (xp, yp) = (r.x_px.unwrap_or(0.0), r.y_px.unwrap_or(0.0));
        c.dot(
            (xp - x0 as f64) * scale as f64,
            yp * scale as f64,
            4.0,
            colormap(1.0),
        );
    }
    c.save_png(dir.join("press_motion.png"))?;
    Ok(())
}
