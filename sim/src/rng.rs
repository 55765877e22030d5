//! A small deterministic PRNG (SplitMix64) and a counter-based hash for
//! per-pixel noise.
//!
//! The simulator must give identical output for a seed on every machine and for
//! any number of threads, without a `rand` dependency. Sequential draws (marker
//! layout, load-cell noise) use [`SplitMix64`]; per-pixel noise uses [`hash64`]
//! of (stream, pixel index), so that each row band can draw its own noise in any
//! order and still get the same numbers.

/// SplitMix64 (Steele, Lea & Flood 2014): tiny, fast, passes BigCrush, and any
/// 64-bit seed (including 0) is a good seed.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// The SplitMix64 output function: a strong 64-bit mixer.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a stream key and a counter, for counter-based (order-free) noise.
#[inline]
pub fn hash64(stream: u64, counter: u64) -> u64 {
    mix64(stream ^ mix64(counter.wrapping_mul(GOLDEN).wrapping_add(GOLDEN)))
}

/// An approximately standard-normal number from one 64-bit hash: the sum of four
/// 16-bit uniforms (Irwin-Hall), rescaled to unit variance. Its tails stop at
/// about 3.5 sigma, which is fine for camera noise and far cheaper than
/// Box-Muller per pixel.
#[inline]
pub fn approx_normal_from_bits(bits: u64) -> f32 {
    let a = (bits & 0xFFFF) as u32;
    let b = ((bits >> 16) & 0xFFFF) as u32;
    let c = ((bits >> 32) & 0xFFFF) as u32;
    let d = (bits >> 48) as u32;
    // Each uniform on [0, 65535]: mean 32767.5, variance (65536^2 - 1) / 12.
    let sum = (a + b + c + d) as f32;
    // sqrt(4 * (65536^2 - 1) / 12) = 37837.2...
    (sum - 131_070.0) * (1.0 / 37_837.23)
}

impl SplitMix64 {
    /// A generator for `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN);
        mix64(self.state)
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    #[inline]
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }

    /// Uniform integer in `0..n` (`n > 0`), by widening multiplication (Lemire);
    /// the bias is below 2^-32 for the sizes used here.
    #[inline]
    pub fn below(&mut self, n: u64) -> u64 {
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// Standard normal by Box-Muller (exact, for the few draws that need it).
    pub fn normal(&mut self) -> f64 {
        // 1 - u lies in (0, 1], so the log is finite.
        let u1 = 1.0 - self.next_f64();
        let u2 = self.next_f64();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// A new independent generator derived from this one (for sub-streams).
    pub fn fork(&mut self) -> SplitMix64 {
        SplitMix64::new(mix64(self.next_u64() ^ 0xD1B5_4A32_D192_ED03))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_stream_and_different_seeds_differ() {
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        let mut c = SplitMix64::new(8);
        let xa: Vec<u64> = (0..8).map(|_| a.next_u64()).collect();
        let xb: Vec<u64> = (0..8).map(|_| b.next_u64()).collect();
        let xc: Vec<u64> = (0..8).map(|_| c.next_u64()).collect();
        assert_eq!(xa, xb);
        assert_ne!(xa, xc);
    }

    #[test]
    fn uniform_and_normal_moments() {
        let mut r = SplitMix64::new(1);
        let n = 200_000;
        let (mut s, mut s2, mut g, mut g2, mut h, mut h2) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..n {
            let u = r.next_f64();
            assert!((0.0..1.0).contains(&u));
            s += u;
            s2 += u * u;
            let z = r.normal();
            g += z;
            g2 += z * z;
            let q = approx_normal_from_bits(hash64(3, i)) as f64;
            h += q;
            h2 += q * q;
        }
        let nf = n as f64;
        assert!((s / nf - 0.5).abs() < 0.005);
        assert!((s2 / nf - 1.0 / 3.0).abs() < 0.005);
        assert!((g / nf).abs() < 0.01);
        assert!((g2 / nf - 1.0).abs() < 0.02);
        assert!((h / nf).abs() < 0.01);
        assert!((h2 / nf - 1.0).abs() < 0.02);
    }

    #[test]
    fn below_stays_in_range() {
        let mut r = SplitMix64::new(99);
        let mut seen = [false; 5];
        for _ in 0..1000 {
            let k = r.below(5) as usize;
            seen[k] = true;
        }
        assert!(seen.iter().all(|&b| b));
    }
}
