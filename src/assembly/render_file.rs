//! `aggtool render`: an `.agg` aggregate or an assembly manifest rendered with the LoD runtime
//! (cone tracing, Eq. 30) to EXR and PNG, with the report the command line prints.

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::Serialize;

use super::{Assembly, Representation};
use crate::film::ImageStats;
use crate::render::{ImageFiles, View, ViewRequest};
use crate::report::{mib, usage};
use crate::runtime::{BlockCache, CacheStats, LodScene, PrimitiveKind, TraceSettings};
use crate::util::Progress;

/// `aggtool render MANIFEST`'s default for [`RenderRequest::mesh_below`]: assets of at most
/// this many triangles are drawn from their meshes. Above the 11,799 of the largest piece of
/// the city kits, whose aggregates cost 2.6–3.0× the reference's time for no less error, and
/// below the 20,000 of `aggtool gen forest`'s trees, whose aggregates seen from above give
/// 0.65× the error of the reference at the same spp, less than the reference's at equal time
/// (the book's page of 2026-12-07, "Small meshes drawn as meshes").
pub const DEFAULT_MESH_BELOW: u64 = 16_384;

/// What `render` does besides the view.
#[derive(Clone, Debug)]
pub struct RenderRequest {
    /// The view: a file or the scene framed.
    pub view: ViewRequest,
    /// The output (EXR, or PNG with the EXR beside it; see [`ImageFiles`]).
    pub output: PathBuf,
    /// Exposure of the PNG in stops.
    pub exposure: f32,
    /// The runtime's settings; `trace.level` is set from [`RenderRequest::level`].
    pub trace: TraceSettings,
    /// Force the level of this resolution (as `inspect` names levels) instead of choosing by
    /// the pixel footprint.
    pub level: Option<u32>,
    /// Assemblies: draw an instance seen finer than its aggregate's finest level from its mesh.
    pub meshes: bool,
    /// Assemblies, with `meshes`: draw every asset of at most this many triangles from its
    /// mesh at every distance ([`Assembly::draw_small_meshes`]); 0 for none.
    pub mesh_below: u64,
    /// Assemblies: also write a PNG colouring each pixel by what its first hit was drawn with.
    pub level_map: Option<PathBuf>,
    /// Memory budget of the block cache in MiB (default: a quarter of the machine's memory).
    pub cache_mib: Option<u64>,
    /// The process ends after this call (the command line): the scene's prepared blocks and
    /// ABSDFs are left to the operating system instead of being freed one by one, as
    /// clang's `-disable-free` leaves its ASTs. Freeing a prepared maple of 128³ voxels took
    /// 3% of a 256² render, on one thread after the image was written. Default false: a
    /// library caller keeps its memory.
    pub exiting: bool,
}

impl Default for RenderRequest {
    fn default() -> Self {
        RenderRequest {
            view: ViewRequest::default(),
            output: PathBuf::from("render.exr"),
            exposure: 0.0,
            trace: TraceSettings::default(),
            level: None,
            meshes: true,
            mesh_below: DEFAULT_MESH_BELOW,
            level_map: None,
            cache_mib: None,
            exiting: false,
        }
    }
}

/// One asset of a [`RenderReport`] (an aggregate alone is one asset without an id).
#[derive(Clone, Debug, Serialize)]
pub struct AssetRender {
    /// The asset's id (empty for an aggregate rendered alone).
    pub id: String,
    /// The resolutions of the levels the render used, finest first.
    pub levels_used: Vec<u32>,
    /// Triangles of its mesh, when the mesh was loaded (hybrid assemblies).
    pub mesh_triangles: Option<usize>,
    /// Whether it was drawn from its mesh at every distance (a small mesh,
    /// [`RenderRequest::mesh_below`]).
    pub mesh_only: bool,
}

