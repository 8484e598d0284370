//! A scrambled low-discrepancy sequence: the first two dimensions of Sobol's sequence with
//! nested uniform (Owen) scrambling by hashing, after Burley 2020, "Practical Hash-based Owen
//! Scrambling". Every prefix of 2^m points is a (0, m, 2)-net: each elementary rectangle of area
//! 2^-m holds exactly one point, whatever the seed.

use glam::Vec2;

/// Direction numbers of Sobol's second dimension (primitive polynomial x + 1).
const fn sobol_dim1() -> [u32; 32] {
    let mut v = [0u32; 32];
    v[0] = 1 << 31;
    let mut i = 1;
    while i < 32 {
        v[i] = v[i - 1] ^ (v[i - 1] >> 1);
        i += 1;
    }
    v
}
const DIM1: [u32; 32] = sobol_dim1();

/// `DIM1_BYTES[b][v]`: the XOR of the direction numbers of the set bits of byte value `v` at
/// byte `b` of the index, so that the second dimension takes four lookups instead of a loop
/// over the index's bits (after scrambling, about 16 unpredictable branches per point; the
/// line of that loop held 15.5% of `estimate`'s profile samples in the maple's 256³ bake).
const fn sobol_dim1_bytes() -> [[u32; 256]; 4] {
    let mut t = [[0u32; 256]; 4];
    let mut b = 0;
    while b < 4 {
        let mut v = 0;
        while v < 256 {
            let mut y = 0u32;
            let mut k = 0;
            while k < 8 {
                if v & (1 << k) != 0 {
                    y ^= DIM1[8 * b + k];
                }
                k += 1;
            }
            t[b][v] = y;
            v += 1;
        }
        b += 1;
    }
    t
}
static DIM1_BYTES: [[u32; 256]; 4] = sobol_dim1_bytes();

/// Sobol's second dimension of index `i`: the XOR of the direction numbers of its set bits.
#[inline]
fn sobol_dim1_of(i: u32) -> u32 {
    let t = &DIM1_BYTES;
    t[0][(i & 0xff) as usize]
        ^ t[1][((i >> 8) & 0xff) as usize]
        ^ t[2][((i >> 16) & 0xff) as usize]
        ^ t[3][(i >> 24) as usize]
}

/// Laine–Karras style hash permutation: bit k of the output depends only on bits ≤ k.
#[inline]
fn lk_permutation(mut x: u32, seed: u32) -> u32 {
    x = x.wrapping_add(seed);
    x ^= x.wrapping_mul(0x6c50_b47c);
    x ^= x.wrapping_mul(0xb82f_1e52);
    x ^= x.wrapping_mul(0xc7af_e638);
    x ^= x.wrapping_mul(0x8d22_f6e6);
    x
}

/// Nested uniform scramble of a 32-bit fixed-point value.
#[inline]
fn owen_scramble(x: u32, seed: u32) -> u32 {
    lk_permutation(x.reverse_bits(), seed).reverse_bits()
}

#[inline]
fn hash(a: u32, b: u32) -> u32 {
    (super::rng::mix64(((a as u64) << 32) | b as u64) >> 32) as u32
}

/// A 32-bit fixed-point fraction as an f32 in [0, 1) (its top 24 bits, so it never rounds to 1).
#[inline]
fn unit(x: u32) -> f32 {
    (x >> 8) as f32 / 16_777_216.0
}

/// Point `index` of the scrambled 2D sequence for `seed`, in [0,1)².
#[inline]
pub fn sobol_2d(index: u32, seed: u32) -> Vec2 {
    // Shuffle the order (so that prefixes of different seeds differ), then generate.
    let i = owen_scramble(index, hash(seed, 0));
    let x = i.reverse_bits();
    let y = sobol_dim1_of(i);
    let x = owen_scramble(x, hash(seed, 1));
    let y = owen_scramble(y, hash(seed, 2));
    Vec2::new(unit(x), unit(y))
}

/// A cheaper padded point for per-pixel sampling: the index shuffled by a nested uniform
/// scramble (a nonlinear permutation within every aligned run of 2^m indices, so that
/// dimensions with their own shuffles are not correlated), then Sobol's first two dimensions
/// with a random digital shift (XOR) each instead of a second and third Owen scramble. Every
/// aligned run of 2^m indices is still a (0, m, 2)-net, and each point alone is uniform over
/// the shifts. Seeds: the shuffle's, then x's and y's shifts.
#[inline]
pub fn shifted_2d(index: u32, seeds: [u32; 3]) -> Vec2 {
    let i = owen_scramble(index, seeds[0]);
    let x = i.reverse_bits() ^ seeds[1];
    let y = sobol_dim1_of(i) ^ seeds[2];
    Vec2::new(unit(x), unit(y))
}

