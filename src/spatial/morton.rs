//! Morton (Z-order) keys of voxel coordinates: a level's voxels sorted by key are sorted
//! spatially, which the file's blocks and the runtime's look-ups rely on.

use glam::UVec3;

/// Interleaves the low 21 bits of x, y and z (Morton / Z-order).
#[inline]
pub fn morton3(p: UVec3) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut x = (v as u64) & 0x1f_ffff;
        x = (x | x << 32) & 0x001f_0000_0000_ffff;
        x = (x | x << 16) & 0x001f_0000_ff00_00ff;
        x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
        x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
        x = (x | x << 2) & 0x1249_2492_4924_9249;
        x
    }
    spread(p.x) | spread(p.y) << 1 | spread(p.z) << 2
}

/// Inverse of [`morton3`].
#[inline]
pub fn demorton3(m: u64) -> UVec3 {
    fn compact(mut x: u64) -> u32 {
        x &= 0x1249_2492_4924_9249;
        x = (x ^ (x >> 2)) & 0x10c3_0c30_c30c_30c3;
        x = (x ^ (x >> 4)) & 0x100f_00f0_0f00_f00f;
        x = (x ^ (x >> 8)) & 0x001f_0000_ff00_00ff;
        x = (x ^ (x >> 16)) & 0x001f_0000_0000_ffff;
        x = (x ^ (x >> 32)) & 0x1f_ffff;
        x as u32
    }
    UVec3::new(compact(m), compact(m >> 1), compact(m >> 2))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;

    #[test]
    fn morton_round_trip() {
        let mut rng = Pcg32::new(1, 1);
        for _ in 0..1000 {
            let p = UVec3::new(
                rng.next_u32() & 0x1f_ffff,
                rng.next_u32() & 0x1f_ffff,
                rng.next_u32() & 0x1f_ffff,
            );
            assert_eq!(demorton3(morton3(p)), p);
        }
        assert!(morton3(UVec3::new(1, 0, 0)) < morton3(UVec3::new(0, 1, 0)));
        // A parent's key is its child's key shifted by three bits.
        let c = UVec3::new(13, 6, 9);
        assert_eq!(morton3(c) >> 3, morton3(c / 2));
    }
}
