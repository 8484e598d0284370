//! Reading `.agg` files: map, verify everything once on open, then read zero-copy.
//!
//! Verification covers the header (identifier, major version, checksum, size: truncated and
//! trailing data are told apart), every blob's range, alignment and CRC-32, the FlatBuffers
//! verifier on the index and on every block, and the invariants the accessors rely on (sorted
//! keys, ranges inside their arrays, well-shaped wavelet trees, finite numbers). After that,
//! accessors index without further checks that could fail, and no user file can make them
//! panic.

use std::fs::File;
use std::path::Path;

use glam::{Mat3, UVec3, Vec2, Vec3};

use super::encode::Counts;
use super::{fb, FormatError, Header, ALIGN, BLOCK_ID, HEADER_SIZE, INDEX_ID};
use crate::absdf::{MaterialMoments, Moments, NdfLobe, VoxelAppearance};
use crate::bake::boundary::{Face, UVec3Key};
use crate::bake::level::{FaceData, LevelData, VoxelData};
use crate::bake::primitive::Ellipsoid;
use crate::bake::voxelize::{demorton3, Grid};
use crate::math::haar::{eval_tree, validate_tree, Node, SparseHaar};
use crate::math::sphere_maps::{equal_area_sphere_to_square, grid_cell};

enum Backing {
    Map(memmap2::Mmap),
    Owned(Vec<u8>),
}

/// An opened, verified aggregate.
pub struct Aggregate {
    data: Backing,
    header: Header,
}

fn corrupt(s: impl Into<String>) -> FormatError {
    FormatError::Corrupt(s.into())
}

pub(crate) fn g(v: &fb::Vec3f) -> Vec3 {
    Vec3::new(v.x(), v.y(), v.z())
}

fn finite3(v: &fb::Vec3f) -> bool {
    g(v).is_finite()
}

fn node(n: &fb::HaarNode) -> Node {
    Node {
        details: [n.h(), n.v(), n.d()],
        children: n.children(),
        subtree: n.subtree(),
    }
}

fn verifier_options() -> flatbuffers::VerifierOptions {
    flatbuffers::VerifierOptions {
        max_depth: 16,
        max_tables: 1 << 24,
        max_apparent_size: 1 << 31,
        ignore_missing_null_terminator: false,
    }
}

impl Aggregate {
    /// Maps and verifies a file.
    pub fn open(path: &Path) -> Result<Aggregate, FormatError> {
        let file = File::open(path)?;
        let len = file.metadata()?.len();
        if len == 0 {
            return Err(FormatError::Truncated {
                expected: HEADER_SIZE as u64,
                actual: 0,
            });
        }
        // SAFETY: the map is read-only; the usual caveat of memory maps applies (another
        // process truncating the file while it is mapped), as for every mapped-file reader.
        let map = unsafe { memmap2::Mmap::map(&file)? };
        Self::verified(Backing::Map(map), true)
    }

    /// Verifies an in-memory file.
    pub fn from_bytes(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        Self::verified(Backing::Owned(bytes), true)
    }

    /// Verifies an in-memory file with every check but the CRC-32s: for fuzzing, where
    /// random bytes would otherwise never get past the checksums to the structural checks.
    pub fn from_bytes_ignoring_checksums(bytes: Vec<u8>) -> Result<Aggregate, FormatError> {
        Self::verified(Backing::Owned(bytes), false)
    }

    fn verified(data: Backing, checksums: bool) -> Result<Aggregate, FormatError> {
        let bytes: &[u8] = match &data {
            Backing::Map(m) => m,
            Backing::Owned(v) => v,
        };
        let header = Header::parse_with(bytes, checksums)?;
        verify(bytes, &header, checksums)?;
        Ok(Aggregate { data, header })
    }

    pub fn bytes(&self) -> &[u8] {
        match &self.data {
            Backing::Map(m) => m,
            Backing::Owned(v) => v,
        }
    }

    pub fn header(&self) -> Header {
        self.header
    }

    /// The index (verified on open).
    pub fn index(&self) -> fb::Index<'_> {
        let h = &self.header;
        let b = &self.bytes()[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
        // SAFETY: verified by `verify` on open, and the bytes are immutable since.
        unsafe { flatbuffers::root_unchecked::<fb::Index>(b) }
    }

