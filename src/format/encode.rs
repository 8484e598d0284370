//! From baked levels to FlatBuffer blobs: voxel blocks, face blocks and the index. Here the
//! bake's effect detection becomes storage: a voxel without metal stores the dielectric
//! moments, a constant visibility map stores its value and no tree, and every choice is counted
//! per level so that `aggtool inspect` can say what was kept or dropped, and why.

use flatbuffers::FlatBufferBuilder;
use glam::Vec3;

use super::fb;
use super::level::{FaceData, VoxelData};
use super::settings::RecordedSettings;
use super::{BLOCK_ID, INDEX_ID};
use crate::absdf::{MaterialMoments, Moments};
use crate::math::beta::MIN_VARIANCE;
use crate::math::haar::{quantize_tree, Node, QNode, SparseHaar};
use crate::spatial::morton3;

/// What a level stores, counted while encoding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Counts {
    /// Voxels.
    pub voxels: u64,
    /// Boundary faces.
    pub faces: u64,
    /// Voxels with directional moments (Eq. 23).
    pub directional_moments: u64,
    /// Voxels with metallic moments.
    pub metallic: u64,
    /// Voxels with a roughness variance (two microfacet lobes).
    pub roughness_variance: u64,
    /// Voxels with more than one SGGX lobe.
    pub multi_lobe: u64,
    /// Voxels with an AIV tree.
    pub aiv_trees: u64,
    /// Voxels whose AIV is 1 everywhere.
    pub aiv_all_visible: u64,
    /// Voxels whose AIV is 0 everywhere.
    pub aiv_all_occluded: u64,
    /// Faces with an ABV tree.
    pub abv_trees: u64,
    /// Voxels with cut-outs (coverage below one).
    pub cut_out: u64,
    /// AIV tree nodes.
    pub aiv_nodes: u64,
    /// ABV tree nodes.
    pub abv_nodes: u64,
    /// Voxels whose exposure is below one (format 1.1).
    pub exposure: u64,
}

impl Counts {
    /// Adds another level's or block's counts.
    pub fn add(&mut self, o: &Counts) {
        self.voxels += o.voxels;
        self.faces += o.faces;
        self.directional_moments += o.directional_moments;
        self.metallic += o.metallic;
        self.roughness_variance += o.roughness_variance;
        self.multi_lobe += o.multi_lobe;
        self.aiv_trees += o.aiv_trees;
        self.aiv_all_visible += o.aiv_all_visible;
        self.aiv_all_occluded += o.aiv_all_occluded;
        self.abv_trees += o.abv_trees;
        self.cut_out += o.cut_out;
        self.aiv_nodes += o.aiv_nodes;
        self.abv_nodes += o.abv_nodes;
        self.exposure += o.exposure;
    }

    /// The effects at least one voxel or face stores.
    pub fn effects(&self) -> fb::Effect {
        let mut e = fb::Effect::empty();
        let pairs = [
            (self.directional_moments, fb::Effect::DirectionalMoments),
            (self.metallic, fb::Effect::MetallicMoments),
            (self.roughness_variance, fb::Effect::RoughnessVariance),
            (self.multi_lobe, fb::Effect::MultiLobeNdf),
            (self.aiv_trees, fb::Effect::AivTrees),
            (self.abv_trees, fb::Effect::AbvTrees),
            (self.cut_out, fb::Effect::CutOuts),
            (self.exposure, fb::Effect::Exposure),
        ];
        for (n, f) in pairs {
            if n > 0 {
                e |= f;
            }
        }
        e
    }

    pub(crate) fn from_fb(c: &fb::LevelCounts) -> Counts {
        Counts {
            voxels: c.voxels(),
            faces: c.faces(),
            directional_moments: c.directional_moments(),
            metallic: c.metallic(),
            roughness_variance: c.roughness_variance(),
            multi_lobe: c.multi_lobe(),
            aiv_trees: c.aiv_trees(),
            aiv_all_visible: c.aiv_all_visible(),
            aiv_all_occluded: c.aiv_all_occluded(),
            abv_trees: c.abv_trees(),
            cut_out: c.cut_out(),
            aiv_nodes: c.aiv_nodes(),
            abv_nodes: c.abv_nodes(),
            exposure: c.exposure(),
        }
    }
}

