//! The bake settings a file records (`BakeSettings` in the schema), decoded: what a reader
//! needs to know about how a file was made (map resolutions, truncation, the AIV weighting).
//! The bake converts its own settings into this record; readers never see the generated
//! FlatBuffers table.

use serde::{Deserialize, Serialize};

use super::fb;

/// What the AIV (Eq. 25) averages visibility over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum AivWeighting {
    /// Surface area, as Eq. 25 is written (files of format 1.0 and 1.1).
    #[default]
    Area,
    /// Projected area |n·ω| dA towards the direction (format 1.2 on).
    ProjectedArea,
}

/// The settings a bake recorded in its file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedSettings {
    /// Finest and coarsest level resolution.
    pub max_res: u32,
    /// Coarsest level resolution.
    pub min_res: u32,
    /// Surface samples per voxel at the finest level.
    pub samples: u32,
    /// Cap on the samples per voxel of coarser levels.
    pub max_samples: u32,
    /// Interior-visibility map resolution.
    pub aiv_res: u32,
    /// Interior-visibility rays per surface sample.
    pub aiv_rays: u32,
    /// Fewest rays an AIV cell's estimate rests on; 0: chosen per voxel by cross-validation.
    /// 1 in files that do not record it (the per-cell average they were baked with).
    #[serde(default = "one")]
    pub aiv_min_rays: u32,
    /// Boundary-visibility map resolution.
    pub abv_res: u32,
    /// Boundary-visibility rays per direction cell (or per block of cells above
    /// `abv_full_res`).
    pub abv_rays: u32,
    /// Levels finer than this share ABV rays among blocks of cells (0: none do).
    pub abv_full_res: u32,
    /// ABV cells could average windows of cells centred on them besides enclosing blocks;
    /// false in files that do not record it.
    #[serde(default)]
    pub abv_windows: bool,
    /// Most SGGX lobes per voxel.
    pub ndf_lobes: u32,
    /// Directional-moment grid resolution.
    pub moment_res: u32,
    /// Fraction of wavelet coefficients kept at most.
    pub keep: f32,
    /// Detail energy kept by the truncation.
    pub energy: f32,
    /// Every effect stored in full.
    pub keep_all_effects: bool,
    /// Monte Carlo noise shrunk out of the visibility wavelets.
    pub denoise: bool,
    /// What the AIV averages over.
    pub aiv_weighting: AivWeighting,
    /// The 1.0–1.3 float layout was kept (`--lossless`, format 1.4); false in older files,
    /// which are float whatever it says.
    #[serde(default)]
    pub lossless: bool,
    /// The Zstandard level of the blocks (format 1.5); 0 in older files: none.
    #[serde(default)]
    pub compression: i32,
    /// The rate control's file budget in MiB (0, also in files that do not record it: none).
    #[serde(default)]
    pub size_mib: f64,
    /// The rate control's finest-level budget in MiB (0: none).
    #[serde(default)]
    pub level_mib: f64,
    /// The rate control's error bound (0: none).
    #[serde(default)]
    pub error: f64,
    /// Levels finer than this are visibility levels, shaded by the level of this resolution
    /// (format 1.7); 0, also in older files: every level shades itself.
    #[serde(default)]
    pub shading_res: u32,
    /// Without a rate target, each block's details and moments were allocated at the
    /// per-map truncation's error (format 1.8); false, also in older files: each map was
    /// truncated on its own.
    #[serde(default)]
    pub block_allocation: bool,
}

impl RecordedSettings {
    /// Decodes the schema's table.
    pub fn from_fb(s: &fb::BakeSettings) -> RecordedSettings {
        RecordedSettings {
            max_res: s.max_res(),
            min_res: s.min_res(),
            samples: s.samples(),
            max_samples: s.max_samples(),
            aiv_res: s.aiv_res(),
            aiv_rays: s.aiv_rays(),
            aiv_min_rays: s.aiv_min_rays(),
            abv_res: s.abv_res(),
            abv_rays: s.abv_rays(),
            abv_full_res: s.abv_full_res(),
            abv_windows: s.abv_windows(),
            ndf_lobes: s.ndf_lobes(),
            moment_res: s.moment_res(),
            keep: s.keep(),
            energy: s.energy(),
            keep_all_effects: s.keep_all_effects(),
            denoise: s.denoise(),
            aiv_weighting: if s.aiv_weighting() == fb::AivWeighting::ProjectedArea {
                AivWeighting::ProjectedArea
            } else {
                AivWeighting::Area
            },
            lossless: s.lossless(),
            compression: s.compression(),
            size_mib: s.size_mib(),
            level_mib: s.level_mib(),
            error: s.error(),
            shading_res: s.shading_res(),
            block_allocation: s.block_allocation(),
        }
    }

    /// The schema table's arguments.
    pub fn to_fb_args(&self) -> fb::BakeSettingsArgs {
        fb::BakeSettingsArgs {
            max_res: self.max_res,
            samples: self.samples,
            max_samples: self.max_samples,
            aiv_res: self.aiv_res,
            aiv_rays: self.aiv_rays,
            aiv_min_rays: self.aiv_min_rays,
            abv_res: self.abv_res,
            abv_rays: self.abv_rays,
            ndf_lobes: self.ndf_lobes,
            moment_res: self.moment_res,
            keep: self.keep,
            energy: self.energy,
            keep_all_effects: self.keep_all_effects,
            min_res: self.min_res,
            denoise: self.denoise,
            aiv_weighting: match self.aiv_weighting {
                AivWeighting::Area => fb::AivWeighting::Area,
                AivWeighting::ProjectedArea => fb::AivWeighting::ProjectedArea,
            },
            abv_full_res: self.abv_full_res,
            lossless: self.lossless,
            compression: self.compression,
            abv_windows: self.abv_windows,
            size_mib: self.size_mib,
            level_mib: self.level_mib,
            error: self.error,
            shading_res: self.shading_res,
            block_allocation: self.block_allocation,
        }
    }
}

/// The serde default of `aiv_min_rays` in records and settings that predate it (also
/// `bake::BakeSettings`'s).
pub(crate) fn one() -> u32 {
    1
}

/// The serde default of `bake::BakeSettings::block_allocation` in settings that do not name
/// it (the bake's default).
pub(crate) fn yes() -> bool {
    true
}
