//! The bake: from a scene to the `.agg` file (paper §7.1–§7.2). Levels double in resolution
//! from `min_res` up to `max_res`; each is voxelized with exact per-voxel areas
//! ([`voxelize`]), sampled ([`sampling`]), reduced to per-voxel statistics, ellipsoids and
//! interior-visibility trees ([`level`], [`primitive`], [`visibility`]), and closed by the
//! visibility trees of its boundary faces ([`boundary`], [`boundary_visibility`]).
//! [`bake_to_file`] streams it all into the file, one block of voxels or faces at a time.

pub mod boundary;
pub mod boundary_visibility;
pub mod convert;
pub mod level;
mod pipeline;
pub mod primitive;
pub mod rate;
pub mod sampling;
pub mod visibility;
pub mod voxelize;

pub use pipeline::*;

use crate::absdf::estimate::EstimateSettings;
use level::LevelSettings;

/// Settings of a whole bake (the `aggtool convert` options). Recorded in the file.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BakeSettings {
    /// Finest level resolution (a power of two).
    pub max_res: u32,
    /// Coarsest level resolution (a power of two).
    pub min_res: u32,
    /// Surface samples per voxel at the finest level. A level of resolution r gets
    /// `samples · (max_res / r)²` (the same density of samples per unit area, paper §7.1),
    /// capped at `max_samples`.
    pub samples: u32,
    /// Most surface samples per voxel at any level.
    pub max_samples: u32,
    /// Interior visibility (AIV): sphere-map resolution.
    pub aiv_res: u32,
    /// Interior-visibility rays per surface sample (paper: 16 to 64).
    pub aiv_rays: u32,
    /// The fewest rays an AIV map cell's estimate rests on (the cell pools the rays of the
    /// smallest enclosing block of cells holding that many); 0 chooses it per voxel by
    /// cross-validation over the voxel's surface samples ([`visibility::aiv_map`]), 1 is the
    /// per-cell average of formats up to 1.5 (and of files that do not record it).
    #[serde(default = "crate::format::settings::one")]
    pub aiv_min_rays: u32,
    /// Boundary visibility (ABV): hemisphere-map resolution.
    pub abv_res: u32,
    /// Boundary-visibility rays per direction cell (Eq. 26).
    pub abv_rays: u32,
    /// Levels up to this resolution trace `abv_rays` per direction cell of each boundary face;
    /// a finer level of resolution r traces them per block of (r / abv_full_res)² cells, so
    /// that every level from here on costs about the same number of ABV rays (four times the
    /// faces, a quarter of the rays per face), as the surface samples do (paper §7.1).
    pub abv_full_res: u32,
    /// ABV map cells may also average a window of cells centred on them, where a face's
    /// held-out rays say so, besides the enclosing blocks of cells they always may
    /// ([`boundary_visibility::abv_map`]): less bias where the visibility is smooth, at about
    /// twice the ABV's bytes (a smooth map keeps more wavelet coefficients). On in the `high`
    /// preset; absent in files that predate it (false).
    #[serde(default)]
    pub abv_windows: bool,
    /// Most SGGX lobes per voxel.
    pub ndf_lobes: u32,
    /// Directional-moment grid resolution (Eq. 23).
    pub moment_res: u32,
    /// Wavelet truncation: fraction of coefficients kept at most (paper Table 2).
    pub keep: f32,
    /// Detail energy the kept coefficients must hold (paper Table 2).
    pub energy: f32,
    /// Shrink Monte Carlo noise out of the visibility wavelets before truncation
    /// (`math::haar::shrink`); off reproduces the paper's truncation alone.
    pub denoise: bool,
    /// Store every effect in full even where the asset does not need it (for measuring what
    /// effect detection saves; renders are the same).
    pub keep_all_effects: bool,
    /// Keep the float layout of format 1.0–1.3 (f32 Haar nodes, lobes and moments) instead of
    /// format 1.4's quantized one (`format::quantize`, `math::haar::QNode`), for measuring
    /// what quantization costs; renders differ by the quantization error only.
    pub lossless: bool,
    /// Zstandard level of the block blobs (format 1.5; 0 stores them uncompressed): lossless,
    /// inflated by readers the first time a block is read.
    pub compression: i32,
    /// Rate control ([`rate`]): the whole file's size in MiB (within 3% under it), spent on
    /// the visibility details where they matter most to radiance; 0: none (the per-map
    /// `keep` and `energy` truncate). At most one of `size_mib`, `level_mib` and `error`.
    #[serde(default)]
    pub size_mib: f64,
    /// Rate control: the finest level's size in MiB; coarser levels get the same multiplier.
    /// 0: none.
    #[serde(default)]
    pub level_mib: f64,
    /// Rate control: the largest level error estimate (RMS visibility error weighted by
    /// radiance, [`rate`]); 0: none.
    #[serde(default)]
    pub error: f64,
    /// How many of the finest levels are visibility levels (format 1.7): their voxels keep
    /// the geometry (ellipsoid, SGGX lobes, constant material moments) and their faces the
    /// ABV, and take their interior visibility (AIV and exposure) from the voxel of the finest
    /// shading level that contains them, so that no AIV rays are traced and no AIV trees or
    /// directional moments are stored there. On foliage, seen about a voxel a pixel, what
    /// varies inside a voxel is mostly whether a ray gets through (the ABV and the
    /// primitives), and the maple's RMSE at 64² is unchanged; on solids the finer AIV tells
    /// the sides of a wall apart and a building's RMSE rises by 30%
    /// (`docs/src/studies/2026-12-06-visibility-levels.md`). At least the coarsest level
    /// shades; 0: every level shades itself.
    #[serde(default)]
    pub visibility_levels: u32,
    /// Without a rate target, choose each block's visibility details and directional moments
    /// as the rate control does ([`rate`]: by weighted energy per byte) at the estimated error
    /// that truncating each map to `keep` and `energy` would give
    /// ([`rate::equal_error_block`]): the same error estimate in fewer bytes, streaming
    /// block by block (shards too). On the maple at 64³: 0.79× the bytes, RMSE within 0.2% at
    /// 64² and 256² (`docs/src/studies/2026-12-06-derived-fields.md`). False truncates each
    /// map on its own (the paper's rule, and files before format 1.8).
    #[serde(default = "crate::format::settings::yes")]
    pub block_allocation: bool,
}

