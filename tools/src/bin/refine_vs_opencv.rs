//! Compares our refinement with OpenCV's `VariationalRefinement` on the same input.
//!
//! 1. Write the input and OpenCV's result (needs `numpy` and `opencv-python` 5):
//!    save the script below as `gen.py`, run `python3 gen.py DIR`;
//! 2. `cargo run --release -p optical-tactile-tools --bin refine_vs_opencv -- DIR`.
//!
//! Prints, for `opencv()`, `opencv()` with OpenCV 5.0's actual default epsilon 0.001
//! (DIS does not set it), and `accurate()`: AEPE against the true flow and the mean
//! endpoint distance to OpenCV's output (16 px border excluded).
//!
//! ```text
//! import numpy as np, cv2, sys
//! d = sys.argv[1]
//! w, h = 160, 120
//! rng = np.random.default_rng(1)
//! yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
//! def markers(fu, fv):
//!     img = np.full((h, w), 200.0, np.float32)
//!     for y in np.arange(3.0, h, 6.0):
//!         for x in np.arange(3.0, w, 6.0):
//!             x0 = x + rng.uniform(-1, 1) * 0 ; y0 = y
//!             cx, cy = x + fu(x, y), y + fv(x, y)
//!             r2 = (xx - cx) ** 2 + (yy - cy) ** 2
//!             img -= 150.0 * np.exp(-r2 / 2.0)
//!     return img
//! bump = lambda x, y, c: 1.2 * np.exp(-((x - 80) ** 2 + (y - 60) ** 2) / (2 * 20.0 ** 2)) * ((x - 80) if c == 0 else (y - 60)) / 20.0
//! i0 = np.clip(np.round(markers(lambda x, y: 0, lambda x, y: 0)), 0, 255).astype(np.uint8)
//! i1 = np.clip(np.round(markers(lambda x, y: 0.3 + bump(x, y, 0), lambda x, y: -0.2 + bump(x, y, 1))), 0, 255).astype(np.uint8)
//! tu = 0.3 + bump(xx, yy, 0); tv = -0.2 + bump(xx, yy, 1)
//! u0 = (tu + 0.2 * np.sin(xx / 7)).astype(np.float32); v0 = (tv + 0.2 * np.cos(yy / 5)).astype(np.float32)
//! for name, a in [("i0", i0.astype(np.float32)), ("i1", i1.astype(np.float32)), ("u0", u0), ("v0", v0), ("tu", tu.astype(np.float32)), ("tv", tv.astype(np.float32))]:
//!     a.astype('<f4').tofile(f"{d}/{name}.f32")
//! cv2.setNumThreads(1)
//! vr = cv2.VariationalRefinement_create()
//! u, v = vr.calcUV(i0, i1, u0.copy(), v0.copy())
//! u.astype('<f4').tofile(f"{d}/cv_u.f32"); v.astype('<f4').tofile(f"{d}/cv_v.f32")
//! b = 16
//! e = lambda a, b_: np.mean(np.hypot(a[0][b:-b, b:-b] - b_[0][b:-b, b:-b], a[1][b:-b, b:-b] - b_[1][b:-b, b:-b]))
//! print("AEPE init", e((u0, v0), (tu, tv)), "opencv VR", e((u, v), (tu, tv)))
//! ```

#[path = "../../../examples/cli_support/mod.rs"]
mod cli_support;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use cli_support::{Failure, Sink};
use ndarray::Array2;
use optical_tactile::flow::refine::{RefineParams, VariationalRefiner};

const W: usize = 160;
const H: usize = 120;

/// Compares our variational refinement with OpenCV's on the same input
/// (written by the script in this tool's documentation).
#[derive(Parser, Debug)]
#[command(name = "refine_vs_opencv")]
struct Cli {
    /// Folder with i0, i1, u0, v0, tu, tv, cv_u, cv_v as little-endian f32
    /// files (160x120).
    #[arg(value_name = "DIR")]
    dir: PathBuf,
}

fn load(dir: &Path, name: &str) -> Result<Array2<f32>, String> {
    let path = dir.join(format!("{name}.f32"));
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let v: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Array2::from_shape_vec((H, W), v)
        .map_err(|_| format!("{}: expected a 160x120 f32 file", path.display()))
}

/// Mean endpoint distance between two flows, 16 px border excluded.
fn aepe(u: &Array2<f32>, v: &Array2<f32>, ru: &Array2<f32>, rv: &Array2<f32>) -> f64 {
    let b = 16;
    let mut s = 0.0f64;
    let mut n = 0;
    for y in b..H - b {
        for x in b..W - b {
            s += ((u[[y, x]] - ru[[y, x]]) as f64).hypot((v[[y, x]] - rv[[y, x]]) as f64);
            n += 1;
        }
    }
    s / n as f64
}

fn main() -> ExitCode {
    cli_support::finish(run(&Cli::parse()).map(|()| ExitCode::SUCCESS))
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let mut out = Sink::stdout();
    let mut arrays = Vec::with_capacity(8);
    for name in ["i0", "i1", "u0", "v0", "tu", "tv", "cv_u", "cv_v"] {
        arrays.push(load(&cli.dir, name)?);
    }
    let Ok([i0, i1, u0, v0, tu, tv, cu, cv]) = <[Array2<f32>; 8]>::try_from(arrays) else {
        unreachable!("eight names, eight arrays");
    };
    let configs = [
        ("opencv()", RefineParams::opencv()),
        (
            "opencv(), epsilon 0.001",
            RefineParams {
                epsilon: 0.001,
                ..RefineParams::opencv()
            },
        ),
        ("accurate()", RefineParams::accurate()),
    ];
    writeln!(out, "initial flow: AEPE {:.4}", aepe(&u0, &v0, &tu, &tv))?;
    writeln!(out, "OpenCV VR: AEPE {:.4}", aepe(&cu, &cv, &tu, &tv))?;
    for (name, p) in configs {
        let mut vr = VariationalRefiner::new(p);
        vr.set_reference(i0.view())?;
        let (mut u, mut v) = (u0.clone(), v0.clone());
        vr.refine(i1.view(), &mut u, &mut v)?;
        writeln!(
            out,
            "{name}: AEPE {:.4}, mean distance to OpenCV VR {:.2e} px",
            aepe(&u, &v, &tu, &tv),
            aepe(&u, &v, &cu, &cv)
        )?;
    }
    Ok(())
}