/// The level map of an assembly render.
#[derive(Clone, Debug, Serialize)]
pub struct LevelMapReport {
    /// The PNG written.
    pub path: String,
    /// Its legend: MESH, each resolution and SKY with its share of pixels.
    pub legend: Vec<String>,
}

/// What `aggtool render` reports.
#[derive(Clone, Debug, Serialize)]
pub struct RenderReport {
    /// The aggregate or manifest.
    pub input: String,
    /// What it holds ("3 levels, 1000 bytes" or "2 assets, 40 instances").
    pub holds: String,
    /// Milliseconds to open it.
    pub open_ms: f64,
    /// Whether it is an assembly.
    pub assembly: bool,
    /// The render's figures.
    pub stats: ImageStats,
    /// Cones per pixel.
    pub spp: u32,
    /// Light samples per shaded voxel.
    pub nee: u32,
    /// Per asset.
    pub assets: Vec<AssetRender>,
    /// The block cache.
    pub cache: CacheStats,
    /// Bytes of the level skeletons.
    pub skeleton_bytes: u64,
    /// Peak resident memory, as a line, where the platform tells it.
    pub peak_memory: Option<String>,
    /// The level map, if asked for.
    pub level_map: Option<LevelMapReport>,
    /// The files written.
    pub output: ImageFiles,
}

/// The level index of resolution `res` among `resolutions` (finest first), or an error listing
/// those there are.
pub fn level_of_resolution(what: &str, resolutions: &[u32], res: u32) -> Result<usize> {
    resolutions.iter().position(|&r| r == res).ok_or_else(|| {
        let list: Vec<String> = resolutions.iter().map(|r| r.to_string()).collect();
        usage(format!(
            "--level {res}: {what} has no level of resolution {res}; its levels are {} (as \
             `aggtool inspect` lists them)",
            list.join(", ")
        ))
    })
}

/// Renders the aggregate or manifest `path` as `request` says and writes the images.
pub fn render_file(
    path: &Path,
    request: &RenderRequest,
    progress: Progress,
) -> Result<RenderReport> {
    let manifest = super::is_manifest(path);
    if !manifest && (!request.meshes || request.level_map.is_some()) {
        bail!(usage(
            "--no-mesh and --level-map are for assembly manifests (.json)"
        ));
    }
    if manifest && request.trace.primitive == PrimitiveKind::Volume {
        bail!(usage("--volume is not supported for assemblies"));
    }
    if let Some(m) = request.cache_mib {
        BlockCache::global().set_budget(m.saturating_mul(1 << 20));
    }
    let read = || format!("cannot read {}", path.display());
    // The view first (a missing view file is said before the aggregate is read); framing
    // opens the file for its bounds.
    let view = request.view.resolve(|| {
        let opened = super::Opened::open(path).with_context(read)?;
        let (lo, hi) = opened
            .bounds()
            .ok_or_else(|| anyhow::anyhow!("{}: nothing to frame", path.display()))?;
        Ok((0.5 * (lo + hi), (0.5 * (hi - lo).length()).max(1e-6)))
    })?;
    let t0 = Instant::now();
    if manifest {
        let mut asm = Assembly::open(path).with_context(read)?;
        let open_ms = t0.elapsed().as_secs_f64() * 1e3;
        if request.meshes {
            asm.set_representation(Representation::Hybrid);
            if request.mesh_below > 0 {
                asm.draw_small_meshes(request.mesh_below);
            }
        }
        let report = render_assembly(path, &asm, &view, open_ms, request, progress);
        if request.exiting {
            std::mem::forget(asm);
        }
        report
    } else {
        let scene = LodScene::open(path).with_context(read)?;
        let open_ms = t0.elapsed().as_secs_f64() * 1e3;
        let report = render_aggregate(path, &scene, &view, open_ms, request, progress);
        if request.exiting {
            std::mem::forget(scene);
        }
        report
    }
}