    /// A block (verified on open).
    pub fn block(&self, r: &fb::BlobRef) -> fb::Block<'_> {
        let b = &self.bytes()[r.offset() as usize..(r.offset() + r.size()) as usize];
        // SAFETY: as for `index`: every BlobRef of the index was verified on open.
        unsafe { flatbuffers::root_unchecked::<fb::Block>(b) }
    }

    pub fn level_count(&self) -> usize {
        self.index().levels().map_or(0, |l| l.len())
    }

    /// The grid of level `l`.
    pub fn grid(&self, l: usize) -> Grid {
        let lv = self.index().levels().unwrap().get(l);
        Grid {
            origin: g(lv.origin().unwrap()),
            size: lv.size(),
            res: lv.res(),
        }
    }

    pub fn counts(&self, l: usize) -> Counts {
        let lv = self.index().levels().unwrap().get(l);
        lv.counts().map(|c| Counts::from_fb(&c)).unwrap_or_default()
    }

    fn aiv_res(&self) -> u32 {
        self.index().settings().map_or(32, |s| s.aiv_res())
    }

    fn abv_res(&self) -> u32 {
        self.index().settings().map_or(64, |s| s.abv_res())
    }

    /// The voxel with Morton key `key` at level `l`, found by binary search over the blocks'
    /// key ranges and then over the block's keys.
    pub fn find_voxel(&self, l: usize, key: u64) -> Option<VoxelRef<'_>> {
        let lv = self.index().levels()?.get(l);
        let blocks = lv.voxel_blocks()?;
        let (mut lo, mut hi) = (0usize, blocks.len());
        while lo < hi {
            let mid = (lo + hi) / 2;
            let r = blocks.get(mid);
            if r.last_key() < key {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        if lo >= blocks.len() || blocks.get(lo).first_key() > key {
            return None;
        }
        let block = self.block(blocks.get(lo));
        let keys = block.keys()?;
        let (mut a, mut b) = (0usize, keys.len());
        while a < b {
            let m = (a + b) / 2;
            if keys.get(m) < key {
                a = m + 1;
            } else {
                b = m;
            }
        }
        (a < keys.len() && keys.get(a) == key).then(|| VoxelRef {
            key,
            rec: block.voxels().unwrap().get(a),
            block,
            index: a as u32,
            aiv_res: self.aiv_res(),
        })
    }

    /// Every voxel of level `l` in Morton order.
    pub fn voxels(&self, l: usize) -> impl Iterator<Item = VoxelRef<'_>> + '_ {
        let lv = self.index().levels().unwrap().get(l);
        let aiv_res = self.aiv_res();
        lv.voxel_blocks().into_iter().flatten().flat_map(move |r| {
            let block = self.block(r);
            let keys = block.keys().unwrap();
            let recs = block.voxels().unwrap();
            (0..keys.len()).map(move |i| VoxelRef {
                key: keys.get(i),
                rec: recs.get(i),
                block,
                index: i as u32,
                aiv_res,
            })
        })
    }

    /// Decodes level `l` into memory (tests, tools; renderers read zero-copy instead).
    pub fn read_level(&self, l: usize) -> LevelData {
        let voxels = self
            .voxels(l)
            .map(|v| VoxelData {
                key: v.key,
                area: v.rec.area() as f64,
                coverage: v.rec.coverage(),
                appearance: v.appearance(),
                ellipsoid: v.ellipsoid(),
                aiv: v.aiv_tree(),
                exposure: v.exposure(),
            })
            .collect();
        let lv = self.index().levels().unwrap().get(l);
        let abv_res = self.abv_res();
        let mut faces = Vec::new();
        for r in lv.face_blocks().into_iter().flatten() {
            let block = self.block(r);
            let nodes = block.abv_nodes().unwrap();
            for f in block.faces().unwrap() {
                let s = f.abv_start() as usize;
                faces.push(FaceData {
                    face: Face {
                        voxel: UVec3Key(f.x(), f.y(), f.z()),
                        dir: f.dir() as u8,
                    },
                    abv: SparseHaar {
                        n: abv_res,
                        scaling: f.abv_scaling(),
                        nodes: (s..s + f.abv_count() as usize)
                            .map(|i| node(nodes.get(i)))
                            .collect(),
                    },
                });
            }
        }
        LevelData {
            grid: self.grid(l),
            voxels,
            faces,
            rays: 0,
        }
    }
}

