//! Synthetic motion profiles for the profile model's tests.

/// Per channel, the profile over `n` cells of `scale` full-resolution
/// pixels (cell `j` centred on pixel `(j + 0.5) * scale - 0.5`) of contacts
/// at columns `cols` with local forces `forces`, where channel `ch` answers
/// force component `k` of a contact at column `c` with `response(ch, k, c,
/// t)` at offset `t` pixels: the sum over contacts and components of the
/// force times the response.
pub fn channel_profiles<const C: usize>(
    n: usize,
    scale: f64,
    response: impl Fn(usize, usize, f64, f64) -> f64,
    cols: &[f64],
    forces: &[[f64; 3]],
) -> [Vec<f64>; C] {
    std::array::from_fn(|ch| {
        (0..n)
            .map(|j| {
                let x = (j as f64 + 0.5) * scale - 0.5;
                cols.iter()
                    .zip(forces)
                    .map(|(c, f)| {
                        f.iter()
                            .enumerate()
                            .map(|(k, fk)| fk * response(ch, k, *c, x - c))
                            .sum::<f64>()
                    })
                    .sum()
            })
            .collect()
    })
}