impl Default for BakeSettings {
    fn default() -> Self {
        BakeSettings {
            max_res: 256,
            min_res: 4,
            samples: 32,
            max_samples: 1024,
            aiv_res: 32,
            aiv_rays: 32,
            aiv_min_rays: 0,
            abv_res: 64,
            abv_rays: 1,
            abv_full_res: 64,
            abv_windows: false,
            ndf_lobes: 4,
            moment_res: 3,
            keep: 0.15,
            energy: 0.98,
            denoise: true,
            keep_all_effects: false,
            lossless: false,
            compression: crate::format::DEFAULT_COMPRESSION,
            size_mib: 0.0,
            level_mib: 0.0,
            error: 0.0,
            visibility_levels: 0,
            block_allocation: true,
        }
    }
}

/// Named starting points for [`BakeSettings`] (`aggtool convert --preset`); flags given beside
/// a preset override its values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// A quick look: 64³ finest level, an eighth of the samples and of the AIV rays, 16² AIV
    /// and 32² ABV maps, at most two lobes, the coarser truncation of format 1.5's default
    /// (10% of the coefficients, 95% of the detail energy), fast compression.
    Draft,
    /// [`BakeSettings::default`].
    Default,
    /// Twice the surface samples and the AIV rays, two ABV rays per cell, centred ABV windows
    /// ([`BakeSettings::abv_windows`]).
    High,
    /// The paper's ablation control (Table 4 "Maximum"): up to 4 lobes, no truncation or
    /// denoising of the visibility wavelets, no quantization, no compression.
    Max,
}

impl Preset {
    /// Every preset, for help texts and sweeps.
    pub const ALL: [Preset; 4] = [Preset::Draft, Preset::Default, Preset::High, Preset::Max];

    /// The preset's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Draft => "draft",
            Preset::Default => "default",
            Preset::High => "high",
            Preset::Max => "max",
        }
    }

    /// The preset named `name`.
    pub fn from_name(name: &str) -> Option<Preset> {
        Preset::ALL.into_iter().find(|p| p.name() == name)
    }

    /// What the preset is for, in a line (for menus and `aggtool presets`).
    pub fn summary(self) -> &'static str {
        match self {
            Preset::Draft => {
                "a quick look: 64³, an eighth of the samples and rays, coarser truncation"
            }
            Preset::Default => "the defaults: 256³, 32 samples per voxel, 32 AIV rays",
            Preset::High => "twice the samples and AIV rays, two ABV rays per cell, ABV windows",
            Preset::Max => {
                "the paper's control: 4 lobes, no truncation, quantization or compression"
            }
        }
    }

    /// The preset's settings ([`BakeSettings::preset`]).
    pub fn settings(self) -> BakeSettings {
        BakeSettings::preset(self)
    }
}