/// A voxel record inside its block, read zero-copy.
#[derive(Clone, Copy)]
pub struct VoxelRef<'a> {
    pub key: u64,
    pub rec: &'a fb::Voxel,
    block: fb::Block<'a>,
    /// Position in the block.
    index: u32,
    aiv_res: u32,
}

impl<'a> VoxelRef<'a> {
    /// The exposure η in [1/16, 1] (format 1.1; 1 where the block stores none).
    pub fn exposure(&self) -> f32 {
        self.block
            .exposure()
            .map_or(1.0, |e| e.get(self.index as usize))
    }

    pub fn coords(&self) -> UVec3 {
        demorton3(self.key)
    }

    pub fn ellipsoid(&self) -> Ellipsoid {
        let r = self.rec;
        Ellipsoid {
            center: g(r.center()),
            axes: Mat3::from_cols(g(r.axis_x()), g(r.axis_y()), g(r.axis_z())),
        }
    }

    /// The interior visibility towards `d` (unit), walking one path of the tree.
    #[inline]
    pub fn aiv(&self, d: Vec3) -> f32 {
        let r = self.rec;
        let n = self.aiv_res;
        let scaling = r.aiv_scaling();
        if r.aiv_count() == 0 {
            return (scaling / n.max(1) as f32).clamp(0.0, 1.0);
        }
        let cell = grid_cell(equal_area_sphere_to_square(d), n);
        let nodes = self.block.aiv_nodes().unwrap();
        let start = r.aiv_start() as usize;
        eval_tree(
            n,
            scaling,
            r.aiv_count() as usize,
            |i| node(nodes.get(start + i)),
            cell % n,
            cell / n,
        )
        // A visibility: truncated wavelets may ring slightly outside [0, 1].
        .clamp(0.0, 1.0)
    }

    pub fn aiv_tree(&self) -> SparseHaar {
        let r = self.rec;
        let nodes = self.block.aiv_nodes().unwrap();
        let s = r.aiv_start() as usize;
        SparseHaar {
            n: self.aiv_res,
            scaling: r.aiv_scaling(),
            nodes: (s..s + r.aiv_count() as usize)
                .map(|i| node(nodes.get(i)))
                .collect(),
        }
    }

    /// The ABSDF inputs.
    pub fn appearance(&self) -> VoxelAppearance {
        let r = self.rec;
        let lobes = self.block.lobes().unwrap();
        let lobes = (r.lobe_start()..r.lobe_start() + r.lobe_count())
            .map(|i| {
                let l = lobes.get(i as usize);
                NdfLobe {
                    weight: l.weight(),
                    frame: Mat3::from_cols(g(l.t()), g(l.b()), g(l.n())),
                    alpha: Vec2::new(l.alpha_x(), l.alpha_y()),
                }
            })
            .collect();
        let range = r.moment_start() as usize..(r.moment_start() + r.moment_count()) as usize;
        let sets: Vec<MaterialMoments> = if r.flags().contains(fb::VoxelFlags::Metallic) {
            let m = self.block.moments().unwrap();
            range
                .map(|i| {
                    let x = m.get(i);
                    MaterialMoments {
                        c: g(x.base()),
                        mc: g(x.metal_base()),
                        s: x.specular(),
                        ms: x.metal_specular(),
                        m: x.metallic(),
                        f90: x.f90(),
                        mf90: x.metal_f90(),
                    }
                })
                .collect()
        } else {
            let m = self.block.dielectric_moments().unwrap();
            range
                .map(|i| {
                    let x = m.get(i);
                    MaterialMoments {
                        c: g(x.base()),
                        s: x.specular(),
                        f90: x.f90(),
                        ..Default::default()
                    }
                })
                .collect()
        };
        let moments = if r.flags().contains(fb::VoxelFlags::DirectionalMoments) {
            let cells = (r.moment_res() * r.moment_res()) as usize;
            Moments::Directional {
                res: r.moment_res(),
                diffuse: sets[..cells].to_vec(),
                specular: sets[cells..].to_vec(),
            }
        } else {
            Moments::Constant(sets[0])
        };
        VoxelAppearance {
            lobes,
            roughness_mean: r.roughness_mean(),
            roughness_variance: r.roughness_variance(),
            moments,
        }
    }
}

