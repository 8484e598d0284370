//! The truncated ellipsoid primitive (paper §6.1, §7.1): the intersection of a voxel with an
//! ellipsoid bounding the voxel's surface samples. The ellipsoid comes from a PCA of the sample
//! positions: the points are expressed in the principal axes, each axis scaled to the unit
//! interval, a bounding sphere is taken there, and it is mapped back.

use glam::{Mat3, Vec3};

use crate::math::sggx::symmetric_eigen;
use crate::spatial::Ellipsoid;

/// Fits the ellipsoid of a voxel's sample positions. `min_extent` (a small fraction of the
/// voxel size) keeps flat and fibre-like sets from giving a degenerate ellipsoid. `None`
/// without points.
pub fn fit_ellipsoid(points: &[Vec3], min_extent: f32) -> Option<Ellipsoid> {
    fit_ellipsoid_bounding(points, &[], min_extent)
}

/// Fits an ellipsoid oriented by the PCA of `points` (the surface samples) that bounds both
/// `points` and `bound` (the vertices of the voxel's clipped surface polygons: an ellipsoid is
/// convex, so bounding them bounds all the surface, not just the samples, which a few samples
/// would leave uncovered at the corners).
pub fn fit_ellipsoid_bounding(
    points: &[Vec3],
    bound: &[Vec3],
    min_extent: f32,
) -> Option<Ellipsoid> {
    let mut pts: Vec<Vec3> = points.iter().copied().filter(|p| p.is_finite()).collect();
    if pts.is_empty() {
        pts = bound.iter().copied().filter(|p| p.is_finite()).collect();
    }
    if pts.is_empty() {
        return None;
    }
    let n = pts.len() as f32;
    let mean = pts.iter().copied().sum::<Vec3>() / n;
    let mut cov = Mat3::ZERO;
    for p in &pts {
        let d = *p - mean;
        cov += Mat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    let (_, basis) = symmetric_eigen(cov / n);
    // Coordinates in the principal frame and their extents.
    let local: Vec<Vec3> = pts
        .iter()
        .chain(bound.iter().filter(|p| p.is_finite()))
        .map(|p| basis.transpose() * (*p - mean))
        .collect();
    let lo = local
        .iter()
        .fold(Vec3::splat(f32::INFINITY), |a, p| a.min(*p));
    let hi = local
        .iter()
        .fold(Vec3::splat(f32::NEG_INFINITY), |a, p| a.max(*p));
    let centre = 0.5 * (lo + hi);
    let half = (0.5 * (hi - lo)).max(Vec3::splat(min_extent.max(1e-12)));
    // Bounding sphere of the box-normalised points, centred on the box centre.
    let r = local
        .iter()
        .map(|p| ((*p - centre) / half).length())
        .fold(0.0f32, f32::max)
        .max(1e-6)
        // A hair of margin: the bounded points (a square's corners, say) lie on the surface
        // exactly, where rays through them would graze it and miss by rounding.
        * 1.0005;
    let axes = basis * Mat3::from_diagonal(half * r);
    Some(Ellipsoid {
        center: mean + basis * centre,
        axes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32;

    #[test]
    fn bounds_every_point() {
        let mut rng = Pcg32::new(2, 2);
        // A tilted slab of points (flat voxel) and a blob.
        let rot = Mat3::from_quat(glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, 0.9, -0.4));
        let slab: Vec<Vec3> = (0..500)
            .map(|_| rot * Vec3::new(rng.next_f32(), rng.next_f32() * 0.5, 0.0))
            .collect();
        let e = fit_ellipsoid(&slab, 1e-3).unwrap();
        assert!(slab.iter().all(|p| e.contains(*p, 1e-4)));
        // Thin: far smaller than the bounding sphere of the points.
        let sphere_vol = 4.0 / 3.0 * std::f32::consts::PI * (0.5f32 * 1.25f32.sqrt()).powi(3);
        assert!(
            e.volume() < 0.05 * sphere_vol,
            "{} vs {sphere_vol}",
            e.volume()
        );
        let blob: Vec<Vec3> = (0..500)
            .map(|_| Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()))
            .collect();
        let e = fit_ellipsoid(&blob, 1e-3).unwrap();
        assert!(blob.iter().all(|p| e.contains(*p, 1e-4)));
        assert!(fit_ellipsoid(&[], 1e-3).is_none());
        let one = fit_ellipsoid(&[Vec3::ONE], 1e-3).unwrap();
        assert!(one.contains(Vec3::ONE, 1e-4) && one.axes.determinant().is_finite());
    }
}