/// One row of the [`PresetTable`]: a preset's name, its summary and its settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PresetEntry {
    /// The name `--preset` and the bindings take ([`Preset::name`]).
    pub name: &'static str,
    /// What it is for ([`Preset::summary`]).
    pub summary: &'static str,
    /// Its settings, keyed as [`BakeSettings::with_field`] names them.
    pub settings: BakeSettings,
}

/// Every preset with its settings, cheapest first: what `aggtool presets` prints (`--json`:
/// this struct serialised), what the Python module's `aggtool.presets()` returns and what the
/// Blender extension's preset menu is read from, so that no binding keeps a copy.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PresetTable {
    /// The name of the preset used when none is named.
    pub default: &'static str,
    /// The setting names every preset's `settings` has ([`BakeSettings::field_names`]).
    pub fields: Vec<String>,
    /// Every preset, in [`Preset::ALL`]'s order.
    pub presets: Vec<PresetEntry>,
}

impl PresetTable {
    /// The table of [`Preset::ALL`].
    pub fn new() -> PresetTable {
        PresetTable {
            default: Preset::Default.name(),
            fields: BakeSettings::field_names(),
            presets: Preset::ALL
                .iter()
                .map(|&p| PresetEntry {
                    name: p.name(),
                    summary: p.summary(),
                    settings: p.settings(),
                })
                .collect(),
        }
    }
}

impl Default for PresetTable {
    fn default() -> Self {
        PresetTable::new()
    }
}

impl std::fmt::Display for PresetTable {
    /// A setting per row, a preset per column, then each preset's summary.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let values: Vec<serde_json::Map<String, serde_json::Value>> = self
            .presets
            .iter()
            .map(|p| match serde_json::to_value(&p.settings) {
                Ok(serde_json::Value::Object(m)) => m,
                _ => serde_json::Map::new(),
            })
            .collect();
        let width = self.fields.iter().map(|n| n.len()).max().unwrap_or(0);
        write!(f, "{:width$}", "setting")?;
        for p in &self.presets {
            write!(f, "  {:>8}", p.name)?;
        }
        writeln!(f)?;
        for name in &self.fields {
            write!(f, "{name:width$}")?;
            for v in &values {
                // The settings' fractions are f32: shown as f32s (0.95, not 0.949999988).
                let v = match v.get(name) {
                    Some(serde_json::Value::Number(n)) if n.is_f64() => {
                        format!("{}", n.as_f64().unwrap_or(f64::NAN) as f32)
                    }
                    Some(v) => v.to_string(),
                    None => String::new(),
                };
                write!(f, "  {v:>8}")?;
            }
            writeln!(f)?;
        }
        writeln!(f)?;
        for p in &self.presets {
            let mark = if p.name == self.default {
                " (used when none is named)"
            } else {
                ""
            };
            writeln!(f, "{}: {}{mark}", p.name, p.summary)?;
        }
        Ok(())
    }
}

/// A setting's value as the command line writes it: a number, `true`/`false`, or a
/// percentage (`1%` is 0.01); anything else stays a string (of the wrong kind for every
/// setting).
fn read_text(text: &str) -> serde_json::Value {
    use serde_json::Value;
    let text = text.trim();
    match text.strip_suffix('%').map(|p| p.trim().parse::<f64>()) {
        Some(Ok(p)) => serde_json::Number::from_f64(p / 100.0).map_or(Value::Null, Value::Number),
        Some(Err(_)) => Value::String(text.to_string()),
        None => serde_json::from_str(text).unwrap_or_else(|_| Value::String(text.into())),
    }
}

/// A value in a message: strings as given, non-finite numbers (JSON's null) said so.
fn shown(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Null => "(not a finite number)".into(),
        v => v.to_string(),
    }
}