/// Verifies the index and every block of `data`.
fn verify(data: &[u8], h: &Header, checksums: bool) -> Result<(), FormatError> {
    let index_bytes = &data[h.index_offset as usize..(h.index_offset + h.index_size) as usize];
    if h.index_offset % ALIGN != 0 {
        return Err(corrupt("index not aligned"));
    }
    if checksums && crc32fast::hash(index_bytes) != h.index_crc32 {
        return Err(corrupt("index checksum mismatch"));
    }
    if !has_identifier(index_bytes, INDEX_ID) {
        return Err(corrupt("index has the wrong identifier"));
    }
    let opts = verifier_options();
    let index = flatbuffers::root_with_opts::<fb::Index>(&opts, index_bytes)
        .map_err(|e| corrupt(format!("index: {e}")))?;
    let settings = index
        .settings()
        .ok_or_else(|| corrupt("no bake settings"))?;
    let (aiv_res, abv_res) = (settings.aiv_res(), settings.abv_res());
    for (what, n) in [("aiv_res", aiv_res), ("abv_res", abv_res)] {
        if !n.is_power_of_two() || n > 1024 {
            return Err(corrupt(format!(
                "{what} {n} is not a power of two up to 1024"
            )));
        }
    }
    let levels = index.levels().ok_or_else(|| corrupt("no level table"))?;
    // Every blob in order, for the overlap check.
    let mut ranges: Vec<(u64, u64)> = Vec::new();
    for (li, lv) in levels.iter().enumerate() {
        let res = lv.res();
        if !res.is_power_of_two() || res > 1 << 20 {
            return Err(corrupt(format!("level {li}: resolution {res}")));
        }
        let origin = lv
            .origin()
            .ok_or_else(|| corrupt(format!("level {li}: no origin")))?;
        if !finite3(origin) || !(lv.size() > 0.0 && lv.size().is_finite()) {
            return Err(corrupt(format!("level {li}: bad extent")));
        }
        let mut voxels = 0u64;
        let mut prev_last: Option<u64> = None;
        for r in lv.voxel_blocks().into_iter().flatten() {
            let block = check_blob(data, h, r, &opts, &mut ranges, checksums)?;
            voxels += check_voxel_block(&block, r, li as u32, res, aiv_res)?;
            if prev_last.is_some_and(|p| p >= r.first_key()) {
                return Err(corrupt(format!("level {li}: voxel blocks out of order")));
            }
            prev_last = Some(r.last_key());
        }
        let mut faces = 0u64;
        for r in lv.face_blocks().into_iter().flatten() {
            let block = check_blob(data, h, r, &opts, &mut ranges, checksums)?;
            faces += check_face_block(&block, r, li as u32, res, abv_res)?;
        }
        if let Some(c) = lv.counts() {
            if c.voxels() != voxels || c.faces() != faces {
                return Err(corrupt(format!(
                    "level {li}: counts disagree with its blocks"
                )));
            }
        }
    }
    for r in index.pca_blocks().into_iter().flatten() {
        check_range(h, r, &mut ranges)?;
    }
    // Blobs must not overlap, and the gaps between them (alignment padding) must be zeros,
    // so that no byte of the file goes unchecked.
    ranges.push((h.index_offset, h.index_offset + h.index_size));
    ranges.sort_unstable();
    let mut end = HEADER_SIZE as u64;
    for (a, b) in ranges {
        if a < end {
            return Err(corrupt("blobs overlap"));
        }
        if data[end as usize..a as usize].iter().any(|&x| x != 0) {
            return Err(corrupt(format!("non-zero padding at {end}")));
        }
        end = b;
    }
    Ok(())
}