/// Bytes stored per component (FlatBuffer payloads, without per-vector headers and padding).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ComponentBytes {
    /// Morton keys.
    pub keys: u64,
    /// Voxel records.
    pub voxels: u64,
    /// SGGX lobes.
    pub lobes: u64,
    /// Full material moments.
    pub moments: u64,
    /// Dielectric material moments.
    pub dielectric_moments: u64,
    /// AIV tree nodes.
    pub aiv_nodes: u64,
    /// Face records.
    pub faces: u64,
    /// ABV tree nodes.
    pub abv_nodes: u64,
    /// Exposures.
    pub exposure: u64,
}

impl ComponentBytes {
    /// Adds another block's bytes.
    pub fn add(&mut self, o: &ComponentBytes) {
        self.keys += o.keys;
        self.voxels += o.voxels;
        self.lobes += o.lobes;
        self.moments += o.moments;
        self.dielectric_moments += o.dielectric_moments;
        self.aiv_nodes += o.aiv_nodes;
        self.faces += o.faces;
        self.abv_nodes += o.abv_nodes;
        self.exposure += o.exposure;
    }
}

fn bytes_of<T>(v: &[T]) -> u64 {
    std::mem::size_of_val(v) as u64
}

pub(crate) fn v3(v: Vec3) -> fb::Vec3f {
    fb::Vec3f::new(v.x, v.y, v.z)
}

fn haar_node(n: &Node) -> fb::HaarNode {
    fb::HaarNode::new(
        n.details[0],
        n.details[1],
        n.details[2],
        n.subtree,
        n.children,
    )
}

fn qhaar_node(n: &QNode) -> fb::QHaarNode {
    fb::QHaarNode::new(n.links, n.q[0], n.q[1], n.q[2])
}

/// A block's trees, collected in both layouts until one does not fit the quantized one (a map
/// above 64²): format 1.4 stores `aiv_qnodes`/`abv_qnodes` unless `lossless` or a tree does
/// not fit, then the float `HaarNode`s for the whole block.
struct TreeNodes {
    f32: Vec<fb::HaarNode>,
    q16: Option<Vec<fb::QHaarNode>>,
}

impl TreeNodes {
    fn new(lossless: bool) -> TreeNodes {
        TreeNodes {
            f32: Vec::new(),
            q16: (!lossless).then(Vec::new),
        }
    }

    fn len(&self) -> usize {
        self.f32.len()
    }

    fn push(&mut self, t: &SparseHaar) {
        self.f32.extend(t.nodes.iter().map(haar_node));
        if let Some(q) = &mut self.q16 {
            match quantize_tree(t) {
                Some(qt) => q.extend(qt.iter().map(qhaar_node)),
                None => self.q16 = None,
            }
        }
    }

    /// Bytes of the layout stored.
    fn bytes(&self) -> u64 {
        self.q16
            .as_ref()
            .map_or(bytes_of(&self.f32), |q| bytes_of(q))
    }
}

fn has_metal(m: &MaterialMoments) -> bool {
    m.m != 0.0 || m.mf90 != 0.0 || m.ms != 0.0 || m.mc != Vec3::ZERO
}

fn full(m: &MaterialMoments) -> fb::Moments {
    fb::Moments::new(&v3(m.c), &v3(m.mc), m.s, m.ms, m.m, m.f90, m.mf90)
}

fn dielectric(m: &MaterialMoments) -> fb::DielectricMoments {
    fb::DielectricMoments::new(&v3(m.c), m.s, m.f90)
}