/// Why a setting given by name ([`BakeSettings::with_value`], [`BakeSettings::with_field`])
/// was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SettingError {
    /// No setting has this name.
    #[error("unknown bake setting '{name}'; the settings are: {}", valid.join(", "))]
    Unknown {
        /// The name given.
        name: String,
        /// Every valid name ([`BakeSettings::field_names`]).
        valid: Vec<String>,
    },
    /// The value is of the wrong kind for the setting (a float or a string for a count, a
    /// number for a switch).
    #[error("{name}={value}: expected {expected}")]
    Type {
        /// The setting, as serialised.
        name: String,
        /// The value given.
        value: String,
        /// What the setting takes ("an integer", "true or false", "a number").
        expected: &'static str,
    },
    /// No preset has this name.
    #[error("unknown bake preset '{name}'; the presets are: {}", valid.join(", "))]
    UnknownPreset {
        /// The name given.
        name: String,
        /// Every preset's name ([`Preset::ALL`]).
        valid: Vec<String>,
    },
    /// The value is of the right kind but outside what its type holds (a negative count).
    #[error("{name}={value}: {message}")]
    Invalid {
        /// The setting, as serialised.
        name: String,
        /// The value given.
        value: String,
        /// What is wrong with it.
        message: String,
    },
    /// The settings with the values given are refused by [`BakeSettings::validate`] (a
    /// resolution not a power of two, `min_res` above `max_res`, a fraction above 1).
    #[error("{given}: {message}")]
    Rejected {
        /// The values given, `name=value, ...`.
        given: String,
        /// [`BakeSettings::validate`]'s message, naming the setting by its flag.
        message: String,
    },
}

impl BakeSettings {
    /// The settings of a preset.
    pub fn preset(p: Preset) -> BakeSettings {
        let d = BakeSettings::default();
        match p {
            Preset::Draft => BakeSettings {
                max_res: 64,
                samples: 4,
                aiv_res: 16,
                aiv_rays: 4,
                abv_res: 32,
                abv_full_res: 32,
                ndf_lobes: 2,
                keep: 0.10,
                energy: 0.95,
                compression: 3,
                ..d
            },
            Preset::Default => d,
            Preset::High => BakeSettings {
                samples: 64,
                aiv_rays: 64,
                abv_rays: 2,
                abv_windows: true,
                ..d
            },
            Preset::Max => BakeSettings {
                ndf_lobes: 4,
                aiv_min_rays: 1,
                keep: 1.0,
                energy: 1.0,
                denoise: false,
                lossless: true,
                compression: 0,
                block_allocation: false,
                ..d
            },
        }
    }

