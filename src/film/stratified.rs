//! The image loop's stratified sampler: the numbers a sample of a pixel draws first are
//! low-discrepancy over the pixel's samples, the rest come from the pixel's random stream.

use glam::Vec2;

use super::Sample;
use crate::math::rng::Pcg32;
use crate::math::sampling::Sampler;

/// The sampler of one sample of a pixel: its first [`STRATIFIED_DIMENSIONS`] numbers (each call
/// of [`Sampler::next_1d`] or [`Sampler::next_2d`] one dimension) are padded low-discrepancy
/// points of the sample's index, one sequence a dimension with its own nonlinear shuffle of the
/// index and its own digital shift ([`crate::math::lowdiscrepancy::shifted_2d`], seeded by the
/// pixel and the dimension; Owen-scrambling the values too cost 10–20% of a cone), so that the
/// pixel's samples stratify the choices a cone makes first (its level, which hit a reservoir shades, the
/// light sample, the ABSDF sample); the numbers after them come from `inner`. Each number alone
/// is uniform, so every estimate stays unbiased; what falls is its variance over the pixel.
pub struct Stratified<'a, S: Sampler + ?Sized> {
    inner: &'a mut S,
    index: u32,
    seed: u32,
    dimension: u32,
}

/// The dimensions [`Stratified`] stratifies: the level's dither (continuous level of detail),
/// the reservoir's pick, then two light and ABSDF sample sets (3 dimensions each).
pub const STRATIFIED_DIMENSIONS: u32 = 8;

impl<'a, S: Sampler + ?Sized> Stratified<'a, S> {
    /// Sample `index` of the pixel of `seed`, drawing from `inner` past the stratified
    /// dimensions.
    pub fn new(inner: &'a mut S, index: u32, seed: u32) -> Self {
        Stratified {
            inner,
            index,
            seed,
            dimension: 0,
        }
    }

    /// The scramble seeds of the next stratified dimension (one 64-bit hash of the pixel's
    /// seed and the dimension, and a multiple of it), or `None` past them.
    #[inline]
    fn next_dimension(&mut self) -> Option<[u32; 3]> {
        if self.dimension >= STRATIFIED_DIMENSIONS {
            return None;
        }
        self.dimension += 1;
        let h = crate::math::rng::mix64(((self.seed as u64) << 32) | self.dimension as u64);
        let g = h.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        Some([h as u32, (h >> 32) as u32, (g >> 32) as u32])
    }
}

impl<'a> Stratified<'a, Pcg32> {
    /// The sampler of one sample of the shared image loop ([`Sample`]).
    pub fn of_sample<'b>(s: &'a mut Sample<'b>) -> Stratified<'a, Pcg32> {
        Stratified::new(s.rng, s.index, s.pixel_seed)
    }
}

impl<S: Sampler + ?Sized> Sampler for Stratified<'_, S> {
    #[inline]
    fn next_1d(&mut self) -> f32 {
        match self.next_dimension() {
            Some([a, b, _]) => crate::math::lowdiscrepancy::shifted_1d(self.index, [a, b]),
            None => self.inner.next_1d(),
        }
    }
    #[inline]
    fn next_2d(&mut self) -> Vec2 {
        match self.next_dimension() {
            Some(seeds) => crate::math::lowdiscrepancy::shifted_2d(self.index, seeds),
            None => self.inner.next_2d(),
        }
    }
}