/// Encodes one block of voxels (sorted by key) of level `level`, adding to `counts`.
/// With `keep_all`, every voxel stores the metallic moments even without metal; with
/// `lossless`, lobes, moments and trees keep the float layout of format 1.0–1.3 instead of
/// 1.4's quantized one.
pub fn voxel_block(
    level: u32,
    voxels: &[VoxelData],
    keep_all: bool,
    lossless: bool,
    counts: &mut Counts,
    sizes: &mut ComponentBytes,
) -> Vec<u8> {
    let mut keys = Vec::with_capacity(voxels.len());
    let mut recs = Vec::with_capacity(voxels.len());
    let mut lobes = Vec::new();
    let mut moments = Vec::new();
    let mut diel = Vec::new();
    let mut nodes = TreeNodes::new(lossless);
    let mut qlobes = Vec::new();
    let mut qmoments = Vec::new();
    let mut qdiel = Vec::new();
    let mut exposure = Vec::with_capacity(voxels.len());
    for v in voxels {
        let a = &v.appearance;
        exposure.push(v.exposure);
        if v.exposure < 1.0 {
            counts.exposure += 1;
        }
        let mut flags = fb::VoxelFlags::empty();
        counts.voxels += 1;
        // Lobes.
        let lobe_start = lobes.len() as u32;
        for l in &a.lobes {
            lobes.push(fb::Lobe::new(
                l.weight,
                &v3(l.frame.x_axis),
                &v3(l.frame.y_axis),
                &v3(l.frame.z_axis),
                l.alpha.x,
                l.alpha.y,
            ));
            qlobes.push(super::quantize::qlobe(l));
        }
        if a.lobes.len() > 1 {
            counts.multi_lobe += 1;
        }
        // Moments: constant or directional, full or dielectric.
        let sets: Vec<&MaterialMoments> = match &a.moments {
            Moments::Constant(m) => vec![m],
            Moments::Directional {
                diffuse, specular, ..
            } => diffuse.iter().chain(specular.iter()).collect(),
        };
        let moment_res = match &a.moments {
            Moments::Constant(_) => 0,
            Moments::Directional { res, .. } => {
                flags |= fb::VoxelFlags::DirectionalMoments;
                counts.directional_moments += 1;
                *res
            }
        };
        let metal = keep_all || sets.iter().any(|m| has_metal(m));
        let moment_start;
        if metal {
            flags |= fb::VoxelFlags::Metallic;
            counts.metallic += 1;
            moment_start = moments.len() as u32;
            moments.extend(sets.iter().map(|m| full(m)));
            qmoments.extend(sets.iter().map(|m| super::quantize::qmoments(m)));
        } else {
            moment_start = diel.len() as u32;
            diel.extend(sets.iter().map(|m| dielectric(m)));
            qdiel.extend(sets.iter().map(|m| super::quantize::qdielectric_moments(m)));
        }
        // Roughness: the estimate stores a variance below the threshold (one microfacet lobe)
        // as exactly zero.
        let variance = a.roughness_variance;
        if variance >= MIN_VARIANCE {
            counts.roughness_variance += 1;
        }
        // Sums of sample weights round below one: count only what a cut-out would remove.
        if v.coverage < 0.999 {
            counts.cut_out += 1;
        }
        // Interior visibility.
        let aiv_start = nodes.len() as u32;
        if v.aiv.is_constant() {
            let value = v.aiv.scaling / v.aiv.n.max(1) as f32;
            if value >= 1.0 - 1e-6 {
                counts.aiv_all_visible += 1;
            } else if value <= 1e-6 {
                counts.aiv_all_occluded += 1;
            }
        } else {
            flags |= fb::VoxelFlags::AivTree;
            counts.aiv_trees += 1;
            counts.aiv_nodes += v.aiv.nodes.len() as u64;
            nodes.push(&v.aiv);
        }
        let e = &v.ellipsoid;
        keys.push(v.key);
        recs.push(fb::Voxel::new(
            v.area as f32,
            v.coverage,
            a.roughness_mean,
            variance,
            &v3(e.center),
            &v3(e.axes.x_axis),
            &v3(e.axes.y_axis),
            &v3(e.axes.z_axis),
            flags,
            lobe_start,
            a.lobes.len() as u32,
            moment_start,
            sets.len() as u32,
            moment_res,
            aiv_start,
            nodes.len() as u32 - aiv_start,
            v.aiv.scaling,
        ));
    }
    sizes.keys += bytes_of(&keys);
    sizes.voxels += bytes_of(&recs);
    if lossless {
        sizes.lobes += bytes_of(&lobes);
        sizes.moments += bytes_of(&moments);
        sizes.dielectric_moments += bytes_of(&diel);
    } else {
        sizes.lobes += bytes_of(&qlobes);
        sizes.moments += bytes_of(&qmoments);
        sizes.dielectric_moments += bytes_of(&qdiel);
    }
    sizes.aiv_nodes += nodes.bytes();
    // Only blocks with some closed surface store exposures.
    let exposure = if exposure.iter().any(|&e| e < 1.0) {
        sizes.exposure += bytes_of(&exposure);
        Some(exposure)
    } else {
        None
    };
    let mut b = FlatBufferBuilder::with_capacity(
        64 + recs.len() * 120 + lobes.len() * 48 + moments.len() * 44 + nodes.len() * 20,
    );
    let keys = b.create_vector(&keys);
    let recs = b.create_vector(&recs);
    let (lobes, qlobes) = if lossless {
        (Some(b.create_vector(&lobes)), None)
    } else {
        (None, Some(b.create_vector(&qlobes)))
    };
    let (moments, diel, qmoments, qdiel) = if lossless {
        let m = b.create_vector(&moments);
        (Some(m), Some(b.create_vector(&diel)), None, None)
    } else {
        let m = b.create_vector(&qmoments);
        (None, None, Some(m), Some(b.create_vector(&qdiel)))
    };
    let (aiv_nodes, aiv_qnodes) = match &nodes.q16 {
        Some(q) => (None, Some(b.create_vector(q))),
        None => (Some(b.create_vector(&nodes.f32)), None),
    };
    let exposure = exposure.map(|e| b.create_vector(&e));
    let root = fb::Block::create(
        &mut b,
        &fb::BlockArgs {
            level,
            keys: Some(keys),
            voxels: Some(recs),
            lobes,
            moments,
            dielectric_moments: diel,
            aiv_nodes,
            exposure,
            qlobes,
            qmoments,
            qdielectric_moments: qdiel,
            aiv_qnodes,
            ..Default::default()
        },
    );
    b.finish(root, Some(BLOCK_ID));
    b.finished_data().to_vec()
}