    /// Checks the settings, with a message naming the option at fault.
    pub fn validate(&self) -> Result<(), String> {
        let pow2 = |name: &str, v: u32, lo: u32, hi: u32| {
            if v.is_power_of_two() && (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(format!(
                    "{name} must be a power of two from {lo} to {hi}, got {v}"
                ))
            }
        };
        pow2("--max-res", self.max_res, 1, 4096)?;
        pow2("--min-res", self.min_res, 1, self.max_res)?;
        pow2("--aiv-res", self.aiv_res, 2, 256)?;
        pow2("--abv-res", self.abv_res, 2, 256)?;
        pow2("--abv-full-res", self.abv_full_res, 1, 4096)?;
        if self.samples == 0 || self.max_samples == 0 || self.aiv_rays == 0 || self.abv_rays == 0 {
            return Err(
                "--samples, --max-samples, --aiv-rays and --abv-rays must be positive".into(),
            );
        }
        if !(1..=4).contains(&self.ndf_lobes) {
            return Err(format!(
                "--ndf-lobes must be 1 to 4, got {}",
                self.ndf_lobes
            ));
        }
        if !(1..=16).contains(&self.moment_res) {
            return Err(format!(
                "--moment-res must be 1 to 16, got {}",
                self.moment_res
            ));
        }
        if !(0..=22).contains(&self.compression) {
            return Err(format!(
                "--compression-level must be 0 (none) to 22, got {}",
                self.compression
            ));
        }
        if !(self.keep > 0.0 && self.keep <= 1.0) {
            return Err(format!("--keep must be in (0, 1], got {}", self.keep));
        }
        if !(self.energy >= 0.0 && self.energy <= 1.0) {
            return Err(format!("--energy must be in [0, 1], got {}", self.energy));
        }
        let targets = [
            ("--size-mib", self.size_mib),
            ("--level-mib", self.level_mib),
            ("--error", self.error),
        ];
        for (name, v) in targets {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(format!(
                    "{name} must be a positive number (0: none), got {v}"
                ));
            }
        }
        if self.visibility_levels > 16 {
            return Err(format!(
                "--visibility-levels must be 0 to 16, got {}",
                self.visibility_levels
            ));
        }
        let set: Vec<&str> = targets.iter().filter(|t| t.1 > 0.0).map(|t| t.0).collect();
        if set.len() > 1 {
            return Err(format!(
                "{} name the same thing (the bake's rate); give one",
                set.join(" and ")
            ));
        }
        Ok(())
    }

    /// The rate target these settings name ([`rate::RateTarget::of`]).
    pub fn rate_target(&self) -> Option<rate::RateTarget> {
        rate::RateTarget::of(self)
    }

    /// The resolutions of the levels, finest first.
    pub fn resolutions(&self) -> Vec<u32> {
        let mut r = self.max_res;
        let mut out = Vec::new();
        while r >= self.min_res.max(1) {
            out.push(r);
            if r == 1 {
                break;
            }
            r /= 2;
        }
        out
    }

    /// The finest level that shades its own hits ([`Self::visibility_levels`] below the
    /// finest, and at least the coarsest).
    pub fn finest_shading_res(&self) -> u32 {
        (self.max_res >> self.visibility_levels.min(31)).max(self.min_res.min(self.max_res))
    }

    /// The resolution a file records as its `shading_res`: 0 when every level shades itself.
    pub fn shading_res(&self) -> u32 {
        match self.finest_shading_res() {
            r if r >= self.max_res => 0,
            r => r,
        }
    }

    /// Whether the level of resolution `res` is a visibility level
    /// ([`Self::visibility_levels`]).
    pub fn is_visibility_level(&self, res: u32) -> bool {
        res > self.finest_shading_res()
    }

    /// Surface samples per voxel at resolution `res`: `samples` at the finest level, more on
    /// coarser ones (the same density per unit area). A shading level below visibility
    /// levels keeps the samples it has in a full bake: it shades their hits, and with fewer
    /// (as many as a bake of its own resolution takes) the maple at 64² lost 8% of RMSE.
    pub fn samples_at(&self, res: u32) -> u32 {
        let k = (self.max_res as f64 / res as f64).powi(2);
        ((self.samples as f64 * k).round() as u64).clamp(1, self.max_samples as u64) as u32
    }

    /// The side of the block of ABV direction cells that shares `abv_rays` at resolution `res`.
    pub fn abv_stride_at(&self, res: u32) -> u32 {
        (res / self.abv_full_res.max(1)).clamp(1, self.abv_res)
    }

    /// The record of these settings a file keeps.
    pub fn recorded(&self) -> crate::format::RecordedSettings {
        crate::format::RecordedSettings {
            max_res: self.max_res,
            min_res: self.min_res,
            samples: self.samples,
            max_samples: self.max_samples,
            aiv_res: self.aiv_res,
            aiv_rays: self.aiv_rays,
            aiv_min_rays: self.aiv_min_rays,
            abv_res: self.abv_res,
            abv_rays: self.abv_rays,
            abv_full_res: self.abv_full_res,
            abv_windows: self.abv_windows,
            ndf_lobes: self.ndf_lobes,
            moment_res: self.moment_res,
            keep: self.keep,
            energy: self.energy,
            keep_all_effects: self.keep_all_effects,
            denoise: self.denoise,
            aiv_weighting: crate::format::AivWeighting::ProjectedArea,
            lossless: self.lossless,
            compression: self.compression,
            size_mib: self.size_mib,
            level_mib: self.level_mib,
            error: self.error,
            shading_res: self.shading_res(),
            block_allocation: self.block_allocation,
        }
    }

    /// The names [`Self::with_field`] accepts, sorted: the fields as serialised (`ndf_lobes`,
    /// `keep`, ...), which are also `convert --report`'s and `inspect --json`'s keys.
    pub fn field_names() -> Vec<String> {
        let mut names: Vec<String> = match serde_json::to_value(BakeSettings::default()) {
            Ok(serde_json::Value::Object(m)) => m.keys().cloned().collect(),
            _ => Vec::new(),
        };
        names.sort();
        names
    }

    /// These settings with the field `name` (as serialised; dashes are read as underscores,
    /// so `ndf-lobes` is `ndf_lobes`) set to `value`: a number, `true` or `false`, or a
    /// percentage (`1%` is 0.01). The result is [validated](Self::validate). Errors name the
    /// valid fields for an unknown name, and the expected type for a wrong value.
    pub fn with_field(&self, name: &str, value: &str) -> Result<BakeSettings, String> {
        self.with_value(name, &serde_json::Value::String(value.into()))
            .map_err(|e| e.to_string())
    }

    /// These settings with the field `name` (as [`Self::with_field`] names it) set to a typed
    /// value, as the bindings pass them: a boolean for a switch, an integer for a count or a
    /// level, any number for a fraction; a string is read as [`Self::with_field`] reads it.
    /// The result is [validated](Self::validate).
    pub fn with_value(
        &self,
        name: &str,
        value: &serde_json::Value,
    ) -> Result<BakeSettings, SettingError> {
        self.with_values(&[(name.to_string(), value.clone())])
    }

    /// These settings with every `(name, value)` set as [`Self::with_value`] sets one, in
    /// order, then [validated](Self::validate) once, together: so `min_res=128, max_res=256`
    /// over a 64³ preset is valid in either order. The Python module's `convert(preset,
    /// **overrides)` goes through here ([`Self::from_preset`]).
    pub fn with_values(
        &self,
        values: &[(String, serde_json::Value)],
    ) -> Result<BakeSettings, SettingError> {
        let mut s = self.clone();
        for (name, value) in values {
            s = s.assign(name, value)?;
        }
        s.validate().map_err(|message| SettingError::Rejected {
            given: values
                .iter()
                .map(|(n, v)| format!("{}={}", n.trim().replace('-', "_"), shown(v)))
                .collect::<Vec<_>>()
                .join(", "),
            message,
        })?;
        Ok(s)
    }

    /// A preset's settings (by its name, as `--preset` takes it) with `overrides` applied
    /// ([`Self::with_values`]): what a binding's `convert(preset, **overrides)` bakes.
    pub fn from_preset(
        preset: &str,
        overrides: &[(String, serde_json::Value)],
    ) -> Result<BakeSettings, SettingError> {
        let p = Preset::from_name(preset.trim()).ok_or_else(|| SettingError::UnknownPreset {
            name: preset.to_string(),
            valid: Preset::ALL.iter().map(|p| p.name().to_string()).collect(),
        })?;
        p.settings().with_values(overrides)
    }

    /// These settings with one field set, unvalidated: the name known, the value of the
    /// field's kind (a string read as [`Self::with_field`] reads it) and within its type's
    /// range.
    fn assign(&self, name: &str, value: &serde_json::Value) -> Result<BakeSettings, SettingError> {
        use serde_json::Value;
        let key = name.trim().replace('-', "_");
        let value = match value {
            Value::String(text) => read_text(text),
            v => v.clone(),
        };
        let invalid = |message: String| SettingError::Invalid {
            name: key.clone(),
            value: shown(&value),
            message,
        };
        let mut v = serde_json::to_value(self).map_err(|e| invalid(e.to_string()))?;
        let Some(field) = v.as_object_mut().and_then(|m| m.get_mut(&key)) else {
            return Err(SettingError::Unknown {
                name: name.to_string(),
                valid: Self::field_names(),
            });
        };
        // The kind the field takes is the kind of its current value.
        let expected = match &*field {
            Value::Bool(_) => "true or false",
            Value::Number(n) if n.is_f64() => "a number",
            _ => "an integer",
        };
        let kind_ok = match (&*field, &value) {
            (Value::Bool(_), Value::Bool(_)) => true,
            (Value::Number(n), Value::Number(_)) if n.is_f64() => true,
            (Value::Number(_), Value::Number(m)) => m.is_i64() || m.is_u64(),
            _ => false,
        };
        if !kind_ok {
            return Err(SettingError::Type {
                name: key,
                value: shown(&value),
                expected,
            });
        }
        *field = value.clone();
        serde_json::from_value(v).map_err(|e| invalid(e.to_string()))
    }

    /// The settings a file recorded, as a bake names them (the inverse of [`Self::recorded`];
    /// the AIV weighting, which the format version fixes, is the record's alone).
    pub fn from_recorded(r: &crate::format::RecordedSettings) -> BakeSettings {
        BakeSettings {
            max_res: r.max_res,
            min_res: r.min_res,
            samples: r.samples,
            max_samples: r.max_samples,
            aiv_res: r.aiv_res,
            aiv_rays: r.aiv_rays,
            aiv_min_rays: r.aiv_min_rays,
            abv_res: r.abv_res,
            abv_rays: r.abv_rays,
            abv_full_res: r.abv_full_res,
            abv_windows: r.abv_windows,
            ndf_lobes: r.ndf_lobes,
            moment_res: r.moment_res,
            keep: r.keep,
            energy: r.energy,
            denoise: r.denoise,
            keep_all_effects: r.keep_all_effects,
            lossless: r.lossless,
            compression: r.compression,
            size_mib: r.size_mib,
            level_mib: r.level_mib,
            error: r.error,
            visibility_levels: match r.shading_res {
                0 => 0,
                s => r.max_res.checked_div(s).map_or(0, |k| k.max(1).ilog2()),
            },
            block_allocation: r.block_allocation,
        }
    }

    /// Whether the rate control chooses the details (a target, or the block allocation)
    /// rather than each map's own truncation.
    pub fn allocates(&self) -> bool {
        self.rate_target().is_some() || self.allocates_per_block()
    }

    /// Whether each block is allocated on its own at the per-map truncation's error
    /// ([`rate::equal_error_block`]): the block allocation without a target (a target
    /// allocates over the whole file instead).
    pub fn allocates_per_block(&self) -> bool {
        self.block_allocation && self.rate_target().is_none()
    }

    /// The settings of one level.
    pub fn level(&self, res: u32) -> LevelSettings {
        LevelSettings {
            shade: !self.is_visibility_level(res),
            samples_per_voxel: self.samples_at(res),
            aiv_rays: self.aiv_rays,
            aiv_min_rays: self.aiv_min_rays,
            aiv_res: self.aiv_res,
            abv_res: self.abv_res,
            abv_rays: self.abv_rays,
            abv_stride: self.abv_stride_at(res),
            abv_windows: self.abv_windows,
            // With a rate target or the block allocation every detail that survives the
            // shrinkage is a candidate, and the rate control truncates ([`rate`]).
            keep: if self.allocates() { 1.0 } else { self.keep },
            energy: if self.allocates() { 1.0 } else { self.energy },
            denoise: self.denoise,
            estimate: EstimateSettings {
                max_lobes: self.ndf_lobes as usize,
                moment_res: self.moment_res,
                detect_constant: !self.keep_all_effects,
                ..Default::default()
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every preset is valid and round-trips its name; `default` is `Default`; `max` is the
    /// paper's control (4 lobes, nothing truncated, quantized or compressed); `draft` costs
    /// less than `default` in every ray and sample count, `high` more.
    #[test]
    fn presets() {
        for p in Preset::ALL {
            BakeSettings::preset(p).validate().unwrap();
            assert_eq!(Preset::from_name(p.name()), Some(p));
        }
        assert_eq!(Preset::from_name("fast"), None);
        let (d, draft, high, max) = (
            BakeSettings::preset(Preset::Default),
            BakeSettings::preset(Preset::Draft),
            BakeSettings::preset(Preset::High),
            BakeSettings::preset(Preset::Max),
        );
        assert_eq!(d, BakeSettings::default());
        assert_eq!((max.ndf_lobes, max.keep, max.energy), (4, 1.0, 1.0));
        assert!(max.lossless && max.compression == 0 && !max.denoise);
        for (lo, hi) in [(&draft, &d), (&d, &high)] {
            assert!(lo.samples < hi.samples && lo.aiv_rays <= hi.aiv_rays);
            assert!(lo.aiv_res <= hi.aiv_res && lo.abv_res <= hi.abv_res);
            assert!(lo.abv_rays <= hi.abv_rays && lo.keep <= hi.keep);
        }
    }

    /// `with_field` sets one field by its serialised name (dashes or underscores, numbers,
    /// booleans, percentages), validates, and refuses unknown names with the list of valid
    /// ones and wrong types with the field's name.
    #[test]
    fn with_field_sets_one_field() {
        let d = BakeSettings::default();
        let s = d.with_field("ndf-lobes", "1").unwrap();
        assert_eq!(
            s,
            BakeSettings {
                ndf_lobes: 1,
                ..d.clone()
            }
        );
        assert_eq!(d.with_field("keep", "1%").unwrap().keep, 0.01);
        assert!(d.with_field("lossless", "true").unwrap().lossless);
        let e = d.with_field("lobes", "2").unwrap_err();
        assert!(
            e.contains("lobes") && e.contains("ndf_lobes") && e.contains("keep"),
            "{e}"
        );
        assert!(d
            .with_field("ndf_lobes", "1.5")
            .unwrap_err()
            .contains("ndf_lobes"));
        assert!(d
            .with_field("ndf_lobes", "9")
            .unwrap_err()
            .contains("--ndf-lobes"));
        assert!(d.with_field("keep", "many").is_err());
        assert_eq!(BakeSettings::field_names().len(), 24);
        assert!(
            !d.with_field("block_allocation", "false")
                .unwrap()
                .block_allocation
        );
    }

    /// `with_value` takes typed values as the bindings pass them: integers for counts (a
    /// float or a string that is not one is of the wrong kind), any number for fractions,
    /// booleans for switches; out-of-range values are invalid, not of the wrong kind; strings
    /// are read as `with_field` reads them. Unknown names list the valid ones.
    #[test]
    fn with_value_classifies_refusals() {
        use serde_json::json;
        let d = BakeSettings::default();
        assert_eq!(d.with_value("max_res", &json!(64)).unwrap().max_res, 64);
        assert_eq!(d.with_value("keep", &json!(1)).unwrap().keep, 1.0);
        assert_eq!(d.with_value("keep", &json!("1%")).unwrap().keep, 0.01);
        assert!(!d.with_value("denoise", &json!(false)).unwrap().denoise);
        assert_eq!(
            d.with_value("compression-level", &json!(0)).unwrap_err(),
            SettingError::Unknown {
                name: "compression-level".into(),
                valid: BakeSettings::field_names()
            }
        );
        for (name, v) in [
            ("max_res", json!(64.0)),
            ("max_res", json!("big")),
            ("denoise", json!(1)),
            ("keep", json!(true)),
        ] {
            assert!(
                matches!(d.with_value(name, &v), Err(SettingError::Type { .. })),
                "{name}={v}"
            );
        }
        let e = d.with_value("max_res", &json!(-64)).unwrap_err();
        assert!(matches!(e, SettingError::Invalid { .. }), "{e:?}");
        assert!(e.to_string().starts_with("max_res=-64: "), "{e}");
        for (name, v) in [
            ("max_res", json!(48)),
            ("ndf_lobes", json!(5)),
            ("keep", json!(0)),
        ] {
            let e = d.with_value(name, &v).unwrap_err();
            assert!(
                matches!(e, SettingError::Rejected { .. }),
                "{name}={v}: {e:?}"
            );
            assert!(e.to_string().starts_with(&format!("{name}={v}: ")), "{e}");
        }
        // Validated together: a finer coarsest level with a finer finest level, in any order.
        let min = ("min_res".to_string(), json!(128));
        let max = ("max_res".to_string(), json!(256));
        let draft = BakeSettings::preset(Preset::Draft);
        for pair in [[min.clone(), max.clone()], [max, min]] {
            assert_eq!(draft.with_values(&pair).unwrap().min_res, 128);
        }
    }

    /// The preset table has every preset in order with its settings and every field; a preset
    /// name is parsed or refused with the list of names.
    #[test]
    fn preset_table() {
        let t = PresetTable::new();
        let names: Vec<&str> = t.presets.iter().map(|p| p.name).collect();
        assert_eq!(names, ["draft", "default", "high", "max"]);
        assert_eq!(t.default, "default");
        assert_eq!(t.fields, BakeSettings::field_names());
        for (p, e) in Preset::ALL.iter().zip(&t.presets) {
            assert_eq!(e.settings, BakeSettings::preset(*p));
        }
        let text = t.to_string();
        assert!(
            text.contains("0.95") && text.contains("compression"),
            "{text}"
        );
        let e = BakeSettings::from_preset("fast", &[])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("'fast'") && e.contains("draft, default, high, max"),
            "{e}"
        );
        let s = BakeSettings::from_preset(
            "draft",
            &[
                ("max_res".into(), serde_json::json!(16)),
                ("aiv_res".into(), serde_json::json!(8)),
            ],
        )
        .unwrap();
        assert_eq!((s.max_res, s.aiv_res, s.samples), (16, 8, 4));
    }

    /// Every preset survives the trip through the file's record unchanged.
    #[test]
    fn recorded_round_trip() {
        for p in Preset::ALL {
            let s = BakeSettings::preset(p);
            assert_eq!(
                BakeSettings::from_recorded(&s.recorded()),
                s,
                "{}",
                p.name()
            );
        }
    }

    /// A ray per ABV cell up to --abv-full-res, then blocks of (res / full)² cells per ray
    /// (never larger than the map), so every level from there on traces about as many.
    #[test]
    fn abv_budget_per_level() {
        let s = BakeSettings {
            max_res: 1024,
            abv_full_res: 64,
            abv_res: 64,
            ..Default::default()
        };
        let strides: Vec<(u32, u32)> = s
            .resolutions()
            .into_iter()
            .map(|r| (r, s.level(r).abv_stride))
            .collect();
        assert_eq!(
            strides,
            [
                (1024, 16),
                (512, 8),
                (256, 4),
                (128, 2),
                (64, 1),
                (32, 1),
                (16, 1),
                (8, 1),
                (4, 1)
            ]
        );
        let tiny_map = BakeSettings {
            abv_res: 8,
            ..s.clone()
        };
        assert_eq!(tiny_map.abv_stride_at(4096), 8);
        let paper = BakeSettings {
            abv_full_res: 1024,
            ..s.clone()
        };
        assert!(paper
            .resolutions()
            .iter()
            .all(|&r| paper.abv_stride_at(r) == 1));
        assert!(BakeSettings {
            abv_full_res: 48,
            ..s
        }
        .validate()
        .is_err());
    }
}