fn check_range(
    h: &Header,
    r: &fb::BlobRef,
    ranges: &mut Vec<(u64, u64)>,
) -> Result<(), FormatError> {
    let end = r.offset().checked_add(r.size());
    if r.offset() < HEADER_SIZE as u64
        || r.offset() % ALIGN != 0
        || end.is_none_or(|e| e > h.index_offset)
    {
        return Err(corrupt(format!(
            "blob at {}+{} out of range",
            r.offset(),
            r.size()
        )));
    }
    ranges.push((r.offset(), r.offset() + r.size()));
    Ok(())
}

/// Whether a FlatBuffer blob carries this file identifier; false for one too short to hold an
/// identifier (flatbuffers asserts on those).
fn has_identifier(b: &[u8], id: &str) -> bool {
    b.len() >= flatbuffers::SIZE_UOFFSET + flatbuffers::FILE_IDENTIFIER_LENGTH
        && flatbuffers::buffer_has_identifier(b, id, false)
}

fn check_blob<'a>(
    data: &'a [u8],
    h: &Header,
    r: &fb::BlobRef,
    opts: &flatbuffers::VerifierOptions,
    ranges: &mut Vec<(u64, u64)>,
    checksums: bool,
) -> Result<fb::Block<'a>, FormatError> {
    check_range(h, r, ranges)?;
    let b = &data[r.offset() as usize..(r.offset() + r.size()) as usize];
    if checksums && crc32fast::hash(b) != r.crc32() {
        return Err(corrupt(format!(
            "block at {}: checksum mismatch",
            r.offset()
        )));
    }
    if !has_identifier(b, BLOCK_ID) {
        return Err(corrupt(format!(
            "block at {}: wrong identifier",
            r.offset()
        )));
    }
    flatbuffers::root_with_opts::<fb::Block>(opts, b)
        .map_err(|e| corrupt(format!("block at {}: {e}", r.offset())))
}

fn check_voxel_block(
    b: &fb::Block,
    r: &fb::BlobRef,
    level: u32,
    res: u32,
    aiv_res: u32,
) -> Result<u64, FormatError> {
    let at = r.offset();
    let err = |s: &str| corrupt(format!("voxel block at {at}: {s}"));
    if b.level() != level {
        return Err(err("belongs to another level"));
    }
    let (Some(keys), Some(recs), Some(lobes), Some(moments), Some(diel), Some(nodes)) = (
        b.keys(),
        b.voxels(),
        b.lobes(),
        b.moments(),
        b.dielectric_moments(),
        b.aiv_nodes(),
    ) else {
        return Err(err("missing arrays"));
    };
    let n = keys.len();
    if recs.len() != n || n as u64 != r.count() as u64 || n == 0 {
        return Err(err("voxel count mismatch"));
    }
    if keys.get(0) != r.first_key() || keys.get(n - 1) != r.last_key() {
        return Err(err("key range mismatch"));
    }
    if let Some(e) = b.exposure() {
        if e.len() != n || e.iter().any(|x| !(0.0625..=1.0).contains(&x)) {
            return Err(err("exposure not one value in [1/16, 1] per voxel"));
        }
    }
    for i in 0..n {
        let k = keys.get(i);
        if i > 0 && keys.get(i - 1) >= k {
            return Err(err("keys not ascending"));
        }
        let c = demorton3(k);
        if k >> 63 != 0 || c.max_element() >= res {
            return Err(err("key outside the level"));
        }
        let v = recs.get(i);
        let floats_ok = [
            v.area(),
            v.coverage(),
            v.roughness_mean(),
            v.roughness_variance(),
            v.aiv_scaling(),
        ]
        .iter()
        .all(|x| x.is_finite())
            && [v.center(), v.axis_x(), v.axis_y(), v.axis_z()]
                .iter()
                .all(|x| finite3(x));
        if !floats_ok {
            return Err(err("non-finite voxel field"));
        }
        let lobe_end = v.lobe_start() as u64 + v.lobe_count() as u64;
        if v.lobe_count() == 0 || v.lobe_count() > 16 || lobe_end > lobes.len() as u64 {
            return Err(err("lobe range"));
        }
        for j in v.lobe_start()..lobe_end as u32 {
            let l = lobes.get(j as usize);
            if ![l.weight(), l.alpha_x(), l.alpha_y()]
                .iter()
                .all(|x| x.is_finite())
                || ![l.t(), l.b(), l.n()].iter().all(|x| finite3(x))
            {
                return Err(err("non-finite lobe"));
            }
        }
        let directional = v.flags().contains(fb::VoxelFlags::DirectionalMoments);
        let mres = v.moment_res() as u64;
        let expected = if directional {
            if mres == 0 || mres > 64 {
                return Err(err("moment resolution"));
            }
            2 * mres * mres
        } else {
            1
        };
        let mend = v.moment_start() as u64 + v.moment_count() as u64;
        let metal = v.flags().contains(fb::VoxelFlags::Metallic);
        let avail = if metal { moments.len() } else { diel.len() } as u64;
        if v.moment_count() as u64 != expected || mend > avail {
            return Err(err("moment range"));
        }
        for j in v.moment_start() as usize..mend as usize {
            let ok = if metal {
                let m = moments.get(j);
                finite3(m.base())
                    && finite3(m.metal_base())
                    && [
                        m.specular(),
                        m.metal_specular(),
                        m.metallic(),
                        m.f90(),
                        m.metal_f90(),
                    ]
                    .iter()
                    .all(|x| x.is_finite())
            } else {
                let m = diel.get(j);
                finite3(m.base()) && m.specular().is_finite() && m.f90().is_finite()
            };
            if !ok {
                return Err(err("non-finite moments"));
            }
        }
        let tree = v.flags().contains(fb::VoxelFlags::AivTree);
        let aend = v.aiv_start() as u64 + v.aiv_count() as u64;
        if aend > nodes.len() as u64 || (tree != (v.aiv_count() > 0)) {
            return Err(err("AIV range"));
        }
        let s = v.aiv_start() as usize;
        validate_tree(aiv_res, v.aiv_count() as usize, |j| node(nodes.get(s + j)))
            .map_err(|e| err(&format!("AIV tree: {e}")))?;
    }
    Ok(n as u64)
}