/// The Morton key of a face's voxel, which orders faces in a level.
pub fn face_key(f: &FaceData) -> u64 {
    morton3(glam::UVec3::new(
        f.face.voxel.0,
        f.face.voxel.1,
        f.face.voxel.2,
    ))
}

/// Encodes one block of boundary faces (sorted by [`face_key`], then direction); `lossless`
/// keeps the float trees of format 1.0–1.3.
pub fn face_block(
    level: u32,
    faces: &[FaceData],
    lossless: bool,
    counts: &mut Counts,
    sizes: &mut ComponentBytes,
) -> Vec<u8> {
    let mut recs = Vec::with_capacity(faces.len());
    let mut nodes = TreeNodes::new(lossless);
    for f in faces {
        counts.faces += 1;
        let start = nodes.len() as u32;
        if !f.abv.is_constant() {
            counts.abv_trees += 1;
            counts.abv_nodes += f.abv.nodes.len() as u64;
            nodes.push(&f.abv);
        }
        let v = f.face.voxel;
        recs.push(fb::Face::new(
            v.0,
            v.1,
            v.2,
            f.face.dir as u32,
            start,
            nodes.len() as u32 - start,
            f.abv.scaling,
        ));
    }
    sizes.faces += bytes_of(&recs);
    sizes.abv_nodes += nodes.bytes();
    let mut b = FlatBufferBuilder::with_capacity(64 + recs.len() * 28 + nodes.len() * 20);
    let recs = b.create_vector(&recs);
    let (abv_nodes, abv_qnodes) = match &nodes.q16 {
        Some(q) => (None, Some(b.create_vector(q))),
        None => (Some(b.create_vector(&nodes.f32)), None),
    };
    let root = fb::Block::create(
        &mut b,
        &fb::BlockArgs {
            level,
            faces: Some(recs),
            abv_nodes,
            abv_qnodes,
            ..Default::default()
        },
    );
    b.finish(root, Some(BLOCK_ID));
    b.finished_data().to_vec()
}