fn render_aggregate(
    path: &Path,
    scene: &LodScene,
    view: &View,
    open_ms: f64,
    request: &RenderRequest,
    progress: Progress,
) -> Result<RenderReport> {
    let resolutions: Vec<u32> = (0..scene.level_count())
        .map(|l| scene.grid(l).res)
        .collect();
    let mut settings = request.trace;
    settings.level = match request.level {
        Some(r) => Some(level_of_resolution(
            &path.display().to_string(),
            &resolutions,
            r,
        )?),
        None => None,
    };
    let lights = view.lights()?;
    let (img, stats) = crate::runtime::render(
        scene,
        &view.camera(),
        &lights,
        view.spp,
        view.seed,
        &settings,
        progress,
    );
    if let Some(e) = scene.first_error() {
        bail!("{}: {e}", path.display());
    }
    let output = ImageFiles::for_output(&request.output);
    output.write(&img, request.exposure)?;
    Ok(RenderReport {
        input: path.display().to_string(),
        holds: format!(
            "{} levels, {} bytes",
            scene.level_count(),
            scene.aggregate().header().file_size
        ),
        open_ms,
        assembly: false,
        stats,
        spp: view.spp,
        nee: settings.nee,
        assets: vec![AssetRender {
            id: String::new(),
            levels_used: scene.resolutions_used(),
            mesh_triangles: None,
            mesh_only: false,
        }],
        cache: BlockCache::global().stats(),
        skeleton_bytes: scene.skeleton_bytes() as u64,
        peak_memory: crate::util::process::peak_rss_line(),
        level_map: None,
        output,
    })
}

fn render_assembly(
    path: &Path,
    asm: &Assembly,
    view: &View,
    open_ms: f64,
    request: &RenderRequest,
    progress: Progress,
) -> Result<RenderReport> {
    let m = asm.manifest();
    let mut settings = request.trace;
    if let Some(r) = request.level {
        // The runtime forces one level index: every asset must hold the resolution there.
        let mut at = None;
        for (a, asset) in m.assets.iter().enumerate() {
            let s = asm.scene(a);
            let res: Vec<u32> = (0..s.level_count()).map(|l| s.grid(l).res).collect();
            let l = level_of_resolution(&format!("asset '{}'", asset.id), &res, r)?;
            if at.is_some_and(|x| x != l) {
                bail!(usage(format!(
                    "--level {r}: the assets hold the {r}³ level at different depths (their \
                     finest resolutions differ), so it cannot be forced for the whole assembly"
                )));
            }
            at = Some(l);
        }
        settings.level = at;
    } else {
        settings.level = None;
    }
    let lights = view.lights()?;
    let camera = view.camera();
    let (img, stats) = super::render(
        asm, &camera, &lights, view.spp, view.seed, &settings, progress,
    );
    for (a, asset) in m.assets.iter().enumerate() {
        if let Some(e) = asm.scene(a).first_error() {
            bail!("asset '{}': {}: {e}", asset.id, asset.aggregate.display());
        }
    }
    if let Some((a, e)) = asm.mesh_error() {
        let (why, instead) = if asm.representation(a) == Representation::Mesh {
            (
                format!(
                    "it has at most {} triangles, so it is drawn from its mesh",
                    request.mesh_below
                ),
                "--mesh-below 0 draws it from its aggregate where it is seen coarse",
            )
        } else {
            (
                "an instance is seen finer than its aggregate's finest level".to_string(),
                "--no-mesh draws every instance from its aggregate",
            )
        };
        bail!(
            "asset '{}': its mesh is needed ({why}) but {e}; {instead}",
            m.assets[a].id
        );
    }
    let output = ImageFiles::for_output(&request.output);
    output.write(&img, request.exposure)?;
    let assets = m
        .assets
        .iter()
        .enumerate()
        .map(|(a, asset)| AssetRender {
            id: asset.id.clone(),
            levels_used: asm.scene(a).resolutions_used(),
            mesh_triangles: asm.mesh_triangles(a),
            mesh_only: asm.representation(a) == Representation::Mesh,
        })
        .collect();
    let skeleton_bytes = (0..m.assets.len())
        .map(|a| asm.scene(a).skeleton_bytes() as u64)
        .sum();
    let mut level_map = None;
    if let Some(p) = &request.level_map {
        let map = super::level_map(asm, &camera, &settings);
        let resolutions = asm.level_resolutions();
        let res_of = |f: &super::FirstHit| match f.drawn {
            super::Drawn::Level(l) => asm.scene(m.asset_of(f.instance)).grid(l).res,
            super::Drawn::Mesh => 0,
        };
        let (rgb, h, legend) =
            super::lod::level_map_picture(&map, camera.width, camera.height, &resolutions, &res_of);
        crate::film::write_rgb8_png(p, camera.width, h, &rgb)?;
        level_map = Some(LevelMapReport {
            path: p.display().to_string(),
            legend,
        });
    }
    Ok(RenderReport {
        input: path.display().to_string(),
        holds: format!(
            "{} assets, {} instances",
            m.assets.len(),
            m.instance_count()
        ),
        open_ms,
        assembly: true,
        stats,
        spp: view.spp,
        nee: settings.nee,
        assets,
        cache: BlockCache::global().stats(),
        skeleton_bytes,
        peak_memory: crate::util::process::peak_rss_line(),
        level_map,
        output,
    })
}