fn check_face_block(
    b: &fb::Block,
    r: &fb::BlobRef,
    level: u32,
    res: u32,
    abv_res: u32,
) -> Result<u64, FormatError> {
    let at = r.offset();
    let err = |s: &str| corrupt(format!("face block at {at}: {s}"));
    if b.level() != level {
        return Err(err("belongs to another level"));
    }
    let (Some(faces), Some(nodes)) = (b.faces(), b.abv_nodes()) else {
        return Err(err("missing arrays"));
    };
    if faces.len() as u64 != r.count() as u64 {
        return Err(err("face count mismatch"));
    }
    for f in faces.iter() {
        if f.x() >= res || f.y() >= res || f.z() >= res || f.dir() >= 6 {
            return Err(err("face outside the level"));
        }
        if !f.abv_scaling().is_finite() {
            return Err(err("non-finite ABV"));
        }
        let end = f.abv_start() as u64 + f.abv_count() as u64;
        if end > nodes.len() as u64 {
            return Err(err("ABV range"));
        }
        let s = f.abv_start() as usize;
        validate_tree(abv_res, f.abv_count() as usize, |j| node(nodes.get(s + j)))
            .map_err(|e| err(&format!("ABV tree: {e}")))?;
    }
    Ok(faces.len() as u64)
}

/// Reads everything a renderer or tool would read from a verified file (every voxel's
/// appearance, ellipsoid and visibility in a few directions, every face, lookups by key):
/// used by the fuzz target and the tests to show that a file that passed verification cannot
/// make an accessor panic.
pub fn exercise(agg: &Aggregate) -> usize {
    let dirs = [Vec3::X, Vec3::NEG_Y, Vec3::new(0.48, 0.6, -0.64)];
    let mut n = 0;
    for l in 0..agg.level_count() {
        let _ = agg.grid(l);
        let _ = agg.counts(l);
        for v in agg.voxels(l) {
            let _ = v.appearance();
            let _ = v.ellipsoid();
            for d in dirs {
                let _ = v.aiv(d);
            }
            let _ = agg.find_voxel(l, v.key);
            n += 1;
        }
        let _ = agg.find_voxel(l, 12345);
        n += agg.read_level(l).faces.len();
    }
    n
}
