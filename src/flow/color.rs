//! Middlebury colour-wheel rendering of flow fields.
//!
//! Hue gives the direction, saturation the magnitude relative to a maximum
//! (the largest magnitude in the field unless given), white means no motion:
//! the convention of the Middlebury flow benchmark (Baker et al. 2011).

use super::FlowField;

/// The 55-colour Middlebury wheel: red-yellow-green-cyan-blue-magenta.
fn wheel() -> Vec<[f32; 3]> {
    const SEGS: [(usize, [f32; 3], [f32; 3]); 6] = [
        (15, [255.0, 0.0, 0.0], [0.0, 255.0, 0.0]), // RY: G rises
        (6, [255.0, 255.0, 0.0], [-255.0, 0.0, 0.0]), // YG: R falls
        (4, [0.0, 255.0, 0.0], [0.0, 0.0, 255.0]),  // GC: B rises
        (11, [0.0, 255.0, 255.0], [0.0, -255.0, 0.0]), // CB: G falls
        (13, [0.0, 0.0, 255.0], [255.0, 0.0, 0.0]), // BM: R rises
        (6, [255.0, 0.0, 255.0], [0.0, 0.0, -255.0]), // MR: B falls
    ];
    let mut w = Vec::with_capacity(55);
    for (n, start, delta) in SEGS {
        for i in 0..n {
            let t = i as f32 / n as f32;
            w.push([
                start[0] + t * delta[0],
                start[1] + t * delta[1],
                start[2] + t * delta[2],
            ]);
        }
    }
    w
}

/// Colour of one flow vector `(u, v)` already divided by the maximum
/// magnitude (so `|(u, v)| <= 1` is inside the wheel), as 8-bit RGB.
pub fn vector_to_rgb(u: f32, v: f32) -> [u8; 3] {
    vector_rgb(&wheel(), u, v)
}

fn vector_rgb(wheel: &[[f32; 3]], u: f32, v: f32) -> [u8; 3] {
    if !u.is_finite() || !v.is_finite() {
        return [0, 0, 0];
    }
    let n = wheel.len();
    let rad = u.hypot(v);
    let a = (-v).atan2(-u) / std::f32::consts::PI; // -1..1
    let fk = (a + 1.0) / 2.0 * (n - 1) as f32;
    let k0 = (fk.floor() as usize).min(n - 1);
    let k1 = (k0 + 1) % n;
    let f = fk - k0 as f32;
    let mut rgb = [0u8; 3];
    for c in 0..3 {
        let col = ((1.0 - f) * wheel[k0][c] + f * wheel[k1][c]) / 255.0;
        let col = if rad <= 1.0 {
            1.0 - rad * (1.0 - col)
        } else {
            col * 0.75 // out of range: darker
        };
        rgb[c] = (255.0 * col).round().clamp(0.0, 255.0) as u8;
    }
    rgb
}

/// Renders `flow` as interleaved 8-bit RGB (`width * height * 3` bytes, row
/// major). `max_magnitude` sets full saturation; `None` uses the field's
/// largest finite magnitude. Non-finite vectors are black.
pub fn flow_to_rgb(flow: &FlowField, max_magnitude: Option<f32>) -> Vec<u8> {
    let maxm = max_magnitude.unwrap_or_else(|| {
        flow.u
            .iter()
            .zip(flow.v.iter())
            .map(|(&u, &v)| u.hypot(v))
            .filter(|m| m.is_finite())
            .fold(0.0f32, f32::max)
    });
    let scale = if maxm > 0.0 { 1.0 / maxm } else { 0.0 };
    let wh = wheel();
    let mut out = Vec::with_capacity(flow.u.len() * 3);
    for (&u, &v) in flow.u.iter().zip(flow.v.iter()) {
        out.extend_from_slice(&vector_rgb(&wh, u * scale, v * scale));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_is_white_and_directions_differ() {
        assert_eq!(vector_to_rgb(0.0, 0.0), [255, 255, 255]);
        // +x (rightwards) is red-ish in the Middlebury wheel... up to the
        // wheel's orientation; check only that opposite directions differ and
        // full magnitude is saturated.
        let r = vector_to_rgb(1.0, 0.0);
        let l = vector_to_rgb(-1.0, 0.0);
        assert_ne!(r, l);
        assert!(r.iter().any(|&c| c < 50));
        assert_eq!(vector_to_rgb(f32::NAN, 0.0), [0, 0, 0]);
        let f = FlowField::zeros(3, 2);
        assert_eq!(flow_to_rgb(&f, None), vec![255u8; 18]);
    }
}
