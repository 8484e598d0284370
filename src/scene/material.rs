//! Materials in the paper's model (Eq. 11, a simplified Disney BRDF) extended with the F90 weight
//! of KHR_materials_specular.
//!
//! The parameters β = (α, β^c, β^m, β^s) are roughness, base colour, metallic and specular
//! intensity; [`SurfaceParams::f90`] is the dielectric Fresnel weight at grazing angles, which is
//! 1 in the paper and `specularFactor` under KHR_materials_specular, so that `specularFactor = 0`
//! is a purely Lambertian material.

use glam::{Mat3, Vec2, Vec3, Vec4};

use super::texture::Texture;
use crate::math::microfacet::clamp_alpha;

/// How the base colour's alpha is used.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlphaMode {
    /// The surface exists everywhere (alpha ignored).
    Opaque,
    /// Cut-out: the surface exists where alpha ≥ cutoff (glTF MASK; BLEND is imported as MASK
    /// at 0.5 with a warning).
    Mask(f32),
}

/// A 2D affine texture-coordinate transform (KHR_texture_transform: T · R · S).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTransform(pub Mat3);

impl Default for UvTransform {
    fn default() -> Self {
        UvTransform(Mat3::IDENTITY)
    }
}

impl UvTransform {
    /// From KHR_texture_transform's offset, rotation (radians) and scale.
    pub fn from_offset_rotation_scale(offset: Vec2, rotation: f32, scale: Vec2) -> Self {
        let t = Mat3::from_cols(Vec3::X, Vec3::Y, Vec3::new(offset.x, offset.y, 1.0));
        let (s, c) = rotation.sin_cos();
        // Column-major: the spec's row-major [c s 0; -s c 0; 0 0 1].
        let r = Mat3::from_cols(Vec3::new(c, -s, 0.0), Vec3::new(s, c, 0.0), Vec3::Z);
        let sc = Mat3::from_diagonal(Vec3::new(scale.x, scale.y, 1.0));
        UvTransform(t * r * sc)
    }

    /// The transformed texture coordinates of `uv`.
    #[inline]
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        self.0.transform_point2(uv)
    }
}

/// A texture used by a material slot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureRef {
    /// Index into [`crate::scene::Scene::textures`].
    pub texture: u32,
    /// The transform applied to the coordinates before the lookup.
    pub transform: UvTransform,
}

/// Material parameters as stored (factors and textures).
#[derive(Clone, Debug)]
pub struct Material {
    /// The material's name in the asset, for messages.
    pub name: String,
    /// Linear RGB base colour and alpha (factor; multiplied by the texture).
    pub base_color: Vec4,
    /// Base colour texture (sRGB decoded to linear), multiplied by `base_color`.
    pub base_color_texture: Option<TextureRef>,
    /// Metallic factor β^m (Eq. 11).
    pub metallic: f32,
    /// glTF perceptual roughness; GGX α is its square.
    pub perceptual_roughness: f32,
    /// Green channel roughness, blue channel metallic (glTF convention), multiplied by the factors.
    pub metallic_roughness_texture: Option<TextureRef>,
    /// KHR_materials_specular `specularFactor` (1 when absent).
    pub specular_factor: f32,
    /// Its alpha channel multiplies `specular_factor`.
    pub specular_texture: Option<TextureRef>,
    /// How alpha cuts the surface out.
    pub alpha_mode: AlphaMode,
}

impl Default for Material {
    /// glTF's default material: white, metallic 1, roughness 1.
    fn default() -> Self {
        Material {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            metallic: 1.0,
            perceptual_roughness: 1.0,
            metallic_roughness_texture: None,
            specular_factor: 1.0,
            specular_texture: None,
            alpha_mode: AlphaMode::Opaque,
        }
    }
}

/// Evaluated parameters of Eq. 11 at one surface point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceParams {
    /// β^c, linear RGB in [0, 1].
    pub base_color: Vec3,
    /// β^m in [0, 1].
    pub metallic: f32,
    /// GGX α, clamped to [`crate::math::microfacet::ALPHA_MIN`, 1].
    pub alpha: f32,
    /// β^s: dielectric normal-incidence reflectance, 0.04 · specularFactor.
    pub specular: f32,
    /// Dielectric grazing reflectance F90 = specularFactor (1 in the paper).
    pub f90: f32,
}