impl fmt::Display for RenderReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.assembly {
            writeln!(
                f,
                "input: {}: {} (opened with the instance BVH in {:.1} ms)",
                self.input, self.holds, self.open_ms
            )?;
            writeln!(f, "{}", self.stats.line("LoD"))?;
            for a in &self.assets {
                let mesh = match (a.mesh_triangles, a.mesh_only) {
                    (Some(t), true) => format!(", drawn from its mesh ({t} triangles)"),
                    (Some(t), false) => format!(", mesh loaded ({t} triangles)"),
                    (None, true) => ", drawn from its mesh (not met)".to_string(),
                    (None, false) => String::new(),
                };
                writeln!(
                    f,
                    "stats: asset '{}': levels used {:?}{mesh}",
                    a.id, a.levels_used
                )?;
            }
        } else {
            writeln!(
                f,
                "input: {}: {} (opened in {:.1} ms)",
                self.input, self.holds, self.open_ms
            )?;
            writeln!(f, "{}", self.stats.line("LoD"))?;
            let used = self
                .assets
                .first()
                .map(|a| a.levels_used.clone())
                .unwrap_or_default();
            writeln!(
                f,
                "stats: {} cones/pixel, {} light samples per shaded voxel, levels used {used:?}",
                self.spp, self.nee
            )?;
        }
        let c = &self.cache;
        writeln!(
            f,
            "stats: cache: {} blocks loaded, {} of them distinct, {} evicted, peak {} of a {} \
             budget (level skeletons {})",
            c.loaded,
            c.distinct,
            c.evicted,
            mib(c.peak),
            mib(c.budget),
            mib(self.skeleton_bytes)
        )?;
        if c.reloads() {
            writeln!(
                f,
                "note: the view's blocks did not fit the cache: each was prepared {:.1} times; \
                 --cache-mib {} (about the view's working set) prepares each once, in less time \
                 and more memory (the image is the same under any budget)",
                c.loaded as f64 / c.distinct.max(1) as f64,
                c.working_set().div_ceil(1 << 20)
            )?;
        }
        if let Some(l) = &self.peak_memory {
            writeln!(f, "{l}")?;
        }
        if let Some(m) = &self.level_map {
            writeln!(
                f,
                "level map: {} (what the cone through each pixel's centre meets first: mesh, or \
                 the aggregate's level by resolution; share of pixels): {}",
                m.path,
                m.legend.join(", ").to_lowercase()
            )?;
        }
        write!(f, "{}", self.output)
    }
}