/// A level's entry in the index.
#[derive(Clone, Debug)]
pub struct LevelEntry {
    /// Voxels per axis.
    pub res: u32,
    /// The level cube's minimum corner.
    pub origin: Vec3,
    /// The cube's edge length.
    pub size: f32,
    /// Where its voxel blocks are.
    pub voxel_blocks: Vec<fb::BlobRef>,
    /// Where its face blocks are.
    pub face_blocks: Vec<fb::BlobRef>,
    /// What it stores.
    pub counts: Counts,
    /// Its voxel keys, encoded ([`super::encode_voxel_keys`]); `None` writes none.
    pub voxel_keys: Option<Vec<u8>>,
}

/// Everything the index records.
pub struct IndexEntry<'a> {
    /// The generator, e.g. "aggtool 0.1.0".
    pub generator: &'a str,
    /// The source asset's file name.
    pub source: &'a str,
    /// The source asset's bounds.
    pub bounds: (Vec3, Vec3),
    /// The bake settings.
    pub settings: &'a RecordedSettings,
    /// Version of the M1–M5 tables.
    pub tables_version: u32,
    /// CRC-32 of the tables.
    pub tables_crc32: u32,
    /// The levels, finest first.
    pub levels: &'a [LevelEntry],
}

/// Encodes the index.
pub fn index(e: &IndexEntry) -> Vec<u8> {
    let mut b = FlatBufferBuilder::with_capacity(4096);
    let settings = fb::BakeSettings::create(&mut b, &e.settings.to_fb_args());
    let mut total = Counts::default();
    let mut levels = Vec::with_capacity(e.levels.len());
    for l in e.levels {
        total.add(&l.counts);
        let c = &l.counts;
        let counts = fb::LevelCounts::create(
            &mut b,
            &fb::LevelCountsArgs {
                voxels: c.voxels,
                faces: c.faces,
                directional_moments: c.directional_moments,
                metallic: c.metallic,
                roughness_variance: c.roughness_variance,
                multi_lobe: c.multi_lobe,
                aiv_trees: c.aiv_trees,
                aiv_all_visible: c.aiv_all_visible,
                aiv_all_occluded: c.aiv_all_occluded,
                abv_trees: c.abv_trees,
                cut_out: c.cut_out,
                aiv_nodes: c.aiv_nodes,
                abv_nodes: c.abv_nodes,
                exposure: c.exposure,
            },
        );
        let vb = b.create_vector(&l.voxel_blocks);
        let fbk = b.create_vector(&l.face_blocks);
        let origin = v3(l.origin);
        let keys = l.voxel_keys.as_ref().map(|k| b.create_vector(k));
        levels.push(fb::Level::create(
            &mut b,
            &fb::LevelArgs {
                res: l.res,
                origin: Some(&origin),
                size: l.size,
                voxel_blocks: Some(vb),
                face_blocks: Some(fbk),
                counts: Some(counts),
                voxel_keys: keys,
            },
        ));
    }
    let levels = b.create_vector(&levels);
    let pca = b.create_vector::<fb::BlobRef>(&[]);
    let generator = b.create_string(e.generator);
    let source = b.create_string(e.source);
    let (lo, hi) = (v3(e.bounds.0), v3(e.bounds.1));
    let root = fb::Index::create(
        &mut b,
        &fb::IndexArgs {
            generator: Some(generator),
            source: Some(source),
            bounds_min: Some(&lo),
            bounds_max: Some(&hi),
            settings: Some(settings),
            effects_kept: total.effects(),
            tables_version: e.tables_version,
            tables_crc32: e.tables_crc32,
            levels: Some(levels),
            pca_blocks: Some(pca),
        },
    );
    b.finish(root, Some(INDEX_ID));
    b.finished_data().to_vec()
}