impl SurfaceParams {
    /// A Lambertian material of the given albedo (specular 0, F90 0).
    pub fn lambertian(albedo: Vec3) -> Self {
        SurfaceParams {
            base_color: albedo,
            metallic: 0.0,
            alpha: 1.0,
            specular: 0.0,
            f90: 0.0,
        }
    }
}

#[inline]
fn fetch(textures: &[Texture], r: &Option<TextureRef>, uv: Vec2) -> Option<Vec4> {
    r.as_ref().and_then(|r| {
        textures
            .get(r.texture as usize)
            .map(|t| t.sample(r.transform.apply(uv)))
    })
}

#[inline]
fn unit(x: f32) -> f32 {
    if x.is_finite() {
        x.clamp(0.0, 1.0)
    } else {
        0.0
    }
}

impl Material {
    /// Evaluates the parameters at texture coordinate `uv`.
    pub fn eval(&self, textures: &[Texture], uv: Vec2) -> SurfaceParams {
        let mut base = self.base_color;
        if let Some(t) = fetch(textures, &self.base_color_texture, uv) {
            base *= t;
        }
        let mut metallic = self.metallic;
        let mut rough = self.perceptual_roughness;
        if let Some(t) = fetch(textures, &self.metallic_roughness_texture, uv) {
            rough *= t.y;
            metallic *= t.z;
        }
        let mut spec = self.specular_factor;
        if let Some(t) = fetch(textures, &self.specular_texture, uv) {
            spec *= t.w;
        }
        let spec = unit(spec);
        let rough = unit(rough);
        SurfaceParams {
            base_color: Vec3::new(unit(base.x), unit(base.y), unit(base.z)),
            metallic: unit(metallic),
            alpha: clamp_alpha(rough * rough),
            specular: 0.04 * spec,
            f90: spec,
        }
    }

    /// Whether the surface exists at `uv` (alpha cut-outs); always true for opaque materials.
    #[inline]
    pub fn is_opaque_at(&self, textures: &[Texture], uv: Vec2) -> bool {
        match self.alpha_mode {
            AlphaMode::Opaque => true,
            AlphaMode::Mask(cutoff) => {
                let mut a = self.base_color.w;
                if let Some(t) = fetch(textures, &self.base_color_texture, uv) {
                    a *= t.w;
                }
                a >= cutoff
            }
        }
    }

    /// Whether any point of the surface can be cut out.
    pub fn has_cutout(&self) -> bool {
        matches!(self.alpha_mode, AlphaMode::Mask(_))
    }

    pub(crate) fn offset_textures(&mut self, by: u32) {
        for r in [
            &mut self.base_color_texture,
            &mut self.metallic_roughness_texture,
            &mut self.specular_texture,
        ]
        .into_iter()
        .flatten()
        {
            r.texture += by;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_transform_matches_spec() {
        // Scale then rotate 90° then offset: (1,0) -> scale (2,0) -> rotate by the spec's matrix
        // [c s; -s c] with θ = 90°: (0,-2) -> offset (0.5,0.5): (0.5,-1.5).
        let t = UvTransform::from_offset_rotation_scale(
            Vec2::new(0.5, 0.5),
            std::f32::consts::FRAC_PI_2,
            Vec2::new(2.0, 2.0),
        );
        let p = t.apply(Vec2::new(1.0, 0.0));
        assert!((p - Vec2::new(0.5, -1.5)).length() < 1e-5, "{p}");
    }

    #[test]
    fn specular_factor_zero_is_lambertian() {
        let m = Material {
            specular_factor: 0.0,
            metallic: 0.0,
            ..Material::default()
        };
        let p = m.eval(&[], Vec2::ZERO);
        assert_eq!((p.specular, p.f90, p.metallic), (0.0, 0.0, 0.0));
        let d = Material::default().eval(&[], Vec2::ZERO);
        assert!((d.specular - 0.04).abs() < 1e-7 && d.f90 == 1.0 && d.alpha == 1.0);
    }
}