/// The first dimension of [`shifted_2d`] alone: one aligned run of 2^m indices falls one to
/// each interval of 2^-m.
#[inline]
pub fn shifted_1d(index: u32, seeds: [u32; 2]) -> f32 {
    let x = owen_scramble(index, seeds[0]).reverse_bits() ^ seeds[1];
    unit(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The byte tables give the bit-by-bit XOR of the direction numbers.
    #[test]
    fn dim1_tables_match_the_bit_loop() {
        let by_bits = |i: u32| {
            (0..32)
                .filter(|k| i >> k & 1 != 0)
                .fold(0u32, |y, k| y ^ DIM1[k])
        };
        let mut rng = crate::math::rng::Pcg32::new(5, 1);
        for i in (0..4096)
            .chain((0..4096).map(|_| rng.next_u32()))
            .chain([u32::MAX])
        {
            assert_eq!(sobol_dim1_of(i), by_bits(i), "index {i:#x}");
        }
    }

    #[test]
    fn nets_are_stratified_for_every_seed() {
        for seed in [0u32, 1, 77, 123_456] {
            let m = 8;
            let n = 1u32 << m;
            let pts: Vec<Vec2> = (0..n).map(|i| sobol_2d(i, seed)).collect();
            for a in 0..=m {
                let (nx, ny) = (1u32 << a, 1u32 << (m - a));
                let mut seen = vec![false; n as usize];
                for p in &pts {
                    assert!((0.0..1.0).contains(&p.x) && (0.0..1.0).contains(&p.y));
                    let cell = ((p.y * ny as f32) as u32) * nx + (p.x * nx as f32) as u32;
                    assert!(
                        !seen[cell as usize],
                        "seed {seed}: two points in one {nx}x{ny} cell"
                    );
                    seen[cell as usize] = true;
                }
            }
        }
        assert_ne!(sobol_2d(3, 1), sobol_2d(3, 2));
    }

    /// Integration error of a smooth function: far below random sampling's at 1024 points.
    #[test]
    fn integrates_better_than_random() {
        let f = |p: Vec2| (3.0 * p.x).sin() * (2.0 * p.y).cos() + p.x * p.y;
        let exact = (1.0 - 3f64.cos()) / 3.0 * (2f64.sin() / 2.0) + 0.25;
        let est: f64 = (0..1024).map(|i| f(sobol_2d(i, 9)) as f64).sum::<f64>() / 1024.0;
        assert!((est - exact).abs() < 2e-3, "{est} vs {exact}");
    }

    /// The padded points of the image loop: every aligned run of 2^m indices is a net in 2D
    /// and stratified in 1D, for any seeds; other seeds give other points.
    #[test]
    fn shifted_points_are_stratified() {
        let mut rng = crate::math::rng::Pcg32::new(11, 4);
        for _ in 0..4 {
            let seeds = [rng.next_u32(), rng.next_u32(), rng.next_u32()];
            for m in 0..=6u32 {
                let n = 1u32 << m;
                for start in [0u32, n, 7 * n] {
                    let mut seen1 = vec![false; n as usize];
                    for a in 0..=m {
                        let (nx, ny) = (1u32 << a, 1u32 << (m - a));
                        let mut seen = vec![false; n as usize];
                        for i in start..start + n {
                            let p = shifted_2d(i, seeds);
                            assert!((0.0..1.0).contains(&p.x) && (0.0..1.0).contains(&p.y));
                            let cell = ((p.y * ny as f32) as u32) * nx + (p.x * nx as f32) as u32;
                            assert!(!seen[cell as usize], "{seeds:?}: two in a {nx}x{ny} cell");
                            seen[cell as usize] = true;
                        }
                    }
                    for i in start..start + n {
                        let x = shifted_1d(i, [seeds[0], seeds[1]]);
                        let c = (x * n as f32) as usize;
                        assert!(
                            !seen1[c],
                            "{seeds:?}, run {start}..+{n}: two in interval {c}"
                        );
                        seen1[c] = true;
                    }
                }
            }
        }
        // Another shuffle's seed (hashed, as the image loop's are) gives another order, another
        // shift other values.
        let [a, b, c, d] = [1u64, 2, 3, 4].map(|k| (crate::math::rng::mix64(k) >> 32) as u32);
        let run = |seeds: [u32; 3]| (0..16).map(|i| shifted_2d(i, seeds)).collect::<Vec<_>>();
        assert_ne!(run([a, b, c]), run([d, b, c]));
        assert_ne!(run([a, b, c]), run([a, d, c]));
        assert_ne!(shifted_1d(0, [a, b]), shifted_1d(0, [a, c]));
    }
}
